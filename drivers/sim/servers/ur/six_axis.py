"""The simulated UR's joint angles when a six-axis arm stands behind it (the hand-eye cell's UR5e).

The world's arm is then a UR5e itself (drivers/sim/ur5e_handeye: its fake reports the nominal forward kinematics
of its encoders, as a real controller does). The controller speaks for it with UR's published table and no
mounting: the base frame is the cell's. Joint targets go to the arm as joints; a pose target is solved on the
branch the arm is on, each angle the nearest turn to where it is, as the arm's own controller does. Poses carry
their full orientation; nothing is held tool-down.

The joints the controller reports are the arm's own after every move (asked once, then kept, as the controller
keeps the pose): the 500 Hz cycle never calls the arm.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz
from geometry.transforms import matrix_of
from geometry.ur import UR5E_DH, Unreachable, branch_of, forward, inverse

from drivers.interfaces import Pose


def pose_of_matrix(T: np.ndarray) -> Pose:
    return Pose(float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), math.atan2(T[1, 0], T[0, 0]),
                quaternion_wxyz(Rotation.from_matrix(T[:3, :3])))


class SixAxisKinematics:
    """The same questions UrKinematics answers, for an arm that is a UR5e."""

    six_axis = True

    def __init__(self, pose: Pose, q, dh=UR5E_DH):
        self.dh = dh
        self.remember(pose, q)

    def remember(self, pose: Pose, q) -> None:
        """Where the arm is after a move: its pose and its own joints."""
        self.pose, self.q = pose, tuple(float(v) for v in q)
        self.branch = branch_of(self.q, self.dh)

    def joints(self, flange: Pose) -> tuple[float, ...]:
        """q (rad) for the flange pose: the arm's own where it stands, else solved near them; Unreachable."""
        if flange == self.pose:
            return self.q
        try:
            q = inverse(matrix_of(flange), self.branch, self.dh, near=np.asarray(self.q))
        except Unreachable as exc:
            raise Unreachable(f"the flange pose ({flange.x * 1e3:.3f}, {flange.y * 1e3:.3f}, {flange.z * 1e3:.3f}) mm "
                              f"is out of the UR5e's reach on its present branch: {exc}") from None
        return tuple(float(v) for v in q)

    def check_path(self, start: Pose, target: Pose) -> None:
        """Unreachable unless the target has joint angles on the arm's branch."""
        self.joints(target)

    def forward(self, q) -> np.ndarray:
        values = [float(v) for v in q]
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"joints {values} are not six finite numbers")
        return forward(values, self.dh)

    def flange_of_joints(self, q) -> Pose:
        return pose_of_matrix(self.forward(q))

    def describe_mount(self) -> str:
        return "the cell's origin (a six-axis arm's base frame is the cell's)"
