"""In-process fake of the UR5e controller on the hand-eye world (backend `sim-ur5e`).

It behaves as a UR controller does for a program: joint moves within the joint limits and the reach, linear moves
solved by its own (nominal) kinematics on the branch the arm is on, and a reported flange pose that is the nominal
forward kinematics of its encoders: the controller cannot see its own geometry errors. What the controller computes
is geometry/ur_controller.py, which the UR protocol simulator (drivers/sim/servers/ur) and the real driver use too:
the pose comes as a controller sends it (a rotation vector, turned into the Pose's quaternion as the driver does)
and a linear target goes the same way, so a routine gets the same numbers here and through ur-rtde. The cameras
are `drivers.sim.devices.SimCamera`, which renders any world.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field

from geometry import ur
from geometry.ur_controller import linear_joints, matrix_of_ur_pose, pose_parts, tcp_pose, ur_pose_of

from drivers.interfaces import JointState, MotionRejected, Pose
from drivers.limits import WorkspaceBox
from drivers.sim.base import Strict
from drivers.sim.devices import SimDevice


class SimUr5eArmSettings(Strict):
    limits: WorkspaceBox = Field(..., description="box for the flange origin; alpha_deg is not used")


class SimUr5eArm(SimDevice):
    """Six joints; the tool is the flange (tool0)."""

    Settings = SimUr5eArmSettings

    def _check_joints(self, q: np.ndarray) -> None:
        robot = self.world.config.robot
        for i, (value, (lo, hi)) in enumerate(zip(np.degrees(q), robot.joint_limits_deg), start=1):
            if not math.isfinite(value):
                raise MotionRejected(f"{self.name}: joint {ur.JOINT_NAMES[i - 1]}={value} is not a finite number; "
                                     "nothing moved")
            if not lo <= value <= hi:
                raise MotionRejected(f"{self.name}: joint {ur.JOINT_NAMES[i - 1]}={value:.4f} deg is outside "
                                     f"[{lo}, {hi}]; nothing moved")
        T = ur.forward(q)
        self.settings.limits.check(Pose(*T[:3, 3], alpha=0.0))
        shoulder = np.array([0.0, 0.0, ur.UR5E_DH[0][1]])
        reach = np.linalg.norm(T[:3, 3] - shoulder) * 1e3
        if reach > robot.reach_mm:
            raise MotionRejected(f"{self.name}: the flange would be {reach:.1f} mm from the shoulder, beyond the "
                                 f"reach of {robot.reach_mm:.0f} mm; nothing moved")

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        if len(joints.positions) != 6:
            raise MotionRejected(f"{self.name}: expects 6 joints (rad), got {len(joints.positions)}")
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
        q = np.asarray(joints.positions, dtype=float)
        self._ready_to_move()
        self._check_joints(q)
        self._count_move()
        self.world.move_joints(q)

    def check_target(self, target: Pose) -> None:
        self._ready()
        self._check_joints(self._linear_joints(target))

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        """The flange to `target`: its orientation (w, x, y, z), else pointing down turned by alpha, taken as a
        controller receives it (a UR pose); on the branch the arm is on, each joint the nearest turn to where it is."""
        self._ready()
        self.move_joints(JointState(tuple(float(v) for v in self._linear_joints(target))), speed)

    def _linear_joints(self, target: Pose) -> np.ndarray:
        current = self.world.reported_joints()
        try:
            q = linear_joints(matrix_of_ur_pose(ur_pose_of(target.x, target.y, target.z, target.alpha,
                                                           target.orientation)), current)
        except ur.Unreachable as exc:
            raise MotionRejected(f"{self.name}: ({target.x:.4f}, {target.y:.4f}, {target.z:.4f}) m is out of reach "
                                 f"on the arm's present branch: {exc}; nothing moved") from None
        except ValueError as exc:  # not finite, not a unit quaternion
            raise MotionRejected(f"{self.name}: target {target}: {exc}; nothing moved") from None
        return q

    def pose(self) -> Pose:
        """The flange (tool0) as the controller reports it: the nominal forward kinematics of the encoders."""
        self._ready()
        return Pose(*pose_parts(tcp_pose(self.world.reported_joints())))

    def joints(self) -> JointState:
        self._ready()
        return JointState(tuple(float(v) for v in self.world.reported_joints()), ur.JOINT_NAMES)
