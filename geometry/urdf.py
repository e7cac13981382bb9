"""A six-axis arm's kinematic table (geometry/kinematic_table.py) as a URDF: the calibrated geometry, exactly, for
ROS, MoveIt, pinocchio or a simulator.

Each row of the table is T_i(q) = Rz(q + theta_i) · F_i with the fixed part F_i = Tz(d_i) · Tx(a_i) · Rx(alpha_i) ·
Ry(beta_i), and T_cell_flange(q) = base · T_1(q_1) ··· T_6(q_6). A URDF joint is a fixed origin followed by a turn
about its axis, so the chain is cut between the rows' parts:

    base · Rz(theta_1) | Rz(q_1) | F_1 · Rz(theta_2) | Rz(q_2) | ... | F_5 · Rz(theta_6) | Rz(q_6) | F_6
     joint 1's origin             joint 2's origin                     joint 6's origin           the flange

so every revolute joint turns about its own z (axis 0 0 1), its position is the angle the controller reports (the
table's q, whose limits it carries), and nothing of the geometry is rounded: each origin is written with
repr-exact numbers. The links: base_link (the table's base frame, the cell frame), link_1 ... link_6, flange (the
frame T_base_flange names, the one ROS-Industrial calls tool0, also given as a link `tool0` on it), and `tool`
when a tool transform T_flange_tool is given. Kinematics only: no inertias, visuals or collisions.

URDF's rpy is fixed-axis roll, pitch, yaw: R = Rz(yaw) · Ry(pitch) · Rx(roll).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from geometry.kinematic_table import KinematicTable

# (velocity rad/s, effort N·m) per joint, which a URDF <limit> must give; neither is geometry and neither is
# calibrated. UR5e: 180 deg/s on every joint, 150 N·m (size-3 joints) and 28 N·m (size-1 wrists), from UR's
# technical specifications and its "max. joint torques" article. IRB 120: the data sheet's axis speeds (250, 250,
# 250, 320, 320, 420 deg/s); ABB publishes no joint torques, so effort 0 (ROS-Industrial's "not given").
JOINT_RATINGS: dict[str, tuple[tuple[float, float], ...]] = {
    "ur5e": tuple((math.radians(180.0), effort) for effort in (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)),
    "irb120": tuple((math.radians(speed), 0.0) for speed in (250.0, 250.0, 250.0, 320.0, 320.0, 420.0)),
}
UNRATED = (0.0, 0.0)  # a model not in JOINT_RATINGS

LINKS = ("base_link", "link_1", "link_2", "link_3", "link_4", "link_5", "link_6")
GIMBAL_LOCK = 1e-12  # |cos(pitch)| below this: roll and yaw turn about the same axis, roll is set to 0


def urdf_of(table: KinematicTable, name: str, tool=None, comment: str | None = None) -> str:
    """The URDF document (text) of `table` as robot `name`.

    `tool`: T_flange_tool, a 4x4 matrix (m) or a pose {x_mm, y_mm, z_mm, qw, qx, qy, qz}, added as link `tool` on
    the flange; None: no tool link. `comment`: written at the top of the document (where it came from)."""
    if len(table.joints) != 6:
        raise ValueError(f"a URDF of a six-axis arm needs 6 joints; the table has {len(table.joints)}")
    base = _finite_matrix(table.base, "the table's base")
    tool_matrix = None if tool is None else tool_transform(tool)
    ratings = JOINT_RATINGS.get(table.model, (UNRATED,) * 6)

    robot = ET.Element("robot", name=str(name))
    if comment:
        robot.append(ET.Comment(f" {_comment_safe(comment)} "))
    for link in LINKS:
        ET.SubElement(robot, "link", name=link)

    before = base  # the fixed transform from the parent link to the next joint, without that joint's theta
    for i, (joint, (velocity, effort)) in enumerate(zip(table.joints, ratings)):
        element = ET.SubElement(robot, "joint", name=joint.name, type="revolute")
        _origin(element, before @ _rz(joint.theta))
        ET.SubElement(element, "parent", link=LINKS[i])
        ET.SubElement(element, "child", link=LINKS[i + 1])
        ET.SubElement(element, "axis", xyz="0 0 1")
        lower, upper = joint.limits
        ET.SubElement(element, "limit", lower=_number(lower), upper=_number(upper), effort=_number(effort),
                      velocity=_number(velocity))
        before = fixed_part(joint.d, joint.a, joint.alpha, joint.beta)

    _fixed(robot, "link_6-flange", LINKS[-1], "flange", before)
    _fixed(robot, "flange-tool0", "flange", "tool0", np.eye(4))
    if tool_matrix is not None:
        _fixed(robot, "flange-tool", "flange", "tool", tool_matrix)
    ET.indent(robot, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def fixed_part(d: float, a: float, alpha: float, beta: float) -> np.ndarray:
    """Tz(d) · Tx(a) · Rx(alpha) · Ry(beta): the part of a row after its joint's turn (kinematic_table's F)."""
    ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
    return np.array([[cb, 0.0, sb, a],
                     [sa * sb, ca, -sa * cb, 0.0],
                     [-ca * sb, sa, ca * cb, d],
                     [0.0, 0.0, 0.0, 1.0]])


def rpy_of(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with R = Rz(yaw) · Ry(pitch) · Rx(roll), pitch in [-pi/2, pi/2]."""
    R = np.asarray(R, dtype=float)
    cos_pitch = math.hypot(R[0, 0], R[1, 0])
    pitch = math.atan2(-R[2, 0], cos_pitch)
    if cos_pitch > GIMBAL_LOCK:
        return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])
    # pitch = +-pi/2: only yaw -+ roll is defined; roll 0 and all of it in yaw
    return 0.0, pitch, math.atan2(-R[0, 1], R[1, 1])


