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
from drivers.sim.kinds import check_runs_on


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


class SimArmSettings(Strict):
    limits: WorkspaceBox


class SimArm(SimDevice):
    """A 4-axis precision robot (x, y, z, alpha) with repeatability noise and systematic errors."""

    Settings = SimArmSettings

    def __init__(self, name, world, settings):
        super().__init__(name, world, settings)
        self._stop = threading.Event()

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._ready_to_move()
        self.settings.limits.check(target)
        if speed is not None and speed <= 0:
            raise MotionRejected(f"{self.name}: speed must be positive, got {speed}")
        self._count_move()
        self._stop.clear()
        if not self.world.move_arm(target, self._stop):
            raise MotionStopped(f"{self.name}: move stopped before reaching its target; the arm stands where it stopped")

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        if len(joints.positions) != 4:
            raise MotionRejected(f"{self.name}: expects 4 joints (x, y, z, alpha), got {len(joints.positions)}")
        x, y, z, alpha = joints.positions
        self.move_linear(Pose(x, y, z, alpha), speed)

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
        held = self.world.grip()
        loss = self.world.faults.vacuum_loss_after_grips
        if held and loss and self._calls > loss:
            self.world.release()
            raise VacuumLost(f"{self.name}: object lost after gripping (simulated); check the nozzle and the part")
        return held

    def release(self) -> None:
        self._ready()
        self._vacuum_on = False
        self.world.release()

    def status(self) -> GripperStatus:
        self._ready()
        held = self.world.held is not None
        vacuum = self.settings.vacuum_kpa if (held and self._vacuum_on) else (5.0 if self._vacuum_on else 0.0)
        return GripperStatus(vacuum, held, self._vacuum_on)

    def stop(self) -> None:
        """A vacuum gripper is left as it is: dropping a held part is not 'safe'."""


class SimCameraSettings(Strict):
    sim_camera: str | None = Field(None, description="camera of the sim section; default: the device name")


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

    @property
    def resolution(self) -> tuple[int, int]:
        return tuple(self.world.config.cameras[self.sim_name].resolution_px)

    def capture(self, timeout_s: float = 2.0) -> Frame:
        self._ready()
        self._calls += 1
        faults = self.world.faults
        if faults.camera_timeout_after_captures and self._calls > faults.camera_timeout_after_captures:
            self.world.clock.advance(timeout_s)
            raise CaptureTimeout(f"{self.name}: no frame within {timeout_s} s (simulated); check the trigger and cable")
        self._frame_id += 1
        image = self.world.capture(self.sim_name, self._frame_id)
        if faults.corrupt_frame_every and self._calls % faults.corrupt_frame_every == 0:
            raise CorruptFrame(f"{self.name}: frame {self._frame_id} arrived truncated (simulated)")
        t = self.world.clock.now()
        cfg = self.world.config.cameras[self.sim_name]
        return Frame(image, self.name, self._frame_id, t, t, cfg.exposure_ms * 1e-3, {"sim_camera": self.sim_name})


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
