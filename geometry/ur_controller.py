"""What a Universal Robots controller computes with its nominal kinematics (geometry/ur.py), written once for
the three places that play or read it: the in-process fake of the hand-eye cell's UR5e
(drivers/sim/ur5e_handeye/devices.py), the UR protocol simulator when that UR5e stands behind it
(drivers/sim/servers/ur/six_axis.py), and the real driver (drivers/arms/ur) that reads the controller's answers.

- A UR pose is [x, y, z, rx, ry, rz]: metres and a rotation vector (rad). RTDE carries actual_TCP_pose and a
  moveL target that way.
- The pose a controller reports for joints q (`tcp_pose`) is the nominal forward kinematics of q composed with
  the TCP offset: a controller cannot see its own geometry errors. With a zero offset, the flange (tool0).
- A linear target's joints (`linear_joints`) come from the closed-form inverse on the branch the arm is on, each
  angle the nearest turn to where it is.
- `pose_parts` turns a reported UR pose into the position, alpha and quaternion (w, x, y, z) of a Pose, and
  `ur_pose_of` a target (an orientation, or the tool pointing down turned by alpha) into a UR pose.

The fake reports its pose through the same rotation vector a controller sends, and takes its linear targets
through the same conversion, so a routine sees the very same numbers in-process and through ur-rtde.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.orientation import alpha_of, quaternion_wxyz, rotation_from_wxyz, tool_down
from geometry.ur import UR5E_DH, UR5E_LIMITS_RAD, branch_of, forward, inverse

ZERO_TCP = (0.0,) * 6


# --- rotation vectors, in numpy alone (the simulator's 500 Hz cycle converts poses all the time) -------------
def matrix_of_rotvec(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    theta = float(np.linalg.norm(v))
    if theta < 1e-15:
        return np.eye(3)
    kx, ky, kz = v / theta
    k = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    return np.eye(3) + math.sin(theta) * k + (1.0 - math.cos(theta)) * (k @ k)


def rotvec_of_matrix(m: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix, through the quaternion (well defined at 180°, the tool-down case)."""
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    squares = [1.0 + trace, 1.0 + m[0, 0] - m[1, 1] - m[2, 2], 1.0 - m[0, 0] + m[1, 1] - m[2, 2],
               1.0 - m[0, 0] - m[1, 1] + m[2, 2]]
    i = int(np.argmax(squares))
    r = math.sqrt(max(squares[i], 0.0)) * 2.0  # 4 * the largest quaternion component
    if i == 0:
        q = (r / 4, (m[2, 1] - m[1, 2]) / r, (m[0, 2] - m[2, 0]) / r, (m[1, 0] - m[0, 1]) / r)
    elif i == 1:
        q = ((m[2, 1] - m[1, 2]) / r, r / 4, (m[0, 1] + m[1, 0]) / r, (m[0, 2] + m[2, 0]) / r)
    elif i == 2:
        q = ((m[0, 2] - m[2, 0]) / r, (m[0, 1] + m[1, 0]) / r, r / 4, (m[1, 2] + m[2, 1]) / r)
    else:
        q = ((m[1, 0] - m[0, 1]) / r, (m[0, 2] + m[2, 0]) / r, (m[1, 2] + m[2, 1]) / r, r / 4)
    w, xyz = q[0], np.array(q[1:])
    if w < 0:
        w, xyz = -w, -xyz
    norm = float(np.linalg.norm(xyz))
    if norm < 1e-15:
        return np.zeros(3)
    return xyz / norm * (2.0 * math.atan2(norm, w))


# --- UR poses ---------------------------------------------------------------------------------------------
def six_finite(values, what: str) -> tuple[float, ...]:
    """The six values as floats; ValueError naming `what` unless they are six finite numbers."""
    out = tuple(float(v) for v in values)
    if len(out) != 6 or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{what} {list(out)} is not six finite numbers")
    return out


def ur_pose_of_matrix(T: np.ndarray) -> tuple[float, ...]:
    """[x, y, z, rx, ry, rz] of a 4x4."""
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), *map(float, rotvec_of_matrix(T[:3, :3])))