def tool_transform(tool) -> np.ndarray:
    """T_flange_tool (4x4, m) from a 4x4 matrix or a pose {x_mm, y_mm, z_mm, qw, qx, qy, qz}; ValueError naming what
    is wrong."""
    if isinstance(tool, dict):
        keys = ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")
        missing = [k for k in keys if k not in tool]
        if missing:
            raise ValueError(f"tool: {', '.join(missing)} missing; a tool pose is {', '.join(keys)}")
        try:
            values = [float(tool[k]) for k in keys]
        except (TypeError, ValueError):
            raise ValueError(f"tool: every one of {', '.join(keys)} must be a number, got {tool!r}") from None
        if not all(map(math.isfinite, values)):
            raise ValueError(f"tool: every one of {', '.join(keys)} must be a finite number, got {tool!r}")
        w, x, y, z = values[3:]
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"tool: quaternion (qw, qx, qy, qz) = {values[3:]} is not of unit length ({norm})")
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        T = np.eye(4)
        T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
        T[:3, 3] = np.array(values[:3]) * 1e-3
        return T
    return _finite_matrix(tool, "tool")


def _finite_matrix(T, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{what}: expected a finite 4x4 transform, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0 or not np.allclose(T[3], (0, 0, 0, 1)):
        raise ValueError(f"{what}: not a rigid transform (its rotation is not orthonormal, or its last row is not "
                         "0 0 0 1)")
    return T


def _rz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _origin(element: ET.Element, T: np.ndarray) -> None:
    ET.SubElement(element, "origin", xyz=" ".join(map(_number, T[:3, 3])), rpy=" ".join(map(_number, rpy_of(T[:3, :3]))))


def _fixed(robot: ET.Element, name: str, parent: str, child: str, T: np.ndarray) -> None:
    ET.SubElement(robot, "link", name=child)
    element = ET.SubElement(robot, "joint", name=name, type="fixed")
    _origin(element, T)
    ET.SubElement(element, "parent", link=parent)
    ET.SubElement(element, "child", link=child)


def _number(value: float) -> str:
    """Every digit of the float (repr round-trips), and no "-0.0"."""
    value = float(value)
    return repr(value + 0.0)


def _comment_safe(text: str) -> str:
    """An XML comment may not hold "--" nor end in "-"."""
    while "--" in text:
        text = text.replace("--", "- -")
    return text.rstrip("-")
