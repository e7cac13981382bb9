"""How a simulated arm looks from behind the ABB protocol: its six-axis jointtarget and its flange (tool0).

The RAPID server module speaks of six axes (degrees, mm for linear axes) and of the flange frame
tool0, to which it applies the tool and work object frames itself. Each simulated world's arm fake
maps to that in its own way; `wire_robot` picks the mapping by the kind of the arm's world (the fake
`drivers.sim.servers.sim_device` built is that world's own), so the server itself has no per-world cases.

Positions are in mm, rotations `scipy` Rotations, as in `abb.py`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.orientation import alpha_of, quaternion_wxyz, rotation_from_wxyz, tilt_of, tool_down

from drivers.interfaces import JointState, Pose
from drivers.sim.kinds import world_kind


class FourAxisRobot:
    """The micro cell's x, y, z, alpha robot (`SimArm`): joints x, y, z (mm), alpha (deg), 0, 0; its flange
    always points down, so a target that tilts it more than `max_tilt` (rad) is unreachable."""

    robot_type = "cellctl 4-axis micro cell"

    def __init__(self, arm, max_tilt: float):
        self.arm = arm
        self.max_tilt = max_tilt

    def wire_joints(self) -> list[float]:
        pose = self.arm.pose()
        return [pose.x * 1e3, pose.y * 1e3, pose.z * 1e3, math.degrees(pose.alpha), 0.0, 0.0]

    def joints_from_wire(self, p: list[float]) -> JointState | None:
        if abs(p[4]) > 1e-3 or abs(p[5]) > 1e-3:
            return None  # the cell arm has no axes 5 and 6
        return JointState((p[0] * 1e-3, p[1] * 1e-3, p[2] * 1e-3, math.radians(p[3])))

    def flange(self) -> tuple[np.ndarray, Rotation]:
        pose = self.arm.pose()
        return np.array([pose.x, pose.y, pose.z]) * 1e3, tool_down(pose.alpha)

    def flange_target(self, p_mm: np.ndarray, r: Rotation) -> Pose | None:
        if tilt_of(r) > self.max_tilt:
            return None  # a 4-axis arm cannot tilt its tool
        current = self.arm.pose().alpha
        alpha = current + math.remainder(alpha_of(r) - current, math.tau)  # nearest turn, as ConfL \Off
        x, y, z = p_mm * 1e-3
        return Pose(float(x), float(y), float(z), alpha)


class SixAxisRobot:
    """The IRB 120 of the six-axis world (`SimSixAxisArm`): six joints in degrees; tool0 is DH frame 6
    (at zero joints (374, 0, 630) mm, q = (0.7071, 0, 0.7071, 0), as on the real robot). The fake moves
    and reports the fixture frame, DH frame 7, which sits `(a7, 0, d7)` from tool0 without turning: a
    client that wants the fixture as its TCP sets that tooldata, as on the real controller."""

    robot_type = "IRB 120-3/0.6"

    def __init__(self, arm, tool0_to_fixture_mm: np.ndarray):
        self.arm = arm
        self.offset = np.asarray(tool0_to_fixture_mm, dtype=float)

    def wire_joints(self) -> list[float]:
        return [math.degrees(v) for v in self.arm.joints().positions]

    def joints_from_wire(self, p: list[float]) -> JointState:
        return JointState(tuple(math.radians(v) for v in p))

    def flange(self) -> tuple[np.ndarray, Rotation]:
        pose = self.arm.pose()
        r = rotation_from_wxyz(pose.orientation)
        return pose.xyz * 1e3 - r.apply(self.offset), r

    def flange_target(self, p_mm: np.ndarray, r: Rotation) -> Pose:
        x, y, z = (p_mm + r.apply(self.offset)) * 1e-3  # the fixture frame the fake moves
        return Pose(float(x), float(y), float(z), alpha_of(r), quaternion_wxyz(r))


def wire_robot(arm, max_tilt: float):
    """The mapping for `arm`, the own arm fake of a simulated world (drivers/sim/kinds.py)."""
    kind = world_kind(arm.world.config)
    if kind == "micro-cell":
        return FourAxisRobot(arm, max_tilt)
    if kind == "irb120-csm":
        d7, a7 = arm.world.tool_m
        return SixAxisRobot(arm, np.array([a7, 0.0, d7]) * 1e3)
    raise ValueError(f"the ABB simulator serves the arm of a micro cell (world: micro-cell) or of an IRB 120 cell "
                     f"(world: irb120-csm), not of world: {kind}")
