"""Poses for the arm's kinematic calibration: many arm configurations that show the wrist camera the table board,
chosen to identify the arm's geometry, checked before anything moves.

Candidates: the camera looks at a point of the board (within `radius`) from `standoff_min..standoff_max`, tilted up
to `tilt` from the board's normal, turned anywhere about its line of sight; the flange pose that puts it there is
solved on every branch of the UR's closed-form inverse whose elbow stays up (a table-friendly pose), within the
joint limits and the reach, every joint clear of the table. From them, the plan takes the poses one at a time that
add the most information about the identifiable deviations (greedy D-optimal: the largest det(I + J M^-1 J^T) of a
pose's 6 x p Jacobian J against the information M so far). The held-out verification poses are the candidates
farthest in joint space from the chosen ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from geometry import ur
from geometry.kinematic_table import KinematicTable, pose_error
from geometry.transforms import inverse, look_at

from calibration.errors import CalibrationInputError
from calibration.models.arm_kinematics import budget_scales

CLEARANCE_M = 0.08  # every joint's origin stays this far above the table
VIEW_SIGMA = np.array([2e-5, 2e-5, 5e-5, 5e-5, 5e-5, 2e-5])  # a view's pose precision (planning): rad x, y, z; m x,y,z
BRANCHES = [ur.Branch(s, e, w) for s in (-1, 1) for e in (-1, 1) for w in (1, -1)]


@dataclass(frozen=True)
class ArmRegion:
    target: np.ndarray  # the board's rough centre (base frame, m)
    standoff: tuple[float, float]
    radius: float
    tilt: float  # rad
    mount_guess: np.ndarray  # T_flange_camera, roughly
    board_guess: np.ndarray  # T_base_board, roughly (for the views and the Jacobian)
    focal_px: float
    image_size: tuple[int, int]
    board_corners: np.ndarray  # (n, 3) the board's corners (board frame)
    home: np.ndarray


@dataclass
class Candidate:
    joints: np.ndarray
    T_base_flange: np.ndarray


def _camera_pose(region: ArmRegion, u: np.ndarray) -> np.ndarray:
    """T_base_camera of one low-discrepancy draw u in [0, 1)^5."""
    angle, r = 2 * math.pi * u[0], region.radius * math.sqrt(u[1])
    aim = region.target + np.array([r * math.cos(angle), r * math.sin(angle), 0.0])
    tilt, azimuth = region.tilt * math.sqrt(u[2]), 2 * math.pi * u[3]
    direction = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)])
    distance = region.standoff[0] + u[4] * (region.standoff[1] - region.standoff[0])
    eye = aim + distance * direction
    T = inverse(look_at(eye, aim, right=(0.0, -1.0, 0.0)))  # T_base_camera, image right along -y first
    roll = Rotation.from_rotvec([0.0, 0.0, 2 * math.pi * u[5]]).as_matrix() if len(u) > 5 else np.eye(3)
    T[:3, :3] = T[:3, :3] @ roll
    return T


def _shows_board(region: ArmRegion, T_base_camera: np.ndarray) -> bool:
    T = inverse(T_base_camera) @ region.board_guess
    p = region.board_corners @ T[:3, :3].T + T[:3, 3]
    if np.any(p[:, 2] < 0.05):
        return False
    w, h = region.image_size
    u = region.focal_px * p[:, 0] / p[:, 2] + (w - 1) / 2
    v = region.focal_px * p[:, 1] / p[:, 2] + (h - 1) / 2
    inside = (u > 0.03 * w) & (u < 0.97 * w) & (v > 0.03 * h) & (v < 0.97 * h)
    return bool(np.mean(inside) > 0.6)


def _clear(q: np.ndarray, reach: float) -> bool:
    """Every joint origin above the table, the elbow up (above the shoulder-wrist line), the wrist within reach."""
    T = np.eye(4)
    origins = []
    for value, row in zip(q, ur.UR5E_DH):
        T = T @ ur.dh_matrix(value, *row)
        origins.append(T[:3, 3].copy())
    if min(o[2] for o in origins[1:]) < CLEARANCE_M:
        return False
    shoulder, elbow, wrist = np.array([0.0, 0.0, ur.UR5E_DH[0][1]]), origins[1], origins[3]
    along = np.clip(np.dot(elbow - shoulder, wrist - shoulder) / max(np.dot(wrist - shoulder, wrist - shoulder), 1e-12),
                    0, 1)
    if elbow[2] < shoulder[2] + along * (wrist[2] - shoulder[2]):
        return False
    return float(np.linalg.norm(origins[-1] - shoulder)) < reach


def candidates(region: ArmRegion, table: KinematicTable, count: int, seed: int, reach: float = 0.85) -> list[Candidate]:
    """Up to `count` reachable, table-clear configurations that show the board (module docstring)."""
    draws = qmc.Halton(6, scramble=True, seed=seed).random(count * 6)
    out: list[Candidate] = []
    for k, u in enumerate(draws):
        T_camera = _camera_pose(region, u)
        if not _shows_board(region, T_camera):
            continue
        T_flange = T_camera @ inverse(region.mount_guess)
        branch = BRANCHES[k % len(BRANCHES)]  # each draw tries one branch: the pool mixes them evenly
        try:
            q = ur.inverse(T_flange, branch, near=region.home)
        except ur.Unreachable:
            continue
        if table.within_limits(q) is not None or not _clear(q, reach):
            continue
        out.append(Candidate(q, T_flange))
        if len(out) >= count:
            break
    return out


def pose_jacobians(cands: list[Candidate], table: KinematicTable, region: ArmRegion, free: np.ndarray) -> np.ndarray:
    """(n, 6, p): how each candidate's camera pose in the board frame moves with X, Y (6 each) and the free
    deviations (each over its budget), in units of a view's precision."""
    Q = np.array([c.joints for c in cands])
    X, Y = region.mount_guess, region.board_guess
    base = inverse(Y)[None] @ table.forward_batch(Q) @ X
    cols = []
    steps = [("X", i) for i in range(6)] + [("Y", i) for i in range(6)] + [("k", i) for i in np.flatnonzero(free)]
    scales = budget_scales(table)
    for kind, i in steps:
        h = 1e-6
        if kind == "k":
            v = table.vector()
            v[i] += h * scales[i]
            T = inverse(Y)[None] @ table.with_vector(v).forward_batch(Q) @ X
        else:
            d = np.zeros(6)
            d[i] = h
            M = np.eye(4)
            M[:3, :3] = Rotation.from_rotvec(d[:3]).as_matrix()
            M[:3, 3] = d[3:]
            T = (inverse(Y)[None] @ table.forward_batch(Q) @ X @ M if kind == "X"
                 else inverse(Y @ M)[None] @ table.forward_batch(Q) @ X)
        e = np.array([np.r_[pose_error(b, t)[3:], pose_error(b, t)[:3]] for b, t in zip(base, T)]) / h
        cols.append(e / VIEW_SIGMA)
    return np.stack(cols, axis=2)


