"""The simulated UR controller's state: modes, registers, TCP, and the arm it moves.

The arm behind the controller is the cell's simulated arm, local or in another process
(see `drivers/sim/remote.py`). When it is a UR5e itself (the hand-eye cell: its pose has
an orientation), the controller moves it by its joints and reports them, as six_axis.py
says. When it is the micro cell's 4-axis arm (x, y, z, alpha), the controller speaks for
it as a six-axis UR would:

- poses are UR poses [x, y, z, rx, ry, rz] (metres, rotation vector) of the TCP, in the
  cell's frame; the flange is the arm's pose with the tool-down orientation
  R = Rz(alpha)·Rx(180°) of `geometry/orientation.py`, and the TCP is the flange moved
  by the `setTcp` offset;
- joints are a UR5e's: the angles (rad) that put a UR5e's flange on the arm's flange pose,
  through its nominal kinematics (geometry/ur.py) with its base mounted in the cell at
  `base_xyz_mm`, `base_yaw_deg`, on one inverse-kinematics branch, continuous along
  every move (`kinematics.py` says which branch and why). Forward kinematics of the
  reported q composed with the TCP offset is the reported TCP pose; moveJ takes the same
  angles;
- a target the four-axis arm cannot reach (tilted tool, joints off the branch) or the
  UR5e cannot reach from its base stops the control script with a script error, as a
  UR stops on an unreachable pose;
- the arm's own faults become the controller's: its ProtectiveStop a protective stop
  (safety mode 3, program paused), a refused target a script error;
- while a move takes wall time (the world's realtime_factor > 0) the reported pose runs
  along the straight line at the time fraction, as the world moves the arm, and freezes
  when a stop is requested; the arm's own report replaces it when the move returns.

The arm is called only to execute a move (never while answering a handshake): a
client in another process may hold its GIL inside a ur_rtde constructor, and a call
back into that process then would deadlock. The pose is cached after every move.
With a TCP offset of zero (the default) the TCP pose is the arm's pose.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from typing import Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from geometry.ur import Unreachable
from geometry.ur_controller import matrix_of_rotvec, rotvec_of_matrix

from drivers.interfaces import (
    ConnectionLost,
    JointState,
    MotionRejected,
    MotionStopped,
    Pose,
    ProtectiveStop,
)
from drivers.sim.base import MotionTimed
from drivers.sim.servers.ur.kinematics import UrKinematics
from drivers.sim.servers.ur.six_axis import SixAxisKinematics

log = logging.getLogger(__name__)

# robot modes (RTDE robot_mode, dashboard "Robotmode: ...")
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
POWER_OFF, IDLE, RUNNING = 3, 5, 7
# safety modes (RTDE safety_mode, dashboard "Safetymode: ...")
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT"}
NORMAL, PROTECTIVE_STOP = 1, 3
# runtime states (RTDE runtime_state)
STOPPING, STOPPED, PLAYING, PAUSING, PAUSED, RESUMING = range(6)
# safety_status_bits
BIT_NORMAL, BIT_PROTECTIVE_STOPPED = 0, 2
# robot_status_bits
BIT_POWER_ON, BIT_PROGRAM_RUNNING = 0, 1

TILT_TOLERANCE_RAD = 1e-4


@runtime_checkable
class ArmSource(Protocol):
    """What the controller needs of the arm: the in-process SimArm or a RemoteArm."""

    def move_linear(self, target: Pose, speed: float | None = None) -> None: ...

    def pose(self) -> Pose: ...

    def stop(self) -> None: ...


class UrSimFaults(BaseModel):
    """Fault knobs of the UR simulator (all off by default)."""

    model_config = ConfigDict(extra="forbid")

    drop_after_commands: int | None = Field(None, ge=1, description="close every connection when command N+1 "
                                            "arrives (once; the command is lost)")
    outage_s: float = Field(1.0, ge=0, le=60, description="after a drop, connections are refused this long")
    protective_stop_after_moves: int | None = Field(None, ge=1, description="move N+1 ends in a protective stop")
    slow_reply_s: float = Field(0.0, ge=0, le=60, description="delay before every dashboard reply (or only "
                                "those to slow_requests)")
    slow_requests: tuple[str, ...] | None = Field(None, description="the dashboard requests slow_reply_s delays, "
                                                  "e.g. ['unlock protective stop'] (case and outer blanks ignored); "
                                                  "default: every request")
    malformed_after_packets: int | None = Field(None, ge=1, description="RTDE data package N+1 has a broken header")
    silent_after_packets: int | None = Field(None, ge=1, description="after N data packages a connection gets no "
                                             "more (its socket stays open and keeps answering requests): a stalled "
                                             "controller or network, seen by the client only as missing data")


class UrSimOptions(BaseModel):
    """How the simulated controller presents itself. A fault knob may also be given by its own name
    (`slow_reply_s: 0.3` for `faults: {slow_reply_s: 0.3}`), as the other simulators take theirs."""

    model_config = ConfigDict(extra="forbid")

    version: tuple[int, int, int, int] = Field((5, 15, 0, 0), description="controller version; major >= 5: 500 Hz")
    serial_number: str = Field("20235500001", pattern=r"^\d+$")
    robot_model: str = Field("UR5", description="the dashboard's 'get robot model' (a UR5e answers UR5)")
    powered: bool = Field(True, description="start powered on with brakes released (robot mode RUNNING)")
    remote_control: bool = True
    unlock_delay_s: float = Field(5.0, ge=0, le=60, description="a protective stop can be unlocked after this")
    base_xyz_mm: tuple[float, float, float] = Field((-65.0, -390.0, 0.0), description="where the UR5e's base "
                                                    "frame sits in the cell frame (its joint angles follow from it)")
    base_yaw_deg: float = Field(180.0, ge=-360, le=360, description="the base frame's turn about the vertical")
    faults: UrSimFaults = UrSimFaults()

    @model_validator(mode="before")
    @classmethod
    def _flat_fault_knobs(cls, data):
        if not isinstance(data, dict):
            return data
        knobs = {k: data[k] for k in data if k in UrSimFaults.model_fields}
        if not knobs:
            return data
        rest = {k: v for k, v in data.items() if k not in knobs}
        faults = rest.get("faults") or {}
        if isinstance(faults, UrSimFaults):
            faults = faults.model_dump(exclude_unset=True)
        if not isinstance(faults, dict):
            return data  # let the field's own validation name the problem
        return {**rest, "faults": {**faults, **knobs}}


def allowed_options() -> str:
    """The options a UR simulator takes, for error messages."""
    settings = [name for name in UrSimOptions.model_fields if name != "faults"]
    return f"{', '.join(settings)}; fault knobs: {', '.join(UrSimFaults.model_fields)} (or faults: {{KNOB: VALUE}})"


def parse_options(options) -> UrSimOptions:
    """UrSimOptions from a dict (a cell file's options, `cellctl sim --option`s): ValueError naming each unknown
    or bad option and listing the allowed ones."""
    if isinstance(options, UrSimOptions):
        return options
    if options is not None and not isinstance(options, dict):
        raise ValueError(f"UR simulator options must be a mapping, got {options!r}; allowed: {allowed_options()}")
    try:
        return UrSimOptions(**(options or {}))
    except ValidationError as exc:
        problems: dict[str, str] = {}
        for error in exc.errors():
            names = [part for part in error["loc"] if isinstance(part, str)]
            where = ".".join(names) or "options"
            if where in problems:
                continue  # one problem per option (a tuple's items each report their own)
            if error["type"] == "extra_forbidden":
                problems[where] = f"unknown UR simulator option {where!r}"
                continue
            model = UrSimFaults if names[:1] == ["faults"] and len(names) > 1 else UrSimOptions
            field = model.model_fields.get(names[-1]) if names else None
            expected = f" (expected {_type_name(field.annotation)})" if field is not None else ""
            problems[where] = f"UR simulator option {where}={error.get('input')!r}: {error['msg']}{expected}"
        raise ValueError(f"{'; '.join(problems.values())}; allowed: {allowed_options()}") from None


def _type_name(annotation) -> str:
    return getattr(annotation, "__name__", None) if not getattr(annotation, "__args__", None) else \
        str(annotation).replace("typing.", "")


# --- pose conventions ---------------------------------------------------------
# The tool-down convention of geometry/orientation.py (R = Rz(alpha)·Rx(180°)), written with numpy alone (fast
# in the 500 Hz cycle); rotation vectors as geometry/ur_controller.py converts them (matrix_of_rotvec and
# rotvec_of_matrix are imported from there, and kept importable from here).


def tool_down_matrix(alpha: float) -> np.ndarray:
    c, s = math.cos(alpha), math.sin(alpha)
    return np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])


def flange_to_tcp(flange: Pose, tcp) -> tuple[float, ...]:
    """UR pose of the TCP for the four-axis arm's (tool-down) flange pose (a six-axis arm's: six_axis.py)."""
    return _flange_to_tcp(flange.x, flange.y, flange.z, flange.alpha, tuple(float(v) for v in tcp))


@functools.lru_cache(maxsize=256)  # the 500 Hz cycle asks for the same pose thousands of times
def _flange_to_tcp(x: float, y: float, z: float, alpha: float, tcp: tuple[float, ...]) -> tuple[float, ...]:
    r_f = tool_down_matrix(alpha)
    p = np.array([x, y, z]) + r_f @ np.asarray(tcp[:3])
    return (*map(float, p), *map(float, rotvec_of_matrix(r_f @ matrix_of_rotvec(tcp[3:6]))))


def tcp_to_flange(ur_pose, tcp, near_alpha: float = 0.0) -> Pose:
    """The four-axis arm's pose whose TCP is at `ur_pose`; ValueError if the flange would have to tilt."""
    values = [float(v) for v in ur_pose]
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"pose {values} is not six finite numbers")
    tcp = [float(v) for v in tcp]
    r_f = matrix_of_rotvec(values[3:]) @ matrix_of_rotvec(tcp[3:6]).T
    tilt = math.acos(min(max(-r_f[2, 2], -1.0), 1.0))  # angle between the tool axis and straight down
    if tilt > TILT_TOLERANCE_RAD:
        raise ValueError(f"the tool would tilt {math.degrees(tilt):.3f} deg from vertical; this 4-axis arm only turns "
                         "about the vertical (orientation must be Rz(alpha)*Rx(180 deg))")
    p = np.asarray(values[:3]) - r_f @ np.asarray(tcp[:3])
    alpha = math.atan2(r_f[1, 0], r_f[0, 0])
    alpha = near_alpha + math.remainder(alpha - near_alpha, math.tau)  # shortest turn, as moveL does
    return Pose(float(p[0]), float(p[1]), float(p[2]), alpha)


