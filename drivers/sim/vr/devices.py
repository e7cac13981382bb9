"""In-process fakes of the VR cell: a six-axis arm carrying the ORU, the two cameras, and an operator
who clicks model/image point pairs, aligns the ORU by hand for a reference, and re-mounts cameras.

Backends `sim-vr` in drivers/registry.py. The operator's extra verbs are the
protocol `VrOperator` of calibration/routines/vr_common.py.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz
from geometry.transforms import matrix_of

from ...interfaces import (
    ConnectionLost,
    DeviceState,
    Frame,
    JointState,
    MotionRejected,
    NotConnected,
    Pose,
)
from ...limits import WorkspaceBox
from .world import VrWorld, mounting_key


class _VrDevice:
    Settings: type[BaseModel]

    def __init__(self, name: str, world: VrWorld, settings):
        self.name = name
        self.world = world
        self.settings = settings
        self._state = DeviceState.CREATED

    @classmethod
    def create(cls, name: str, options: dict, context):
        world = context.sim_world()
        if not isinstance(world, VrWorld):
            raise ValueError(f"{name}: backend 'sim-vr' needs a 'sim:' section with world: vr")
        return cls(name, world, cls.Settings(**options))

    @property
    def state(self) -> DeviceState:
        return self._state

    @property
    def clock(self):
        return self.world.clock

    def connect(self) -> None:
        self._state = DeviceState.READY

    def close(self) -> None:
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        """Nothing keeps moving between calls in the simulation."""

    def _ready(self) -> None:
        if self._state is DeviceState.FAULTED:
            raise ConnectionLost(f"{self.name}: the link is down; reconnect the device before going on")
        if self._state is not DeviceState.READY:
            raise NotConnected(f"{self.name}: not connected (state {self._state.value}); call connect() first")


class VrArmSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    limits: WorkspaceBox


class VrArm(_VrDevice):
    """A six-axis arm holding the ORU; the tool frame is the ORU's nominal frame. Joints are not modelled:
    `joints()` reports the pose as (x, y, z, rx, ry, rz) (rotation vector)."""

    Settings = VrArmSettings

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._ready()
        self.settings.limits.check(Pose(target.x, target.y, target.z))
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
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


class VrCameraSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    sim_camera: str | None = Field(None, description="'side' or 'top'; default: the device name")


class VrCameraDevice(_VrDevice):
    Settings = VrCameraSettings

    def __init__(self, name, world, settings):
        super().__init__(name, world, settings)
        self.sim_name = settings.sim_camera or name
        if self.sim_name not in ("side", "top"):
            raise ValueError(f"camera {name!r}: sim_camera must be 'side' or 'top', got {self.sim_name!r}")
        self._frame_id = 0

    @property
    def resolution(self) -> tuple[int, int]:
        return tuple(self.world.config.cameras[self.sim_name].resolution_px)

    def capture(self, timeout_s: float = 2.0) -> Frame:
        self._ready()
        self._frame_id += 1
        image = self.world.capture(self.sim_name, self._frame_id)
        t = self.world.clock.now()
        return Frame(image, self.name, self._frame_id, t, t, 0.01, {"sim_camera": self.sim_name})


class VrOperatorSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    seconds_per_request: float = Field(30.0, ge=0, le=3600)


class VrOperator(_VrDevice):
    """Clicks, hand alignment and camera re-mounting done in the simulated world."""

    Settings = VrOperatorSettings

    def request(self, instruction: str, fixture: str | None = None, present: bool | None = None) -> None:
        self._ready()
        self.world.clock.advance(self.settings.seconds_per_request)

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