def choose(J: np.ndarray, n: int) -> list[int]:
    """Greedy D-optimal choice of n candidates (module docstring)."""
    p = J.shape[2]
    M = 1e-6 * np.eye(p)
    chosen: list[int] = []
    for _ in range(min(n, len(J))):
        Minv = np.linalg.inv(M)
        gains = np.array([np.linalg.slogdet(np.eye(6) + Jk @ Minv @ Jk.T)[1] for Jk in J])
        gains[chosen] = -np.inf
        k = int(np.argmax(gains))
        chosen.append(k)
        M = M + J[k].T @ J[k]
    return chosen


def farthest(cands: list[Candidate], chosen: list[int], n: int) -> list[int]:
    """n candidates not chosen, each the farthest in joint space (largest joint difference) from those taken."""
    Q = np.array([c.joints for c in cands])
    taken = list(chosen)
    out: list[int] = []
    for _ in range(n):
        d = np.min(np.max(np.abs(Q[:, None, :] - Q[None, taken, :]), axis=2), axis=1)
        d[taken] = -1
        k = int(np.argmax(d))
        if d[k] <= 0:
            break
        out.append(k)
        taken.append(k)
    return out


def tour(cands: list[Candidate], indices: list[int], start: np.ndarray) -> list[int]:
    """The indices in nearest-neighbour order from `start` (joint travel: the largest joint change)."""
    left, here, out = list(indices), np.asarray(start, dtype=float), []
    while left:
        k = min(left, key=lambda i: float(np.max(np.abs(cands[i].joints - here))))
        out.append(k)
        left.remove(k)
        here = cands[k].joints
    return out


WIDE_TURN_DEG = 30.0  # a joint that turns less than this across the poses is named in a refusal


def refuse_unidentifiable(missing: list[str], Q: np.ndarray, table: KinematicTable, widen: str) -> None:
    """CalibrationInputError naming the deviations `missing` these poses (joints Q) leave unidentified, the joints
    that hardly turn across them, and what to widen (`widen`: the region's parameters, in words)."""
    if not missing:
        return
    spread = np.degrees(Q.max(axis=0) - Q.min(axis=0))
    still = [f"{j.name} ({s:.0f} deg)" for j, s in zip(table.joints, spread) if s < WIDE_TURN_DEG]
    motion = (f"the joints {', '.join(still)} turn less than {WIDE_TURN_DEG:g} deg across the poses"
              if still else "the poses turn the arm too little")
    raise CalibrationInputError(f"these poses cannot identify {', '.join(missing)}: {motion}; widen {widen}, or ask "
                                "for more poses")


def check_enough(cands: list[Candidate], wanted: int) -> None:
    if len(cands) < wanted:
        raise CalibrationInputError(f"the region gives only {len(cands)} reachable poses that show the board, fewer "
                                    f"than the {wanted} asked for: widen standoff_mm, radius_mm or tilt_deg, or "
                                    "ask for fewer poses")
