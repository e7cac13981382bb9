"""Simulated fakes of the Arm, Gripper, Camera and Operator interfaces, and the base every world's fakes share.

They behave like devices, not mirrors: moves take (simulated) time and are
refused outside the workspace box, connections can drop, captures can time out
or come back corrupt, a pick succeeds only where a sphere lies. The fault knobs
(the world's `faults`, SimFaults) work the same way on every world's fakes.
"""

from __future__ import annotations

import threading

from pydantic import BaseModel, Field

from drivers.interfaces import (
    CaptureTimeout,
    ConnectionLost,
    CorruptFrame,
    DeviceState,
    Frame,
    GripperStatus,
    JointState,
    MotionRejected,
    MotionStopped,
    Pose,
    ProtectiveStop,
    VacuumLost,
)
from drivers.lifecycle import Driver
from drivers.limits import WorkspaceBox
from drivers.sim.base import SimWorld, Strict
from drivers.sim.fault_dice import drawn
from drivers.sim.kinds import check_runs_on
from drivers.sim.render import expose

SIM_EXPOSURE_S = (1e-5, 10.0)  # what a simulated camera's exposure_s may be set to (s)
SIM_GAIN_DB = (0.0, 48.0)  # and its gain_db


class SimDevice(Driver):
    """Lifecycle, state and fault injection of a fake on a simulated world."""

    Settings: type[BaseModel]
    LINK_LOST = "the link is down; reconnect the device before going on"

    def __init__(self, name: str, world: SimWorld, settings):
        check_runs_on(type(self), name, world)
        super().__init__(name, settings)
        self.world = world
        self._calls = 0
        self._protective_stop = False

    @classmethod
    def create(cls, name: str, options: dict, context) -> "SimDevice":
        return cls(name, context.sim_world(), cls.Settings(**options))

    @property
    def clock(self):
        return self.world.clock

    def connect(self) -> None:
        self._state = DeviceState.READY

    def close(self) -> None:
        self.stop()
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        """Nothing keeps moving between calls in the simulation; always safe."""

    def _fault(self, error: Exception) -> Exception:
        self._state = DeviceState.FAULTED
        return error

    # -- the fault knobs of an arm: checked before its move is checked, counted once it is accepted -------------
    def _ready_to_move(self) -> None:
        self._ready()
        if self._protective_stop:
            raise ProtectiveStop(f"{self.name}: in protective stop; clear it on the controller")

    def _count_move(self) -> None:
        self._calls += 1
        faults = self.world.faults
        if faults.arm_drop_after_moves and self._calls > faults.arm_drop_after_moves:
            raise self._fault(ConnectionLost(f"{self.name}: connection lost (simulated after {faults.arm_drop_after_moves} moves)"))
        if faults.protective_stop_after_moves and self._calls > faults.protective_stop_after_moves:
            self._protective_stop = True
            raise ProtectiveStop(f"{self.name}: protective stop (simulated); clear it on the controller")
        fault = drawn(faults.random, "move")
        if fault == "link_drop":
            raise self._fault(ConnectionLost(f"{self.name}: connection lost (simulated at random)"))
        if fault == "protective_stop":
            self._protective_stop = True
            raise ProtectiveStop(f"{self.name}: protective stop (simulated at random); clear it on the controller")


class SimArmSettings(Strict):
    limits: WorkspaceBox


