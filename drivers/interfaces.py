"""The small interfaces every driver implements, their value types and typed errors.

Capabilities are `typing.Protocol`s: a backend is anything with the right methods,
a real controller adapter or a simulated fake alike. Units are SI (metres,
radians, seconds); pixels follow OpenCV (integer coordinates at pixel centres).

Lifecycle, as in ros2_control: a device is built from its configuration without
touching hardware, `connect()` brings it to ready, `close()` releases it. `stop()`
is always safe: idempotent, callable in any state, never raises for "not moving".
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


class DeviceState(str, enum.Enum):
    CREATED = "created"
    READY = "ready"
    FAULTED = "faulted"
    CLOSED = "closed"


# --- value types -----------------------------------------------------------


@dataclass(frozen=True)
class Pose:
    """A tool pose for a SCARA-like arm: position (m) and rotation about the vertical axis (rad).

    Six-axis arms use `orientation` (quaternion w, x, y, z); four-axis arms leave it None
    and use `alpha`.
    """

    x: float
    y: float
    z: float
    alpha: float = 0.0
    orientation: tuple[float, float, float, float] | None = None

    @property
    def xyz(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])


@dataclass(frozen=True)
class JointState:
    positions: tuple[float, ...]  # rad or m per joint
    names: tuple[str, ...] = ()


@dataclass(frozen=True)
class Frame:
    """One captured image with where and when it came from."""

    image: np.ndarray
    camera_id: str
    frame_id: int
    device_timestamp_s: float | None  # the camera's own clock, if it has one
    host_timestamp_s: float  # the host (or simulated cell) clock at capture
    exposure_s: float | None = None
    meta: dict = field(default_factory=dict)


@dataclass(frozen=True)
class GripperStatus:
    vacuum_kpa: float  # relative vacuum below atmosphere
    object_detected: bool
    gripping: bool


# --- typed errors -----------------------------------------------------------


class DeviceError(Exception):
    """Base of every driver error. The message says what failed and what to do."""


class ConnectionLost(DeviceError):
    """The link to the device dropped; reconnect (operator action) before going on."""


class MotionRejected(DeviceError):
    """A target outside the configured limits: refused before anything moved."""


class MotionStopped(DeviceError):
    """stop() ended a move before its target; the arm is standing where it stopped."""


class ProtectiveStop(DeviceError):
    """The controller stopped the arm for safety; it must be cleared on the controller."""


class VacuumLost(DeviceError):
    """An object held by the gripper was lost."""


class CaptureTimeout(DeviceError):
    """No frame arrived within the capture time-out."""


class CorruptFrame(DeviceError):
    """A frame arrived but its content is unusable (wrong size, truncated)."""


class NotConnected(DeviceError):
    """A command reached a device that is not connected (call connect() first)."""


# --- the lifecycle check every driver makes before a call --------------------


def not_ready_error(name: str, state: DeviceState, lost: str) -> DeviceError:
    """Why device `name` in `state` (not READY) cannot take a call: ConnectionLost after a lost link
    (`lost` says what went down and what to do), else NotConnected."""
    if state is DeviceState.FAULTED:
        return ConnectionLost(f"{name}: {lost}")
    return NotConnected(f"{name}: not connected (state {state.value}); call connect() first")


def require_ready(name: str, state: DeviceState, lost: str) -> None:
    """Raise `not_ready_error` unless the device is READY."""
    if state is not DeviceState.READY:
        raise not_ready_error(name, state, lost)


# --- capabilities -----------------------------------------------------------


@runtime_checkable
class Device(Protocol):
    name: str

    @property
    def state(self) -> DeviceState: ...

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def stop(self) -> None: ...


@runtime_checkable
class Arm(Device, Protocol):
    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        """Move to `target` and return once settled. Raises MotionRejected before moving."""

    def move_joints(self, joints: JointState, speed: float | None = None) -> None: ...

    def pose(self) -> Pose:
        """The pose the controller reports (encoder feedback), not the commanded one."""

    def joints(self) -> JointState: ...


@runtime_checkable
class SpeedLimited(Protocol):
    """An optional arm capability: the fastest tool speed (m/s) it will be asked for, its own setting. Manual
    moves go at a fraction of it (cellctl/core/manual.py)."""

    @property
    def max_speed_m_s(self) -> float: ...


@runtime_checkable
class MovesThrough(Protocol):
    """An optional arm capability: a linear move to a via point, a place the arm only passes on its way (over a
    part before going down onto it, up again after): it returns once there without waiting to settle, as a
    controller's blend zone does; nothing is measured or gripped at a via point. `move_via` falls back to
    `move_linear` (settled) for an arm without it. A wrapper that changes the targets it forwards must define it
    itself, so that a via point goes through its change too."""

    def move_through(self, target: Pose, speed: float | None = None) -> None: ...


def move_via(arm, target: Pose, speed: float | None = None) -> None:
    """Move to a via point (MovesThrough), or settled where the arm cannot pass without stopping."""
    if isinstance(arm, MovesThrough):
        arm.move_through(target, speed)
    else:
        arm.move_linear(target, speed)


@runtime_checkable
class ChecksTargets(Protocol):
    """An optional arm capability: would a linear move to `target` be refused (outside the box, out of reach,
    beyond a joint limit on the arm's present branch)? MotionRejected saying why, as the move would, and nothing
    moves. For a path checked whole before its first move (cellctl/core/manual.py)."""

    def check_target(self, target: Pose) -> None: ...


@runtime_checkable
class Gripper(Device, Protocol):
    def grip(self) -> bool:
        """Switch vacuum on; True when an object is detected."""

    def release(self) -> None: ...

    def status(self) -> GripperStatus: ...


@runtime_checkable
class Camera(Device, Protocol):
    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    def capture(self, timeout_s: float = 2.0) -> Frame: ...


@runtime_checkable
class Operator(Device, Protocol):
    """The person at the cell, for what the robot cannot do itself (lay a calibration grid, clear a jam).

    `request` returns once the operator has done it; a simulated operator does it in the world."""

    def request(self, instruction: str, fixture: str | None = None, present: bool | None = None) -> None: ...


@runtime_checkable
class CellClock(Protocol):
    """How long the cell has been working: wall time on a real cell, simulated time in sim."""

    def now(self) -> float: ...