def matrix_of_ur_pose(pose) -> np.ndarray:
    """The 4x4 of [x, y, z, rx, ry, rz]."""
    values = six_finite(pose, "pose")
    T = np.eye(4)
    T[:3, :3] = matrix_of_rotvec(values[3:])
    T[:3, 3] = values[:3]
    return T


def _is_zero(tcp) -> bool:
    return not any(float(v) for v in tcp)


def tcp_of_flange(T_base_flange: np.ndarray, tcp=ZERO_TCP) -> np.ndarray:
    """T_base_tcp: the flange moved by the TCP offset [x, y, z, rx, ry, rz] (a zero offset leaves it untouched)."""
    if _is_zero(tcp):
        return T_base_flange
    return T_base_flange @ matrix_of_ur_pose(tcp)


def flange_of_tcp(ur_pose, tcp=ZERO_TCP) -> np.ndarray:
    """T_base_flange for a TCP at `ur_pose` (a moveL target) with the TCP offset `tcp`."""
    T = matrix_of_ur_pose(ur_pose)
    if _is_zero(tcp):
        return T
    offset = matrix_of_ur_pose(tcp)
    inverse_offset = np.eye(4)
    inverse_offset[:3, :3] = offset[:3, :3].T
    inverse_offset[:3, 3] = -offset[:3, :3].T @ offset[:3, 3]
    return T @ inverse_offset


def tcp_pose(q, tcp=ZERO_TCP, dh=UR5E_DH) -> tuple[float, ...]:
    """actual_TCP_pose for joints q (rad): the nominal forward kinematics composed with the TCP offset."""
    return _tcp_pose(six_finite(q, "joints"), tuple(float(v) for v in tcp), tuple(map(tuple, dh)))


@functools.lru_cache(maxsize=256)  # the simulator's 500 Hz cycle asks for the same joints over and over
def _tcp_pose(q: tuple[float, ...], tcp: tuple[float, ...], dh) -> tuple[float, ...]:
    return ur_pose_of_matrix(tcp_of_flange(forward(q, dh), tcp))


def pose_parts(ur_pose) -> tuple[float, float, float, float, tuple[float, float, float, float]]:
    """(x, y, z, alpha, (w, x, y, z)) of a reported UR pose: the fields of a drivers.interfaces.Pose."""
    values = [float(v) for v in ur_pose]
    rotation = Rotation.from_rotvec(values[3:6])
    return values[0], values[1], values[2], alpha_of(rotation), quaternion_wxyz(rotation)


def ur_pose_of(x: float, y: float, z: float, alpha: float = 0.0, orientation=None) -> list[float]:
    """[x, y, z, rx, ry, rz] of a target: its orientation (w, x, y, z) if given, else the tool pointing down
    turned by alpha (geometry/orientation.py)."""
    rotation = rotation_from_wxyz(orientation) if orientation is not None else tool_down(alpha)
    return [float(x), float(y), float(z), *map(float, rotation.as_rotvec())]


# --- joints -----------------------------------------------------------------------------------------------
def linear_joints(T_base_flange: np.ndarray, current, dh=UR5E_DH) -> np.ndarray:
    """The joints (rad) that put the flange at T on the branch `current` is on, each angle the nearest turn to
    `current`'s; geometry.ur.Unreachable if that branch has none."""
    current = np.asarray(current, dtype=float)
    return inverse(T_base_flange, branch_of(current, dh), dh, near=current)


def outside_limits(q, limits=UR5E_LIMITS_RAD, names=None) -> str | None:
    """What is wrong with joint target q (rad) against (min, max) limits per joint, or None if nothing is."""
    values = [float(v) for v in q]
    if len(values) != len(limits):
        return f"expects {len(limits)} joint angles (rad), got {len(values)}"
    for i, (value, (lo, hi)) in enumerate(zip(values, limits)):
        name = names[i] if names else f"j{i + 1}"
        if not math.isfinite(value):
            return f"joint {name}={value} is not a finite number"
        if not lo <= value <= hi:
            return f"joint {name}={value:.4f} rad is outside its limits [{lo:.4f}, {hi:.4f}] rad"
    return None