# --- the controller -------------------------------------------------------------


class Controller:
    """Everything the ports share. Fields are guarded by `lock`; the arm is called outside it."""

    def __init__(self, arm: ArmSource, options: UrSimOptions | None = None):
        self.arm = arm
        self.options = options or UrSimOptions()
        self.faults = self.options.faults
        self.lock = threading.RLock()
        self.started = time.monotonic()
        self.robot_mode = RUNNING if self.options.powered else POWER_OFF
        self.safety_mode = NORMAL
        self.protective_stop_at: float | None = None
        self.runtime_state = STOPPED
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.in_bits = 0
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.tcp = (0.0,) * 6
        self.flange: Pose = arm.pose()  # read once now; afterwards only after moves (see module docstring)
        self.six_axis = self.flange.orientation is not None  # the hand-eye cell's UR5e, not a four-axis arm
        if self.six_axis:
            self.kinematics = SixAxisKinematics(self.flange, arm.joints().positions)
        else:
            self.kinematics = UrKinematics(tuple(v * 1e-3 for v in self.options.base_xyz_mm),
                                           math.radians(self.options.base_yaw_deg))
        self.target_flange: Pose = self.flange
        self.motion: tuple[Pose, Pose, float, float] | None = None  # start, target, wall start, wall seconds
        self.motion_stopped_at: float | None = None
        self.moves = 0
        self.commands = 0
        self.script = None  # the running program's emulation (script.ControlScript), if any
        self.events: list[str] = []  # what happened, for logs and tests
        self.on_drop = None  # set by the server: closes every connection
        self.kinematics.joints(self.flange)  # Unreachable now, with the mounting named, rather than mid-stream
        self._last_q = self.joints(self.flange)

    # -- state seen on the wire ----------------------------------------------
    def dashboard_delay_s(self, request: str) -> float:
        """How long the dashboard waits before it answers `request` (fault knobs slow_reply_s, slow_requests)."""
        f = self.faults
        if not f.slow_reply_s:
            return 0.0
        if f.slow_requests is not None and request.strip().lower() not in {r.strip().lower() for r in f.slow_requests}:
            return 0.0
        return f.slow_reply_s

    @property
    def protective_stopped(self) -> bool:
        return self.safety_mode == PROTECTIVE_STOP

    def safety_status_bits(self) -> int:
        bits = 1 << BIT_NORMAL if self.safety_mode == NORMAL else 0
        if self.safety_mode == PROTECTIVE_STOP:
            bits |= 1 << BIT_PROTECTIVE_STOPPED
        return bits

    def robot_status_bits(self) -> int:
        bits = 1 << BIT_POWER_ON if self.robot_mode in (4, IDLE, RUNNING) else 0
        if self.runtime_state == PLAYING:
            bits |= 1 << BIT_PROGRAM_RUNNING
        return bits

    def tcp_pose(self, flange: Pose | None = None) -> tuple[float, ...]:
        flange = flange or self.actual_flange()
        if self.six_axis:  # from the arm's own joints, as a UR computes it (six_axis.py)
            return self.kinematics.tcp_pose(flange, self.tcp)
        return flange_to_tcp(flange, self.tcp)

    def joints(self, flange: Pose | None = None) -> tuple[float, ...]:
        """The UR5e's joint angles (rad) for the flange pose (default: where the arm is now)."""
        try:
            q = self.kinematics.joints(flange or self.actual_flange())
        except Unreachable as exc:  # moves are checked for reach before they start: only an arm moved by others
            if not any(e.startswith("joint angles unknown") for e in self.events[-5:]):
                self.note(f"joint angles unknown, reporting the last ones: {exc}")
            return self._last_q
        self._last_q = q
        return q

    def flange_of_joints(self, q) -> Pose:
        """The arm's flange pose for a moveJ target q; ValueError (a script error) if the arm cannot hold q."""
        return self.kinematics.flange_of_joints(q)

    def tcp_of_joints(self, q, tcp) -> tuple[float, ...]:
        """get_forward_kin(q, tcp): the TCP pose of joint angles q, any q (no move, so no tool-down rule)."""
        T = self.kinematics.forward(q)
        values = [float(v) for v in tcp]
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"tcp offset {values} is not six finite numbers")
        rotation = T[:3, :3] @ matrix_of_rotvec(values[3:])
        position = T[:3, 3] + T[:3, :3] @ np.asarray(values[:3])
        return (*map(float, position), *map(float, rotvec_of_matrix(rotation)))

    def check_reach(self, target: Pose) -> None:
        """ValueError unless the UR5e reaches every point of the straight move from here to `target`."""
        self.kinematics.check_path(self.actual_flange(), target)

    def actual_flange(self) -> Pose:
        """Where the arm is now: during a move, along the straight line at the time fraction (as the world
        moves it), frozen once a stop is requested; the arm's own report once the move has returned."""
        if self.motion is None:
            return self.flange
        start, target, t0, seconds = self.motion
        now = self.motion_stopped_at or time.monotonic()
        f = min(max((now - t0) / seconds, 0.0), 1.0) if seconds > 0 else 0.0
        if self.six_axis:  # a joint move's path is not a straight line: the pose it left, until it arrives
            return target if f >= 1.0 else start
        return Pose(*(a + f * (b - a) for a, b in ((start.x, target.x), (start.y, target.y), (start.z, target.z),
                                                    (start.alpha, target.alpha))))

    def note(self, event: str) -> None:
        log.info("ur sim: %s", event)
        self.events.append(event)

    # -- inputs from RTDE clients ------------------------------------------------
    def write_inputs(self, values: dict) -> None:
        with self.lock:
            for name, value in values.items():
                if name.startswith("input_int_register_"):
                    index = int(name.rsplit("_", 1)[1])
                    if index == self._cmd_register() and value != 0 and self.in_int[index] != value:
                        self.commands += 1
                        drop = self.faults.drop_after_commands
                        if drop and self.commands == drop + 1 and self.on_drop:  # once: the network comes back
                            self.note(f"dropping every connection at command {self.commands} (fault knob)")
                            self.on_drop()
                            return
                    self.in_int[index] = int(value)
                elif name.startswith("input_double_register_"):
                    self.in_double[int(name.rsplit("_", 1)[1])] = float(value)
                # other inputs (digital outputs, speed slider, external wrench) have no effect on this cell

    def _cmd_register(self) -> int:
        return self.script.reg_offset if self.script is not None else 0

    # -- modes ---------------------------------------------------------------------
    def protective_stop(self, reason: str) -> None:
        with self.lock:
            if self.safety_mode != PROTECTIVE_STOP:
                self.safety_mode = PROTECTIVE_STOP
                self.protective_stop_at = time.monotonic()
                self.note(f"protective stop: {reason}")
            if self.runtime_state == PLAYING:
                self.runtime_state = PAUSED  # a protective stop pauses the running program
        self.stop_motion()

    def unlock_protective_stop(self) -> str:
        with self.lock:
            if self.safety_mode != PROTECTIVE_STOP:
                return "Protective stop releasing"
            if time.monotonic() - (self.protective_stop_at or 0) < self.options.unlock_delay_s:
                return ("Cannot unlock protective stop until 5s after occurrence. "
                        "Always inspect cause of protective stop before unlocking")
            self.safety_mode = NORMAL
            self.protective_stop_at = None
            self.note("protective stop unlocked")
            return "Protective stop releasing"

    def stop_program(self, reason: str) -> None:
        with self.lock:
            if self.script is not None:
                self.script.halt()
                self.script = None
            if self.runtime_state != STOPPED:
                self.note(f"program stopped: {reason}")
            self.runtime_state = STOPPED

    # -- motion (called from script workers, never under the lock) -------------------
    def tcp_to_flange(self, ur_pose) -> Pose:
        return tcp_to_flange(ur_pose, self.tcp, self.flange.alpha)

    def move_target(self, cmd: int, args) -> tuple[Pose, tuple[float, ...] | None]:
        """Where move command `cmd` (1 moveJ, 2 moveJ_IK, 3 moveL, 4 moveL_FK) with its register arguments goes:
        the flange pose, and for a six-axis arm the joints it is sent (None: a four-axis arm is sent the pose).
        ValueError (a script error) before anything moves if the arm cannot go there."""
        if self.six_axis:
            return self.kinematics.move_target(cmd, args, self.tcp)
        target = self.flange_of_joints(args) if cmd in (1, 4) else self.tcp_to_flange(args)
        self.check_reach(target)  # a UR stops the program when inverse kinematics fails
        return target, None

    def execute_move(self, flange_target: Pose, speed: float | None, joints=None) -> bool:
        """Move the arm; True when the target was reached. A fault becomes the controller's reaction.
        `joints`: what a six-axis arm is sent (move_target), else the arm is sent the flange pose."""
        with self.lock:
            if self.safety_mode != NORMAL or self.robot_mode != RUNNING:
                return False
            self.moves += 1
            self.target_flange = flange_target
            stop_here = self.faults.protective_stop_after_moves and self.moves > self.faults.protective_stop_after_moves
        if stop_here:
            self.protective_stop(f"move {self.moves} (fault knob protective_stop_after_moves)")
            return False
        seconds = self._wall_seconds(self.flange, flange_target)
        with self.lock:
            self.motion_stopped_at = None
            self.motion = (self.flange, flange_target, time.monotonic(), seconds) if seconds > 0 else None
        try:
            if joints is not None:
                self.arm.move_joints(JointState(tuple(float(v) for v in joints)), speed)
            else:
                self.arm.move_linear(flange_target, speed)
            reached = True
        except MotionStopped:
            reached = False
        except ProtectiveStop as exc:
            self.protective_stop(str(exc))
            reached = False
        except (MotionRejected, ValueError) as exc:
            self.script_error(f"target not reachable: {exc}")
            reached = False
        except ConnectionLost as exc:  # the world behind the simulator is gone: the robot is as good as faulted
            self.script_error(f"simulated arm unreachable: {exc}")
            reached = False
        self.refresh_pose()
        return reached

    def refresh_pose(self) -> None:
        try:
            pose = self.arm.pose()
            q = self.arm.joints().positions if self.six_axis else None
        except Exception as exc:  # noqa: BLE001 - keep the last known pose; the error is in the events
            self.note(f"cannot read the arm pose: {exc}")
            return
        with self.lock:  # the pose and its joints change together for the 500 Hz cycle
            if q is not None:
                self.kinematics.remember(pose, q)
            self.flange = pose
            self.target_flange = pose
            self.motion = None

    def _wall_seconds(self, start: Pose, target: Pose) -> float:
        """How long the world will take for this move in wall time (0: it returns at once)."""
        try:
            if isinstance(self.arm, MotionTimed):  # a SimArm, or a RemoteArm that asks the world's owner
                return float(self.arm.wall_seconds(start, target))
        except Exception as exc:  # noqa: BLE001 - only the reported path suffers: it jumps at the end
            self.note(f"cannot estimate the motion time: {exc}")
        return 0.0

    def stop_motion(self) -> None:
        with self.lock:
            if self.motion is not None and self.motion_stopped_at is None:
                self.motion_stopped_at = time.monotonic()
        self.arm.stop()

    def script_error(self, message: str) -> None:
        self.note(f"script error: {message}")
        self.stop_program(message)
