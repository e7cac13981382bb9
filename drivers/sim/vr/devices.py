"""In-process fakes of the VR cell: a six-axis arm carrying the ORU and an operator who clicks model/image
point pairs, aligns the ORU by hand for a reference, and re-mounts cameras. The two cameras are
`drivers.sim.devices.SimCamera`, which renders any world.

Backends `sim-vr` in the world-kind table (drivers/sim/kinds.py). The operator's extra verbs are the
protocol `VrOperator` of calibration/routines/vr/_common.py.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz
from geometry.transforms import matrix_of

from drivers.interfaces import Frame, JointState, MotionRejected, Pose
from drivers.limits import WorkspaceBox
from drivers.sim.base import Strict
from drivers.sim.devices import SimDevice, SimOperator
from drivers.sim.vr.world import mounting_key


class VrArmSettings(Strict):
    limits: WorkspaceBox


class VrArm(SimDevice):
    """A six-axis arm holding the ORU; the tool frame is the ORU's nominal frame. Joints are not modelled:
    `joints()` reports the pose as (x, y, z, rx, ry, rz) (rotation vector)."""

    Settings = VrArmSettings

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._ready_to_move()
        self.settings.limits.check(Pose(target.x, target.y, target.z))
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
        self._count_move()
        self.world.move_arm(matrix_of(target))

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        if len(joints.positions) != 6:
            raise MotionRejected(f"{self.name}: expects 6 values (x, y, z, rx, ry, rz), got {len(joints.positions)}")
        x, y, z, *rv = joints.positions
        self.move_linear(Pose(x, y, z, orientation=quaternion_wxyz(Rotation.from_rotvec(rv))), speed)

    def pose(self) -> Pose:
        self._ready()
        T = self.world.commanded  # the controller reports what it was told: it cannot see its own errors
        R = Rotation.from_matrix(T[:3, :3])
        return Pose(*T[:3, 3], alpha=float(np.arctan2(T[1, 0], T[0, 0])), orientation=quaternion_wxyz(R))

    def joints(self) -> JointState:
        T = matrix_of(self.pose())
        return JointState((*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_rotvec()), ("x", "y", "z", "rx", "ry", "rz"))


class VrOperator(SimOperator):
    """Clicks, hand alignment and camera re-mounting done in the simulated world."""

    def click_points(self, camera: str, frame: Frame, obj: str, model_points, at_least: int = 5,
                     projected=None, edges=None):
        """Pairs (model point index, u, v) the operator clicked on `frame`; [] if fewer than `at_least` are seen.
        The simulated operator knows where the points are: it needs no overlay (`projected`, `edges`)."""
        self._ready()
        sim_name = frame.meta.get("sim_camera", camera)
        return self.world.clicks(sim_name, obj, np.asarray(model_points, float), at_least)

    def align_by_hand(self, arm, standoff_m: float) -> None:
        """Jog the arm until the ORU stands aligned `standoff_m` in front of the receptacle."""
        self._ready()
        T = self.world.hand_aligned_command(standoff_m)
        arm.move_linear(Pose(*T[:3, 3], orientation=quaternion_wxyz(Rotation.from_matrix(T[:3, :3]))))
        self.world.clock.advance(self.settings.seconds_per_request)

    def mount_camera(self, camera: str, inter_camera_angle_deg: float | None = None,
                     view_width_in: float | None = None, look_at_in=None) -> None:
        """Re-mount (and zoom, and aim) a camera for an experiment's viewing condition; nothing to do when it is
        mounted so already."""
        self._ready()
        if camera not in ("side", "top"):
            raise ValueError(f"{self.name}: no camera {camera!r} in the simulated VR cell (side, top)")
        if self.world.mounting.get(camera) == mounting_key(inter_camera_angle_deg, view_width_in, look_at_in):
            return
        self.world.place_camera(camera, inter_camera_angle_deg, view_width_in, look_at_in)
        self.world.clock.advance(self.settings.seconds_per_request)
