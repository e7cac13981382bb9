"""The simulated UR's joint angles: a UR5e's nominal kinematics (geometry/ur.py) mounted in the cell.

The cell's world moves a four-axis arm (x, y, z, alpha) whose flange pose is what the controller reports
as actual_TCP_pose (for a zero TCP offset), in the cell's frame, unchanged. A UR reports joint angles
too, so the simulator stands a UR5e in the cell and reports the angles that put its flange on that pose:

- the mounting: the UR's base frame sits at `base_xyz_mm` in the cell frame, turned `base_yaw_deg` about
  the vertical. The default, (-65, -390, 0) mm and 180 deg, puts the micro cell's work area 0.44 m in
  front of the base, where a UR5e works tool-down in the pose URSim 5.8 starts in
  (q = -92, -99, -126, -46, 91, -2 deg). Poses stay in the cell frame: forward kinematics here is
  T_cell = T_mount · FK_UR5e(q), and FK(q) composed with the TCP offset is actual_TCP_pose to ~1e-15 m;
- one branch: `BRANCH` (shoulder -1, elbow -1 "elbow up", wrist +1: q5 > 0), the branch of that URSim
  pose. With the tool vertical, wrist 2 stays at +90 deg, far from the wrist singularity; the
  shoulder and elbow singularities are out of the cell's reach;
- continuity: every angle comes from a closed form and is moved by whole turns to the value nearest a
  reference: q1..q5 nearest the configuration at the reference pose (0.14 m right of and 0.44 m in front
  of the base, 20 mm up, alpha 0), q6 nearest that configuration's q6 minus the change of alpha (a turn
  of the tool-down flange by +alpha about the vertical is a turn of -alpha about wrist 3's axis). q is
  thus a function of the pose alone: continuous along any move, the same whenever the arm comes back.
  Beyond alpha = +-360 deg of the cell box's extremes q6 can pass UR5e's +-360 deg by the few degrees
  that q1 differs from the reference; the simulator does not enforce joint limits.

Joint targets (moveJ, moveL_FK) must be on the branch and leave the tool pointing down (the four-axis
arm cannot tilt); a target out of the UR5e's reach from its base ends the control script with a script
error, as "inverse kinematics failed" stops a real program.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from geometry.ur import UR5E_DH, Branch, Unreachable, forward, inverse

from drivers.interfaces import Pose

BRANCH = Branch(shoulder=-1, elbow=-1, wrist=1)
REFERENCE_IN_BASE_M = (-0.14, -0.44, 0.02)  # where the reference configuration puts the flange, base frame
TILT_TOLERANCE_RAD = 1e-4
PATH_SAMPLES = 16  # a straight move is checked for reach at this many points along its way


def _rz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def tool_down_matrix(alpha: float) -> np.ndarray:
    """R = Rz(alpha) · Rx(180 deg): the tool pointing down, turned by alpha (geometry/orientation.py)."""
    c, s = math.cos(alpha), math.sin(alpha)
    return np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])


class UrKinematics:
    """Joint angles of a UR5e mounted in the cell for flange poses of the cell's arm, and back."""

    def __init__(self, base_xyz_m=(-0.065, -0.390, 0.0), base_yaw_rad: float = math.pi, dh=UR5E_DH,
                 branch: Branch = BRANCH):
        self.dh = dh
        self.branch = branch
        self.mount = np.eye(4)
        self.mount[:3, :3] = _rz(base_yaw_rad)
        self.mount[:3, 3] = [float(v) for v in base_xyz_m]
        self.mount_inv = np.eye(4)
        self.mount_inv[:3, :3] = self.mount[:3, :3].T
        self.mount_inv[:3, 3] = -self.mount[:3, :3].T @ self.mount[:3, 3]
        reference = np.eye(4)
        reference[:3, :3] = self.mount[:3, :3].T @ tool_down_matrix(0.0)  # the tool down, alpha 0 in the cell
        reference[:3, 3] = REFERENCE_IN_BASE_M
        self.reference_q = inverse(reference, branch, dh)
        self.reference_alpha = float(self.alpha_of(self.mount @ reference))
        self._joints = functools.lru_cache(maxsize=512)(self._joints_uncached)  # the 500 Hz cycle repeats poses

    # -- pose -> joints --------------------------------------------------------------------------------
    def flange_matrix(self, flange: Pose) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = tool_down_matrix(flange.alpha)
        T[:3, 3] = (flange.x, flange.y, flange.z)
        return T

    def near(self, alpha: float) -> np.ndarray:
        """The reference the angles are unwrapped to for a flange turned by alpha."""
        ref = self.reference_q.copy()
        ref[5] -= alpha - self.reference_alpha
        return ref

    def joints(self, flange: Pose) -> tuple[float, ...]:
        """q (rad) putting the flange on `flange` (tool down); Unreachable if the UR5e cannot."""
        return self._joints(float(flange.x), float(flange.y), float(flange.z), float(flange.alpha))

    def _joints_uncached(self, x: float, y: float, z: float, alpha: float) -> tuple[float, ...]:
        T = self.mount_inv @ self.flange_matrix(Pose(x, y, z, alpha))
        try:
            q = inverse(T, self.branch, self.dh, near=self.near(alpha))
        except Unreachable as exc:
            raise Unreachable(f"the flange pose ({x * 1e3:.3f}, {y * 1e3:.3f}, {z * 1e3:.3f}) mm, alpha "
                              f"{math.degrees(alpha):.3f} deg is out of the simulated UR5e's reach from its base at "
                              f"{self.describe_mount()}: {exc}") from None
        return tuple(float(v) for v in q)

    def check_path(self, start: Pose, target: Pose) -> None:
        """Unreachable unless every point of the straight move start -> target has joint angles."""
        for i in range(PATH_SAMPLES + 1):
            f = i / PATH_SAMPLES
            self.joints(Pose(*(a + f * (b - a) for a, b in ((start.x, target.x), (start.y, target.y),
                                                             (start.z, target.z), (start.alpha, target.alpha)))))

    # -- joints -> pose ----------------------------------------------------------------------------------
    def forward(self, q) -> np.ndarray:
        """The flange in the cell frame for joint angles q, 4x4: T_mount · FK_UR5e(q)."""
        values = [float(v) for v in q]
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"joints {values} are not six finite numbers")
        return self.mount @ forward(values, self.dh)

    @staticmethod
    def alpha_of(T: np.ndarray) -> float:
        return math.atan2(T[1, 0], T[0, 0])

    def flange_of_joints(self, q) -> Pose:
        """The four-axis arm's flange pose for joint angles q; ValueError if the tool would tilt or q is not
        on the simulator's branch (the arm could not report q back)."""
        T = self.forward(q)
        tilt = math.acos(min(max(-T[2, 2], -1.0), 1.0))
        if tilt > TILT_TOLERANCE_RAD:
            raise ValueError(f"joints {[round(v, 6) for v in q]} tilt the tool {math.degrees(tilt):.3f} deg from "
                             "vertical; this simulated arm only turns the tool about the vertical")
        q6 = float(q[5])
        # the alpha whose unwrapped q6 is the given one: q6 = ref6 - (alpha - ref_alpha) + whole turns
        alpha_mod = self.alpha_of(T)
        alpha_exact = float(self.reference_q[5]) + self.reference_alpha - q6
        alpha = alpha_exact + math.remainder(alpha_mod - alpha_exact, math.tau)
        flange = Pose(float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), alpha)
        back = self._joints_uncached(flange.x, flange.y, flange.z, flange.alpha)
        if max(abs(a - float(b)) for a, b in zip(back, q)) > 1e-6:
            reference = [round(float(v), 4) for v in self.near(alpha)]
            raise ValueError(f"joints {[round(float(v), 6) for v in q]} are not on this simulated UR's branch "
                             f"(shoulder {self.branch.shoulder:+d}, elbow {self.branch.elbow:+d}, wrist "
                             f"{self.branch.wrist:+d}, within half a turn of {reference}); the same flange pose "
                             f"there is {[round(v, 6) for v in back]}")
        return flange

    def describe_mount(self) -> str:
        x, y, z = (self.mount[:3, 3] * 1e3).round(3)
        return f"({x}, {y}, {z}) mm, turned {math.degrees(math.atan2(self.mount[1, 0], self.mount[0, 0])):.1f} deg"
