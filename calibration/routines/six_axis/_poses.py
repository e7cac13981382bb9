"""Poses for a hand-eye calibration, planned from a region the engineer gives, checked before anything moves.

Eye-in-hand: the camera looks at the board's rough centre (shifted within `radius_mm`) from `standoff_mm` away
(+/- `depth_mm`),
its viewing direction tilted up to `tilt_deg` from the board's normal, turned up to `roll_deg` about it.
Eye-to-hand: the flange's board is held within `radius_mm` of a point in front of the fixed camera (nearer or
farther by up to `depth_mm`), facing it,
tilted up to `tilt_deg`, turned up to `roll_deg`. Candidates come from a scrambled Halton sequence (even cover of
the region, deterministic for a plan seed); each must be reachable by the arm's nominal inverse kinematics on the
branch of its home configuration, within its joint limits and reach, clear of the table, and must show the board
to the camera as the engineer's rough mount and lens predict. From those, the calibration poses are chosen far
apart in orientation (greedy max-min), and their rotation axes must spread (models.hand_eye.check_motion); the
held-out verification poses are the next most distant ones.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from geometry import ur
from geometry.transforms import inverse, look_at

from calibration.errors import CalibrationInputError
from calibration.models.hand_eye import check_motion

CANDIDATES_PER_POSE = 40
MIN_CLEARANCE_M = 0.05  # the flange and the camera stay this far above the board's plane
SHOWN_FRACTION = 0.8  # of the board's central disc that must fall in the image


@dataclass(frozen=True)
class Region:
    """What the engineer says of the cell and where to calibrate (base frame, m and rad)."""

    mount: str  # eye-in-hand | eye-to-hand
    target: np.ndarray  # eye-in-hand: the board's rough centre; eye-to-hand: where to hold the flange's board
    standoff: float  # eye-in-hand: camera to board
    depth: float  # the camera's distance (eye-in-hand) or the board's (eye-to-hand) varies by up to +/- this
    radius: float
    tilt: float
    roll: float
    mount_guess: np.ndarray  # T_flange_camera (eye-in-hand) or T_flange_board centre (eye-to-hand), roughly
    camera_guess: np.ndarray | None  # eye-to-hand: the fixed camera's rough position
    focal_px: float
    image_size: tuple[int, int]
    board_radius: float  # half the board's shorter side
    home: np.ndarray  # joints (rad) whose branch the plan keeps


@dataclass
class PlannedPose:
    name: str
    set: str  # cal | ver
    joints: np.ndarray  # rad
    T_base_flange: np.ndarray  # nominal


@dataclass
class PosePlan:
    poses: list[PlannedPose]
    motion: dict  # check_motion of the calibration poses: max_angle_deg, spread, ...
    candidates: int
    refused: Counter = field(default_factory=Counter)  # reason -> candidates refused for it

    def table(self) -> dict:
        rows = []
        for p in self.poses:
            t = p.T_base_flange[:3, 3] * 1e3
            rv = np.degrees(Rotation.from_matrix(p.T_base_flange[:3, :3]).as_rotvec())
            rows.append([p.name, p.set, *[round(float(v), 1) for v in t], *[round(float(v), 1) for v in rv],
                         *[round(float(v), 1) for v in np.degrees(p.joints)]])
        return {"title": "Planned poses (flange in the base frame, nominal)",
                "columns": ["pose", "set", "x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg",
                            *[f"j{i}_deg" for i in range(1, 7)]],
                "rows": rows,
                "note": f"rotation-axis spread {self.motion['spread']:.2f} (0: all about one axis, 1: even in "
                        f"every direction), largest rotation between poses {self.motion['max_angle_deg']:.1f} deg; "
                        f"{len(self.poses)} of {self.candidates} candidates used"}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _frame(z_axis, roll: float) -> np.ndarray:
    """A rotation whose z axis is `z_axis`, its x axis as near the base's x as can be, then turned by `roll` about z
    (the same x for every tilt: the turn between two poses is their roll and tilt, not where they tilt toward)."""
    z = _unit(z_axis)
    x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = _unit(x - (x @ z) * z)
    R = np.column_stack([x, np.cross(z, x), z])
    return R @ Rotation.from_euler("z", roll).as_matrix()


def _tilted(axis, tilt: float, azimuth: float) -> np.ndarray:
    """`axis` tilted by `tilt` toward the direction at `azimuth` around it."""
    R = _frame(axis, 0.0)
    return R @ np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)])


class Planner:
    def __init__(self, region: Region):
        self.r = region
        self.branch = ur.branch_of(region.home)
        w, h = region.image_size
        self.K = np.array([[region.focal_px, 0, (w - 1) / 2], [0, region.focal_px, (h - 1) / 2], [0, 0, 1]])
        if region.mount == "eye-to-hand":
            if region.camera_guess is None:
                raise CalibrationInputError("camera_mm: eye-to-hand needs the fixed camera's rough position "
                                            "(base frame, mm)")
            self.T_base_camera = inverse(look_at(region.camera_guess, region.target))

    def candidate(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(T_base_flange, T_base_camera, board centre) of a point u in [0, 1)^6 of the region.

        The distance varies too: from one distance alone, the camera's offset along its line of sight, its focal
        length and the board's printed scale explain the images equally well."""
        r = self.r
        azimuth, tilt = 2 * math.pi * u[0], r.tilt * math.sqrt(u[1])
        roll = r.roll * (2 * u[2] - 1)
        rho, phi = r.radius * math.sqrt(u[3]), 2 * math.pi * u[4]
        nearer = r.depth * (2 * u[5] - 1)
        if r.mount == "eye-in-hand":
            aim = r.target + rho * np.array([math.cos(phi), math.sin(phi), 0.0])
            up = _tilted([0.0, 0.0, 1.0], tilt, azimuth)
            T_base_camera = np.eye(4)
            T_base_camera[:3, :3] = _frame(-up, roll)
            T_base_camera[:3, 3] = aim + (r.standoff + nearer) * up
            return T_base_camera @ inverse(r.mount_guess), T_base_camera, r.target
        toward = _unit(r.target - r.camera_guess)  # from the camera to where the board is shown
        side = _frame(toward, 0.0)
        centre = r.target + side[:, :2] @ (rho * np.array([math.cos(phi), math.sin(phi)])) + nearer * toward
        T_base_board = np.eye(4)
        T_base_board[:3, :3] = _frame(_tilted(_unit(centre - r.camera_guess), tilt, azimuth), roll)
        T_base_board[:3, 3] = centre
        return T_base_board @ inverse(r.mount_guess), self.T_base_camera, centre

    def check(self, T_base_flange, T_base_camera, centre) -> tuple[np.ndarray | None, str | None]:
        """The joints reaching T_base_flange, or why the candidate is refused."""
        try:
            q = ur.inverse(T_base_flange, self.branch, near=self.r.home)
        except ur.Unreachable:
            return None, "out of reach"
        if np.any(np.abs(q) > 2 * math.pi):
            return None, "outside the joint limits"
        shoulder = np.array([0.0, 0.0, ur.UR5E_DH[0][1]])
        if np.linalg.norm(T_base_flange[:3, 3] - shoulder) > 0.85:
            return None, "beyond the arm's reach"
        floor = self.r.target[2] + MIN_CLEARANCE_M if self.r.mount == "eye-in-hand" else -math.inf
        if min(T_base_flange[2, 3], T_base_camera[2, 3]) < floor:
            return None, "too close to the board's plane"
        if self.shown(T_base_camera, centre, T_base_flange) < SHOWN_FRACTION:
            return None, "board not in view"
        return q, None

    def shown(self, T_base_camera, centre, T_base_flange) -> float:
        """The fraction of a disc of the board's half-size around its centre that falls in the image (the board
        facing the camera; for eye-in-hand, in the table's plane)."""
        angles = np.linspace(0, 2 * math.pi, 16, endpoint=False)
        rim = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)]) * self.r.board_radius
        if self.r.mount == "eye-in-hand":
            points = centre + rim
        else:
            R = (T_base_flange @ self.r.mount_guess)[:3, :3]
            points = centre + rim @ R.T
        pc = (points - T_base_camera[:3, 3]) @ T_base_camera[:3, :3]
        if np.any(pc[:, 2] <= 0):
            return 0.0
        uv = pc[:, :2] / pc[:, 2:] * self.r.focal_px + self.K[:2, 2]
        w, h = self.r.image_size
        return float(np.mean((uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)))


