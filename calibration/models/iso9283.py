"""ISO 9283:1998 (manipulating industrial robots, performance criteria and related test methods): the test poses
and the pose characteristics, as pure math. Metres and radians in, metres and radians out; no I/O.

- §6.8, the poses to be tested: a cube in the working volume, edges parallel to the base axes, and one of its
  diagonal planes (a plane through two opposite edges) as the measuring plane. P1 is the cube's centre (where the
  plane's diagonals cross); P2..P5 lie on the plane's diagonals, 10 % of the diagonal's length in from its corners
  (the standard allows 10 +/- 2 %). Every pose has the same orientation.
- §7.2.1, pose accuracy AP: the distance between the barycentre of the attained positions and the commanded
  position (APp), its components (APx, APy, APz), and the orientation accuracy (APa, APb, APc): the mean attained
  angle less the commanded one, about x, y and z.
- §7.2.2, pose repeatability RP: RPl = l_mean + 3 S_l, with l_j the distance of attained position j from the
  barycentre and S_l the sample standard deviation of the l_j; the orientation repeatability RPa, RPb, RPc =
  +/- 3 S of each angle.

The angles a, b, c of the standard are turns about the base frame's x, y, z. Euler angles wrap and depend on their
order; the deviations here are measured as the small rotation that carries the reference orientation onto the
attained one, R_j R_ref^T, written as a rotation vector about the base's x, y, z: to first order in the deviation
it is (a_j - a_ref, b_j - b_ref, c_j - c_ref) in any order of angles, and it is well defined for every orientation
(a tool pointing straight down included).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.errors import CalibrationInputError

POSE_NAMES = ("P1", "P2", "P3", "P4", "P5")
INSET = 0.1  # §6.8: P2..P5 this fraction of the diagonal in from its corners (10 +/- 2 %)
# the cube's diagonal planes: each holds two opposite edges, both along `edge`; the plane rises from the edge at the
# `low` side to the one at the opposite side ("x+": the edges along x, from -y at the bottom to +y at the top;
# "z+": the vertical edges at (-x, -y) and (+x, +y))
PLANES: dict[str, tuple[int, np.ndarray]] = {
    "x+": (0, np.array([0.0, 1.0, 1.0])), "x-": (0, np.array([0.0, -1.0, 1.0])),
    "y+": (1, np.array([1.0, 0.0, 1.0])), "y-": (1, np.array([-1.0, 0.0, 1.0])),
    "z+": (2, np.array([1.0, 1.0, 0.0])), "z-": (2, np.array([1.0, -1.0, 0.0])),
}


def cube_poses(centre, edge: float, plane: str = "x+", orientation=None, inset: float = INSET) -> dict[str, np.ndarray]:
    """P1..P5 of ISO 9283 §6.8 as 4x4 poses (base frame, m), every one with the rotation `orientation` (3x3;
    default: the base's axes).

    The measuring plane is the cube's diagonal plane `plane` (PLANES): a rectangle `edge` wide along the two edges
    it holds and edge * sqrt(2) long across, its diagonals edge * sqrt(3) long. P1 is the centre; P2..P5 are on the
    diagonals, `inset` of a diagonal in from its corners, in this order around the rectangle: P2 at the low end of
    the edge axis and the low edge, P3 the high end of the low edge, P4 the high end of the high edge, P5 the low
    end of the high edge."""
    centre = _finite(centre, (3,), "centre")
    if not (math.isfinite(edge) and edge > 0):
        raise CalibrationInputError(f"cube edge {edge!r}: allowed: a positive length (m)")
    if plane not in PLANES:
        raise CalibrationInputError(f"plane {plane!r}: allowed: {', '.join(PLANES)} (the cube's diagonal planes, "
                                    "named by the edges they hold and the side they rise to)")
    if not 0 <= inset < 0.5:
        raise CalibrationInputError(f"inset {inset!r}: allowed: 0 to 0.5 (ISO 9283: 0.1, of the diagonal)")
    R = np.eye(3) if orientation is None else _rotation(orientation)
    axis, across = PLANES[plane]
    along = np.eye(3)[axis] * edge / 2  # from the centre to the plane's side, along its edges
    up = across / np.linalg.norm(across) * edge * math.sqrt(2) / 2  # from the centre to its high edge
    corners = [-along - up, along - up, along + up, -along + up]
    positions = [centre] + [centre + (1 - 2 * inset) * c for c in corners]  # the corner, `inset` of 2 halves in
    return {name: _pose(R, p) for name, p in zip(POSE_NAMES, positions)}


@dataclass(frozen=True)
class PoseAccuracy:
    """ISO 9283 §7.2.1 at one pose (m, rad)."""

    n: int
    barycentre: np.ndarray  # (d,): the mean attained position (x_bar, y_bar, z_bar)
    ap_p: float  # APp: |barycentre - commanded|
    ap_xyz: np.ndarray  # (d,): APx, APy, APz = x_bar - x_c, ...
    ap_abc: np.ndarray | None  # (3,): APa, APb, APc = a_bar - a_c, ... (None for positions alone)


@dataclass(frozen=True)
class PoseRepeatability:
    """ISO 9283 §7.2.2 at one pose (m, rad)."""

    n: int
    barycentre: np.ndarray  # (d,)
    distances: np.ndarray  # (n,): l_j, each attained position's distance from the barycentre
    l_mean: float
    s_l: float  # sample standard deviation of the l_j (n - 1)
    rp_l: float  # RPl = l_mean + 3 S_l
    s_abc: np.ndarray | None  # (3,): S_a, S_b, S_c (n - 1)
    rp_abc: np.ndarray | None  # (3,): RPa, RPb, RPc = 3 S (the half-width of +/- 3 S)


def pose_accuracy(commanded, attained) -> PoseAccuracy:
    """ISO 9283 §7.2.1: APp = sqrt((x_bar - x_c)^2 + (y_bar - y_c)^2 + (z_bar - z_c)^2) with x_bar the mean of the n
    attained x_j, and APa = a_bar - a_c (and b, c alike) with a_bar the mean attained angle.

    `attained`: (n, 4, 4) poses, or (n, d) positions (d = 2 or 3: no orientation then). `commanded`: the one
    commanded pose (4, 4) or position (d,), or one per attained pose ((n, 4, 4) or (n, d): every cycle commanded
    the same pose, up to the controller's rounding; the accuracy is then the mean of attained less commanded). The
    angles: the mean of the small rotations R_j R_c^T about x, y, z (module docstring)."""
    poses = _attained(attained)
    n = len(poses)
    if poses.ndim == 3:
        cmd = _commanded_poses(commanded, n)
        d_xyz = poses[:, :3, 3] - cmd[:, :3, 3]
        d_abc = _deviations(poses[:, :3, :3], cmd[:, :3, :3])
        ap_abc = d_abc.mean(axis=0)
    else:
        cmd = np.asarray(commanded, dtype=float)
        cmd = np.broadcast_to(cmd, poses.shape) if cmd.shape == poses.shape[1:] else cmd
        if cmd.shape != poses.shape or not np.all(np.isfinite(cmd)):
            raise CalibrationInputError(f"commanded position of shape {np.shape(commanded)} for attained positions "
                                        f"{poses.shape}: allowed: one position ({poses.shape[1]},) or one per "
                                        f"attained, all finite")
        d_xyz, ap_abc = poses - cmd, None
    ap = d_xyz.mean(axis=0)
    barycentre = (poses[:, :3, 3] if poses.ndim == 3 else poses).mean(axis=0)
    return PoseAccuracy(n, barycentre, float(np.linalg.norm(ap)), ap, ap_abc)


def pose_repeatability(attained) -> PoseRepeatability:
    """ISO 9283 §7.2.2: RPl = l_mean + 3 S_l, l_j = sqrt((x_j - x_bar)^2 + (y_j - y_bar)^2 + (z_j - z_bar)^2),
    S_l = sqrt(sum (l_j - l_mean)^2 / (n - 1)); RPa = +/- 3 S_a, S_a = sqrt(sum (a_j - a_bar)^2 / (n - 1)), and b, c
    alike (returned as the half-width 3 S).

    `attained`: (n, 4, 4) poses or (n, d) positions (d = 2 or 3), n >= 2. The angles are the small rotations
    from the mean attained orientation (module docstring); their spread does not depend on that reference."""
    poses = _attained(attained)
    n = len(poses)
    if n < 2:
        raise CalibrationInputError(f"{n} attained pose: repeatability needs at least 2 (ISO 9283: 30 cycles)")
    xyz = poses[:, :3, 3] if poses.ndim == 3 else poses
    barycentre = xyz.mean(axis=0)
    distances = np.linalg.norm(xyz - barycentre, axis=1)  # the l_j
    l_mean, s_l = float(distances.mean()), float(distances.std(ddof=1))
    s_abc = rp_abc = None
    if poses.ndim == 3:
        mean = Rotation.from_matrix(poses[:, :3, :3]).mean().as_matrix()
        s_abc = _deviations(poses[:, :3, :3], np.broadcast_to(mean, (n, 3, 3))).std(axis=0, ddof=1)
        rp_abc = 3 * s_abc
    return PoseRepeatability(n, barycentre, distances, l_mean, s_l, l_mean + 3 * s_l, s_abc, rp_abc)


# -- helpers --------------------------------------------------------------------------------------------------------
def _deviations(R: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """(n, 3): the rotation vector of R_j R_ref_j^T, about the base's x, y, z (rad)."""
    return Rotation.from_matrix(R @ np.swapaxes(R_ref, -1, -2)).as_rotvec()


def _attained(attained) -> np.ndarray:
    a = np.asarray(attained, dtype=float)
    if not ((a.ndim == 3 and a.shape[1:] == (4, 4)) or (a.ndim == 2 and a.shape[1] in (2, 3))) or len(a) == 0:
        raise CalibrationInputError(f"attained of shape {a.shape}: allowed: (n, 4, 4) poses or (n, 2 | 3) "
                                    "positions, n >= 1")
    if not np.all(np.isfinite(a)):
        raise CalibrationInputError("attained: a pose or position is not finite")
    if a.ndim == 3:
        _check_rotations(a[:, :3, :3], "attained")
    return a


def _commanded_poses(commanded, n: int) -> np.ndarray:
    c = np.asarray(commanded, dtype=float)
    if c.shape == (4, 4):
        c = np.broadcast_to(c, (n, 4, 4))
    if c.shape != (n, 4, 4) or not np.all(np.isfinite(c)):
        raise CalibrationInputError(f"commanded of shape {np.shape(commanded)} for {n} attained poses: allowed: one "
                                    f"pose (4, 4) or one per attained ({n}, 4, 4), all finite")
    _check_rotations(c[:, :3, :3], "commanded")
    return c


def _check_rotations(R: np.ndarray, what: str) -> None:
    err = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max(axis=(1, 2))
    if np.any(err > 1e-6) or np.any(np.linalg.det(R) < 0):
        raise CalibrationInputError(f"{what}: pose {int(np.argmax(err))} has no rotation matrix (R R^T != I within "
                                    "1e-6, or a reflection)")


def _rotation(R) -> np.ndarray:
    R = _finite(R, (3, 3), "orientation")
    _check_rotations(R[None], "orientation")
    return R


def _finite(values, shape: tuple, what: str) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    if v.shape != shape or not np.all(np.isfinite(v)):
        raise CalibrationInputError(f"{what} {np.asarray(values).tolist()}: allowed: finite numbers of shape {shape}")
    return v


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T