class SimArm(SimDevice):
    """A 4-axis precision robot (x, y, z, alpha) with repeatability noise and systematic errors."""

    Settings = SimArmSettings

    def __init__(self, name, world, settings):
        super().__init__(name, world, settings)
        self._stop = threading.Event()

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._move(target, speed, settle=True)

    def move_through(self, target: Pose, speed: float | None = None) -> None:
        """To a via point: the move's time is counted, its settling is not (MovesThrough)."""
        self._move(target, speed, settle=False)

    def _move(self, target: Pose, speed: float | None, settle: bool) -> None:
        self._ready_to_move()
        self.settings.limits.check(target)
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
        self._count_move()
        self._stop.clear()
        if not self.world.move_arm(target, self._stop, speed, settle=settle):
            raise MotionStopped(f"{self.name}: move stopped before reaching its target; the arm stands where it stopped")

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        if len(joints.positions) != 4:
            raise MotionRejected(f"{self.name}: expects 4 joints (x, y, z, alpha), got {len(joints.positions)}")
        x, y, z, alpha = joints.positions
        self.move_linear(Pose(x, y, z, alpha), speed)

    @property
    def max_speed_m_s(self) -> float:
        return self.world.config.motion.speed_mm_s * 1e-3

    def check_target(self, target: Pose) -> None:
        self._ready_to_move()
        self.settings.limits.check(target)

    def pose(self) -> Pose:
        self._ready()
        return self.world.reported_pose()

    def joints(self) -> JointState:
        p = self.pose()
        return JointState((p.x, p.y, p.z, p.alpha), ("x", "y", "z", "alpha"))

    def stop(self) -> None:
        self._stop.set()

    def wall_seconds(self, start: Pose, target: Pose) -> float:
        """Wall time a move will take (a protocol simulator shows the arm moving meanwhile); 0 if moves are instant."""
        return self.world.motion_time(start, target) * self.world.clock.realtime_factor


class SimGripperSettings(Strict):
    vacuum_kpa: float = Field(60.0, gt=0, le=100, description="vacuum reached with an object sealed")


class SimGripper(SimDevice):
    """A vacuum nozzle: grips a sphere lying under its tip, detects it by the vacuum level."""

    Settings = SimGripperSettings

    def __init__(self, name, world, settings):
        super().__init__(name, world, settings)
        self._vacuum_on = False

    def grip(self) -> bool:
        self._ready()
        self._calls += 1
        self._vacuum_on = True
        if self.world.faults.gripper_no_air:
            return False
        if self.world.faults.gripper_blocked:  # the vacuum builds on the blocked nozzle as on a part
            return True
        held = self.world.grip()
        loss = self.world.faults.vacuum_loss_after_grips
        lost = held and drawn(self.world.faults.random, "grip")
        if held and ((loss and self._calls > loss) or lost):
            self.world.release()
            raise VacuumLost(f"{self.name}: object lost after gripping (simulated); check the nozzle and the part")
        return held

    def release(self) -> None:
        self._ready()
        self._vacuum_on = False
        self.world.release()

    def status(self) -> GripperStatus:
        self._ready()
        faults = self.world.faults
        held = self.world.held is not None or (faults.gripper_blocked and self._vacuum_on)
        vacuum = self.settings.vacuum_kpa if (held and self._vacuum_on) else (5.0 if self._vacuum_on else 0.0)
        if faults.gripper_no_air:
            vacuum, held = 0.0, self.world.held is not None
        return GripperStatus(vacuum, held, self._vacuum_on)

    def stop(self) -> None:
        """A vacuum gripper is left as it is: dropping a held part is not 'safe'."""


class SimCameraSettings(Strict):
    sim_camera: str | None = Field(None, description="camera of the sim section; default: the device name")
    exposure_s: float | None = Field(None, ge=SIM_EXPOSURE_S[0], le=SIM_EXPOSURE_S[1],
                                     description="exposure time; the frame's light scales with it (default: the "
                                     "sim camera's exposure_ms, at which it renders its nominal levels)")
    gain_db: float = Field(0.0, ge=SIM_GAIN_DB[0], le=SIM_GAIN_DB[1],
                           description="sensor gain in dB: the frame's levels times 10^(gain_db / 20)")


