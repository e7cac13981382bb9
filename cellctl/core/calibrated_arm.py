"""Moves through the active `arm` calibration: the tool lands where it was asked, not where the nominal table says.

The controller (a UR's, an ABB's, the simulated one) turns a Cartesian target into joints with its nominal table.
With an `arm` calibration in force, a linear target T goes first through the calibrated table's inverse kinematics
(iterated from the nominal solution: geometry/kinematic_table.py) to the joints q* that truly put the flange at T;
the controller is then sent the pose its own nominal table gives for q*, which it turns back into q*. So every
driver (in-process, ABB over its socket link, UR through ur-rtde) gets the correction without knowing of it, and a
linear move stays linear to within the calibration's correction. `pose()` is the calibrated table's forward
kinematics of the reported joints. Joint moves and everything else pass through unchanged.

The pose a driver takes and reports is its controller's TCP (the flange on a UR with a zero offset, the fixture frame
on the IRB 120 cell): the model's `controller_tcp` is where the controller puts it on the flange (the drawing), its
`tcp` where the calibration found it. The cell frame is the calibration's: with camera views only, the base joint's
zero and height belong to the board's or the cameras' pose (models/arm_kinematics.py), so positions located through
that calibration's cameras are reached exactly.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from geometry import ur
from geometry.kinematic_table import IKFailed, KinematicTable
from geometry.orientation import alpha_of, quaternion_wxyz, rotation_from_wxyz, tool_down
from geometry.transforms import inverse

from drivers.interfaces import ChecksTargets, MotionRejected, Pose, move_via

from calibration.models.hand_eye import pose_from_dict


def matrix_of_pose(pose: Pose) -> np.ndarray:
    T = np.eye(4)
    rotation = rotation_from_wxyz(pose.orientation) if pose.orientation is not None else tool_down(pose.alpha)
    T[:3, :3] = rotation.as_matrix()
    T[:3, 3] = [pose.x, pose.y, pose.z]
    return T


def pose_of_matrix(T: np.ndarray) -> Pose:
    rotation = Rotation.from_matrix(T[:3, :3])
    return Pose(float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), alpha_of(rotation), quaternion_wxyz(rotation))


class CalibratedArm:
    """The cell's arm with an `arm` calibration's model in force (module docstring)."""

    def __init__(self, arm, model: dict):
        self._arm = arm
        self.table = KinematicTable.from_dict(model["table"])
        self.nominal = KinematicTable.from_dict(model["nominal"])
        self.tcp = pose_from_dict(model["tcp"]) if model.get("tcp") else np.eye(4)
        self.controller_tcp = pose_from_dict(model["controller_tcp"]) if model.get("controller_tcp") else np.eye(4)
        self.calibration_id = model.get("calibration_id")

    def __getattr__(self, name):  # every other verb of the driver, unchanged
        return getattr(self._arm, name)

    def calibrated_joints(self, target: Pose) -> np.ndarray:
        """The joints that put the flange at `target` through the calibrated table; MotionRejected if none within
        the limits (before anything moves)."""
        T = matrix_of_pose(target) @ inverse(self.tcp)  # the flange, as the calibration knows it
        q_now = np.asarray(self._arm.joints().positions, dtype=float)
        start = self._nominal_solution(T, q_now)
        try:
            return self.table.inverse(T, start)
        except IKFailed as exc:
            raise MotionRejected(f"{self._arm.name}: ({target.x:.4f}, {target.y:.4f}, {target.z:.4f}) m through the "
                                 f"calibrated arm (calibration {self.calibration_id}): {exc}; nothing moved") from None

    def _nominal_solution(self, T: np.ndarray, q_now: np.ndarray) -> np.ndarray:
        """The nominal joints for the flange at T on the arm's present branch (a UR's closed form; else iterated from
        the present joints), else the present joints."""
        if self.nominal.model == "ur5e":
            try:
                return ur.inverse(T, ur.branch_of(q_now), near=q_now)
            except ur.Unreachable:
                return q_now
        try:
            return self.nominal.inverse(T, q_now)
        except IKFailed:
            return q_now

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._arm.move_linear(self._command(target), speed)

    def move_through(self, target: Pose, speed: float | None = None) -> None:
        """A via point (MovesThrough) through the calibrated table too."""
        move_via(self._arm, self._command(target), speed)

    def check_target(self, target: Pose) -> None:
        """Refused as move_linear would refuse it: through the calibrated table, then by the controller if it can
        check a target (ChecksTargets)."""
        command = self._command(target)
        if isinstance(self._arm, ChecksTargets):
            self._arm.check_target(command)

    def _command(self, target: Pose) -> Pose:
        """What the controller is sent for `target`: its nominal pose of the calibrated joints."""
        q = self.calibrated_joints(target)
        command = pose_of_matrix(self.nominal.forward(q) @ self.controller_tcp)
        if target.orientation is None:  # a tool-down target keeps its turn as given (350 deg stays 350)
            command = Pose(command.x, command.y, command.z, target.alpha + _wrap(command.alpha - target.alpha),
                           command.orientation)
        return command

    def pose(self) -> Pose:
        return pose_of_matrix(self.table.forward(self._arm.joints().positions) @ self.tcp)


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)
