"""The simulated UR controller when a six-axis arm stands behind it (the hand-eye cell's UR5e).

The world's arm is then a UR5e itself (drivers/sim/ur5e_handeye: `SimUr5eArm`, served by an ArmHost). The
controller speaks for it with UR's published table and no mounting (the base frame is the cell's), computing what
the in-process fake computes, with the same functions (geometry/ur_controller.py):

- moveJ: the joints given, checked against the controller's joint limits (the UR5e's +-360 deg, which the
  primary interface reports); the arm is sent those joints;
- moveL, moveJ_IK (a pose) and moveL_FK (the pose of joints): the controller's nominal inverse kinematics on the
  branch the arm is on, each angle the nearest turn to where it is; the arm is sent the joints it found;
- a target that fails either (out of reach on the branch, outside the limits) is a script error before anything
  moves, as "inverse kinematics failed" or a joint limit stops a real program; what the arm itself refuses (its
  reach, its workspace box) becomes one when the arm says so, also before it moved;
- actual_q is the arm's reported encoder joints, asked after every move (the 500 Hz cycle never calls the arm),
  and actual_TCP_pose the nominal forward kinematics of those joints composed with the TCP offset: a real UR cannot
  see its own geometry errors. With a zero TCP offset this is, to the bit, the pose the in-process fake reports.

Poses carry their full orientation; nothing is held tool-down.
"""

from __future__ import annotations

import numpy as np

from geometry.transforms import matrix_of
from geometry.ur import JOINT_NAMES, UR5E_DH, UR5E_LIMITS_RAD, Unreachable, forward
from geometry.ur_controller import (
    flange_of_tcp,
    linear_joints,
    outside_limits,
    pose_parts,
    six_finite,
    tcp_pose,
    ur_pose_of_matrix,
)

from drivers.interfaces import Pose

MOVE_NAMES = {1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK"}


def pose_of_matrix(T: np.ndarray) -> Pose:
    """The Pose the arm reports for a flange at T (through the UR pose, as the fake and the driver both do)."""
    return Pose(*pose_parts(ur_pose_of_matrix(T)))


class SixAxisKinematics:
    """The questions the controller asks of its kinematics (as of UrKinematics), for an arm that is a UR5e."""

    six_axis = True

    def __init__(self, pose: Pose, q, dh=UR5E_DH, limits=UR5E_LIMITS_RAD):
        self.dh = dh
        self.limits = limits
        self.target: tuple[Pose, tuple[float, ...]] | None = None  # the move under way: its pose and joints
        self.remember(pose, q)

    def remember(self, pose: Pose, q) -> None:
        """Where the arm is after a move: its reported pose and its own joints."""
        self.pose, self.q = pose, tuple(float(v) for v in q)
        self.target = None

    # -- moves -------------------------------------------------------------------------------------------
    def move_target(self, cmd: int, args, tcp) -> tuple[Pose, tuple[float, ...]]:
        """(flange pose, joints) a move command goes to; ValueError (Unreachable is one) naming what is wrong,
        before anything moves."""
        name = MOVE_NAMES[cmd]
        if cmd == 1:
            q = self._within_limits(six_finite(args, f"{name} target"), name)
            T = forward(q, self.dh)
        else:
            T = forward(six_finite(args, f"{name} joints"), self.dh) if cmd == 4 else flange_of_tcp(args, tcp)
            try:
                found = linear_joints(T, self.q, self.dh)
            except Unreachable as exc:
                x, y, z = (T[:3, 3] * 1e3).tolist()
                raise Unreachable(f"{name}: the flange pose ({x:.3f}, {y:.3f}, {z:.3f}) mm is out of the UR5e's "
                                  f"reach on its present branch: {exc}; nothing moved") from None
            q = self._within_limits(tuple(float(v) for v in found), name)
        self.target = (pose_of_matrix(T), q)
        return self.target

    def _within_limits(self, q: tuple[float, ...], name: str) -> tuple[float, ...]:
        problem = outside_limits(q, self.limits, JOINT_NAMES)
        if problem:
            raise ValueError(f"{name}: {problem}; nothing moved")
        return q

    # -- what the controller reports ----------------------------------------------------------------------
    def joints(self, flange: Pose) -> tuple[float, ...]:
        """q (rad) for a flange pose: the arm's own where it stands, a move's own target joints, else solved near
        where it stands (Unreachable if they cannot be)."""
        for pose, q in ((self.pose, self.q), self.target or (None, None)):
            if flange == pose:
                return q
        try:
            return tuple(float(v) for v in linear_joints(matrix_of(flange), self.q, self.dh))
        except Unreachable as exc:
            raise Unreachable(f"the flange pose ({flange.x * 1e3:.3f}, {flange.y * 1e3:.3f}, {flange.z * 1e3:.3f}) "
                              f"mm is out of the UR5e's reach on its present branch: {exc}") from None

    def tcp_pose(self, flange: Pose, tcp) -> tuple[float, ...]:
        """actual_TCP_pose: the nominal forward kinematics of the flange's joints composed with the TCP offset."""
        return tcp_pose(self.joints(flange), tcp, self.dh)

    def check_path(self, start: Pose, target: Pose) -> None:
        """Unreachable unless the target has joint angles on the arm's branch."""
        self.joints(target)

    def forward(self, q) -> np.ndarray:
        values = six_finite(q, "joints")
        return forward(values, self.dh)

    def flange_of_joints(self, q) -> Pose:
        return pose_of_matrix(self.forward(q))

    def describe_mount(self) -> str:
        return "the cell's origin (a six-axis arm's base frame is the cell's)"