def plan_poses(region: Region, n_cal: int, n_ver: int, seed: int = 0) -> PosePlan:
    """The calibration and verification poses, or CalibrationInputError naming why the region cannot give them."""
    planner = Planner(region)
    n = (n_cal + n_ver) * CANDIDATES_PER_POSE
    points = qmc.Halton(d=6, scramble=True, seed=seed).random(n)
    feasible, refused = [], Counter()
    for u in points:
        T, T_cam, centre = planner.candidate(u)
        q, why = planner.check(T, T_cam, centre)
        if why:
            refused[why] += 1
        else:
            feasible.append((q, T))
    if len(feasible) < n_cal + n_ver:
        reasons = ", ".join(f"{k} {v}" for k, v in refused.most_common())
        raise CalibrationInputError(
            f"the region gives {len(feasible)} usable poses of {n} tried, fewer than the {n_cal + n_ver} asked "
            f"(refused: {reasons}); move target_mm nearer the arm, shrink radius_mm or tilt_deg, or change "
            "standoff_mm")
    chosen = _spread_out([T for _, T in feasible], n_cal + n_ver)
    cal, ver = chosen[:n_cal], chosen[n_cal:]
    motion = check_motion([feasible[i][1] for i in cal])
    cal = _shortest_tour(cal, [feasible[i][1] for i in cal])
    poses = [PlannedPose(f"p{k + 1:02d}", "cal", *feasible[i]) for k, i in enumerate(cal)]
    poses += [PlannedPose(f"v{k + 1:02d}", "ver", *feasible[i]) for k, i in enumerate(ver)]
    return PosePlan(poses, motion, n, refused)


def _spread_out(transforms: list[np.ndarray], k: int) -> list[int]:
    """k indices, each next one the farthest (rotation angle plus position, 0.1 m counting as 1 rad) from those
    already taken: orientations spread, which is what identifies a hand-eye rotation."""
    R = Rotation.from_matrix(np.array([T[:3, :3] for T in transforms]))
    t = np.array([T[:3, 3] for T in transforms])
    taken = [0]
    nearest = np.full(len(transforms), np.inf)
    while len(taken) < k:
        last = taken[-1]
        d = (R[last].inv() * R).magnitude() + np.linalg.norm(t - t[last], axis=1) / 0.1
        nearest = np.minimum(nearest, d)
        nearest[taken] = -1
        taken.append(int(np.argmax(nearest)))
    return taken


def _shortest_tour(indices: list[int], transforms: list[np.ndarray]) -> list[int]:
    """The poses in a nearest-neighbour order from the first: less travel between them."""
    left = list(range(len(indices)))
    order = [left.pop(0)]
    while left:
        here = transforms[order[-1]][:3, 3]
        nxt = min(left, key=lambda j: np.linalg.norm(transforms[j][:3, 3] - here))
        left.remove(nxt)
        order.append(nxt)
    return [indices[j] for j in order]
