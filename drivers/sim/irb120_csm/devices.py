"""In-process fake of the IRB 120 controller on the six-axis world (backend `sim-irb120`).

The cameras of this world need no fake of their own: `drivers.sim.devices.SimCamera` renders any world,
so cameras keep `backend: sim` in both kinds of cell (drivers/sim/kinds.py).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from geometry.irb120 import IRB120_LIMITS_DEG
from geometry.orientation import quaternion_wxyz, rotation_from_wxyz, tool_down

from drivers.interfaces import JointState, MotionRejected, Pose
from drivers.limits import WorkspaceBox
from drivers.sim.base import Strict
from drivers.sim.devices import SimDevice

JOINT_NAMES = tuple(f"joint_{i}" for i in range(1, 7))


class SimSixAxisArmSettings(Strict):
    limits: WorkspaceBox = Field(..., description="box for the fixture (tool) frame origin; alpha_deg is not used")
    joint_limits_deg: tuple[tuple[float, float], ...] = Field(
        IRB120_LIMITS_DEG, description="per joint (min, max); default: the IRB 120 data sheet")


class SimSixAxisArm(SimDevice):
    """Six joints, joint moves and linear moves (by the controller's nominal inverse kinematics); the
    tool is the fixture frame; the reported pose is the nominal forward kinematics of the commanded joints."""

    Settings = SimSixAxisArmSettings

    def __init__(self, name, world, settings):
        super().__init__(name, world, settings)
        if len(settings.joint_limits_deg) != 6:
            raise ValueError(f"arm {name!r}: joint_limits_deg needs 6 (min, max) pairs, got {len(settings.joint_limits_deg)}")

    def _check_joints(self, q: np.ndarray) -> None:
        for i, (value, (lo, hi)) in enumerate(zip(np.degrees(q), self.settings.joint_limits_deg), start=1):
            if not math.isfinite(value):
                raise MotionRejected(f"{self.name}: joint_{i}={value} is not a finite number; nothing moved")
            if not lo <= value <= hi:
                raise MotionRejected(f"{self.name}: joint_{i}={value:.4f} deg is outside [{lo}, {hi}]; nothing moved")
        _, t = self.world.nominal_arm.fixture_pose(q)
        self.settings.limits.check(Pose(*t, alpha=0.0))

    def _go(self, q: np.ndarray, settle: bool = True) -> None:
        self._ready_to_move()
        self._check_joints(q)
        self._count_move()
        self.world.move_joints(q, settle=settle)

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        if len(joints.positions) != 6:
            raise MotionRejected(f"{self.name}: expects 6 joints (rad), got {len(joints.positions)}")
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
        self._go(np.asarray(joints.positions, dtype=float))

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        """The fixture (tool) frame to `target`: its orientation (w, x, y, z), else tool-down turned by alpha."""
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
        self._go(self._solve(target))

    def move_through(self, target: Pose, speed: float | None = None) -> None:
        """To a via point (MovesThrough): as move_linear, the motion's time counted, its settling not."""
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
        self._go(self._solve(target), settle=False)

    def check_target(self, target: Pose) -> None:
        self._solve(target)

    def _solve(self, target: Pose):
        """The joints for `target` (checked against the box and the joint limits), else MotionRejected."""
        self._ready()
        self.settings.limits.check(Pose(target.x, target.y, target.z, 0.0))
        current = self.world.reported_joints()
        if target.orientation is not None:
            R = rotation_from_wxyz(target.orientation).as_matrix()
        else:  # the cell's convention: the tool points down, turned by alpha
            R = tool_down(target.alpha).as_matrix()
        q = self.world.nominal_arm.solve_fixture_pose(R, target.xyz, current)
        if q is None:
            raise MotionRejected(f"{self.name}: no joint solution within the joint limits reaches "
                                 f"({target.x:.4f}, {target.y:.4f}, {target.z:.4f}) m; nothing moved")
        return q

    def pose(self) -> Pose:
        self._ready()
        R, t = self.world.nominal_arm.fixture_pose(self.world.reported_joints())
        return Pose(float(t[0]), float(t[1]), float(t[2]), math.atan2(R[1, 0], R[0, 0]),
                    quaternion_wxyz(Rotation.from_matrix(R)))

    def joints(self) -> JointState:
        self._ready()
        return JointState(tuple(float(v) for v in self.world.reported_joints()), JOINT_NAMES)