class SimCamera(SimDevice):
    """Renders the world as the true camera sees it, on any kind of world; each frame names its camera of the
    sim section (meta "sim_camera")."""

    Settings = SimCameraSettings

    def __init__(self, name, world, settings):
        super().__init__(name, world, settings)
        self.sim_name = settings.sim_camera or name
        if self.sim_name not in world.config.cameras:
            known = ", ".join(sorted(world.config.cameras)) or "none"
            raise ValueError(f"camera {name!r}: no sim.cameras.{self.sim_name} in the cell file (defined: {known})")
        self._frame_id = 0
        self._exposure_s = settings.exposure_s  # None: the sim camera's nominal exposure
        self._gain_db = settings.gain_db

    @property
    def resolution(self) -> tuple[int, int]:
        return tuple(self.world.config.cameras[self.sim_name].resolution_px)

    # -- exposure and gain, changed live (drivers/cameras/live.py) -----------------------------------------
    @property
    def nominal_exposure_s(self) -> float:
        return self.world.config.cameras[self.sim_name].exposure_ms * 1e-3

    def live_specs(self):
        from drivers.cameras.live import LiveSetting

        return [LiveSetting("exposure_s", "exposure", "s", *SIM_EXPOSURE_S),
                LiveSetting("gain_db", "gain", "dB", *SIM_GAIN_DB)]

    def live_values(self) -> dict:
        return {"exposure_s": self._exposure_s if self._exposure_s is not None else self.nominal_exposure_s,
                "gain_db": self._gain_db}

    def set_live(self, values: dict) -> dict:
        from drivers.cameras.live import checked

        self._ready()
        values = checked(self.name, self.live_specs(), values)
        if "exposure_s" in values:
            self._exposure_s = values["exposure_s"]
        if "gain_db" in values:
            self._gain_db = values["gain_db"]
        return self.live_values()

    @property
    def brightness(self) -> float:
        """How much more light than nominal each pixel collects (exposure) times the gain."""
        exposure = self._exposure_s if self._exposure_s is not None else self.nominal_exposure_s
        return exposure / self.nominal_exposure_s * 10 ** (self._gain_db / 20)

    def capture(self, timeout_s: float = 2.0) -> Frame:
        self._ready()
        self._calls += 1
        faults = self.world.faults
        fault = drawn(faults.random, "capture")
        if fault == "capture_timeout" or (faults.camera_timeout_after_captures
                                          and self._calls > faults.camera_timeout_after_captures):
            self.world.clock.advance(timeout_s)
            raise CaptureTimeout(f"{self.name}: no frame within {timeout_s} s (simulated); check the trigger and cable")
        self._frame_id += 1
        image = _optics_faults(self.world.capture(self.sim_name, self._frame_id), faults, self.name)
        if fault == "corrupt_frame" or (faults.corrupt_frame_every and self._calls % faults.corrupt_frame_every == 0):
            raise CorruptFrame(f"{self.name}: frame {self._frame_id} arrived truncated (simulated)")
        t = self.world.clock.now()
        meta = {"sim_camera": self.sim_name}
        if self._exposure_s is not None or self._gain_db:  # as the cell file (or the live view) sets them
            image = expose(image, self.brightness)
            meta["gain_db"] = self._gain_db
        exposure = self._exposure_s if self._exposure_s is not None else self.nominal_exposure_s
        return Frame(image, self.name, self._frame_id, t, t, exposure, meta)


def _optics_faults(image, faults, camera: str):
    """The knobs of a camera's lens and exposure (SimFaults camera_scale, camera_blur_px, camera_gain), on its
    rendered image; the image itself when none is set for it."""
    scale, blur, gain = (getattr(faults, knob).get(camera) for knob in ("camera_scale", "camera_blur_px",
                                                                         "camera_gain"))
    if scale is None and not blur and gain is None:
        return image
    import cv2
    import numpy as np

    full = np.iinfo(image.dtype).max
    out = image.astype(np.float32)
    if scale is not None and scale != 1.0:
        h, w = out.shape[:2]
        about = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), 0.0, scale)
        out = cv2.warpAffine(out, about, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    if blur:
        out = cv2.GaussianBlur(out, (0, 0), sigmaX=blur)
    if gain is not None:
        out *= np.float32(gain)
    return np.clip(out + 0.5, 0, full).astype(image.dtype)


class SimOperatorSettings(Strict):
    seconds_per_request: float = Field(30.0, ge=0, le=3600, description="cell time an operator action takes")


class SimOperator(SimDevice):
    """Does what it is asked in the simulated world: lays or removes a fixture."""

    Settings = SimOperatorSettings

    def request(self, instruction: str, fixture: str | None = None, present: bool | None = None) -> None:
        self._ready()
        if fixture is not None and present is not None:
            self.world.set_fixture(fixture, present)
        self.world.clock.advance(self.settings.seconds_per_request)
