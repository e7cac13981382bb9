"""The path of a manual move: where a jog or a move-to goes, cut into short segments.

Pure geometry on `Pose`s (metres, radians), no devices. A four-axis arm (a pose without `orientation`) turns about
the vertical only: its tool frame is the cell frame turned by alpha. A six-axis arm's tool frame is its reported
orientation; a turn in the cell frame is about the cell's axes through the tool point, in the tool frame about the
tool's own axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from geometry.orientation import quaternion_wxyz, rotation_from_wxyz, tool_down

from drivers.interfaces import Pose
from drivers.limits import WorkspaceBox

TRANSLATIONS = {"x": 0, "y": 1, "z": 2}
ROTATIONS = {"rx": 0, "ry": 1, "rz": 2}
AXES = (*TRANSLATIONS, *ROTATIONS)
FRAMES = ("cell", "tool")
ROTATION_RADIUS_M = 0.1  # a turn goes at the speed that moves a point this far from the tool at the manual speed
ENDLESS_TURN_RAD = math.pi  # a held turn goes at most half a turn (then the key is pressed again)


class PathError(ValueError):
    """The move cannot be made as asked (an axis a four-axis arm does not have, a target outside the box)."""


def rotation_of(pose: Pose) -> Rotation:
    return rotation_from_wxyz(pose.orientation) if pose.orientation is not None else tool_down(pose.alpha)


def stepped(pose: Pose, axis: str, amount: float, frame: str) -> Pose:
    """`pose` moved by `amount` (m, or rad for rx/ry/rz) along or about `axis` of `frame`."""
    if axis in TRANSLATIONS:
        d = np.zeros(3)
        d[TRANSLATIONS[axis]] = amount
        if frame == "tool":
            d = (rotation_of(pose).as_matrix() if pose.orientation is not None
                 else Rotation.from_euler("z", pose.alpha).as_matrix()) @ d
        return Pose(pose.x + d[0], pose.y + d[1], pose.z + d[2], pose.alpha, pose.orientation)
    if pose.orientation is None:  # four axes: alpha is the only turn, the same in either frame
        if axis != "rz":
            raise PathError(f"axis {axis}: this arm turns about the vertical only (allowed: x, y, z, rz)")
        return Pose(pose.x, pose.y, pose.z, pose.alpha + amount)
    turn = Rotation.from_rotvec(np.eye(3)[ROTATIONS[axis]] * amount)
    rotation = turn * rotation_of(pose) if frame == "cell" else rotation_of(pose) * turn
    return with_rotation(pose, rotation)


def with_rotation(pose: Pose, rotation: Rotation) -> Pose:
    q = quaternion_wxyz(rotation)
    if q[0] < 0:
        q = tuple(-v for v in q)
    m = rotation.as_matrix()
    return Pose(pose.x, pose.y, pose.z, math.atan2(m[1, 0], m[0, 0]), q)


def to_box_edge(pose: Pose, axis: str, direction: int, frame: str, box: WorkspaceBox) -> Pose:
    """Where a held jog along `axis` would end: the workspace box's edge (a translation), or half a turn, or the
    box's alpha limit (a turn)."""
    if axis in ROTATIONS:
        if pose.orientation is None:
            lo, hi = (math.radians(v) for v in box.alpha_deg)
            end = hi if direction > 0 else lo
            return stepped(pose, axis, max(-ENDLESS_TURN_RAD, min(ENDLESS_TURN_RAD, end - pose.alpha)), frame)
        return stepped(pose, axis, direction * ENDLESS_TURN_RAD, frame)
    unit = np.array(stepped(Pose(0.0, 0.0, 0.0, pose.alpha, pose.orientation), axis, 1.0, frame).xyz) * direction
    reach = math.inf
    for i, name in enumerate(("x_mm", "y_mm", "z_mm")):
        lo, hi = (v * 1e-3 for v in getattr(box, name))
        if unit[i] > 1e-12:
            reach = min(reach, (hi - pose.xyz[i]) / unit[i])
        elif unit[i] < -1e-12:
            reach = min(reach, (lo - pose.xyz[i]) / unit[i])
    return stepped(pose, axis, direction * max(reach, 0.0), frame)


@dataclass(frozen=True)
class Segment:
    target: Pose
    seconds: float  # its motion at the manual speed


def segments(start: Pose, end: Pose, speed_m_s: float, seconds_each: float) -> list[Segment]:
    """The straight path from `start` to `end` (position linear, orientation slerped), in pieces of about
    `seconds_each` of motion at `speed_m_s` (turns at the speed that moves a point ROTATION_RADIUS_M away as fast)."""
    distance = float(np.linalg.norm(end.xyz - start.xyz))
    if start.orientation is None:
        angle = abs(end.alpha - start.alpha)
    else:
        angle = float((rotation_of(end) * rotation_of(start).inv()).magnitude())
    duration = max(distance / speed_m_s, angle * ROTATION_RADIUS_M / speed_m_s)
    if duration <= 0:
        return []
    n = max(1, math.ceil(duration / seconds_each - 1e-9))
    fractions = np.arange(1, n + 1) / n
    if start.orientation is not None:
        turns = Slerp([0.0, 1.0], Rotation.concatenate([rotation_of(start), rotation_of(end)]))(fractions)
    out = []
    for i, f in enumerate(fractions):
        xyz = start.xyz + f * (end.xyz - start.xyz)
        if start.orientation is None:
            target = Pose(*map(float, xyz), start.alpha + f * (end.alpha - start.alpha))
        else:
            target = with_rotation(Pose(*map(float, xyz)), turns[i])
        out.append(Segment(target, duration / n))
    return out


def check_in_box(target: Pose, box: WorkspaceBox | None) -> None:
    """PathError naming the coordinate outside the box (a straight path between two points in the box stays in it)."""
    if box is None:
        return
    values = {"x_mm": target.x * 1e3, "y_mm": target.y * 1e3, "z_mm": target.z * 1e3}
    if target.orientation is None:
        values["alpha_deg"] = math.degrees(target.alpha)
    for name, value in values.items():
        lo, hi = getattr(box, name)
        if not math.isfinite(value):
            raise PathError(f"target {name}={value} is not a finite number")
        if not lo - 1e-6 <= value <= hi + 1e-6:
            raise PathError(f"target {name}={value:.3f} is outside the workspace box [{lo}, {hi}] (arm.limits)")


def pose_fields(pose: Pose) -> dict:
    """A pose at the edges: x_mm, y_mm, z_mm, alpha_deg (and the orientation as w, x, y, z when it has one)."""
    out = {"x_mm": pose.x * 1e3, "y_mm": pose.y * 1e3, "z_mm": pose.z * 1e3, "alpha_deg": math.degrees(pose.alpha)}
    if pose.orientation is not None:
        out["quaternion_wxyz"] = [float(v) for v in pose.orientation]
    return out
