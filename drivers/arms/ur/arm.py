"""Universal Robots arm over RTDE, through the ur_rtde library (PyPI `ur-rtde`).

Three ur_rtde objects per connection: `RTDEReceiveInterface` (the 500 Hz state
stream: pose, joints, modes, safety bits, timestamps), `RTDEControlInterface` (uploads
its control script and sends commands through RTDE registers) and `DashboardClient`
(robot and safety mode, power, protective-stop unlock).

Moves are sent asynchronously and then watched from Python, so that
- a protective stop (safety_status_bits bit 2) raises ProtectiveStop at once;
- a dropped link (RTDE stream gone or silent for `link_timeout_s`) raises
  ConnectionLost and leaves the device FAULTED: ur_rtde's own background reconnect is
  never trusted, `connect()` is the only way back;
- `stop()` from another thread ends the move with stopL/stopJ (MotionStopped).

Poses: the cell's tool points down, turned by `alpha` about the vertical, R =
Rz(alpha)·Rx(180°) (`geometry/orientation.py`), sent as a UR pose [x, y, z, rx, ry, rz]
(rotation vector); a Pose with its own `orientation` (quaternion w, x, y, z) is sent
with that orientation. `pose()` is actual_TCP_pose with its full orientation (and alpha,
the tool's turn about the vertical). The TCP offset of the settings is set with setTcp on connect.
Joints: `joints()` is the controller's actual_q, the six joint angles (rad, base to wrist 3,
names base, shoulder, elbow, wrist1, wrist2, wrist3); `move_joints()` takes the same, refuses
targets outside `joint_limits_rad` before sending them, and checks that the arm arrived. On the
simulated micro cell they are a UR5e's (drivers/sim/servers/ur/kinematics.py); on the hand-eye
cell, the simulated UR5e's own (drivers/sim/servers/ur/six_axis.py). Units and frames are those of
the in-process fake `SimUr5eArm` (the conversions are geometry/ur_controller.py): a routine gets the
same numbers through either.
A controller that refuses a target (a script error) stops its control script: the move raises
MotionStopped saying so and nothing more moves until connect() uploads the script again (a refusal
before the move started leaves the arm FAULTED at once, one once it was under way at the next move;
pose() and joints() still answer meanwhile).

A call that gets no answer: every call to the child has a time-out (most: command + settle +
link time-outs + 5 s; moves and connect() longer). A child that does not answer in time (a
deadlock in ur_rtde, a frozen process) is ended (SIGTERM, then SIGKILL) and the call raises
ConnectionLost ("did not answer <call> in time ... call connect()"); the arm is FAULTED and
connect() starts a new child. A slow dashboard: ur_rtde 1.6.5's dashboard client waits about
2.5 s for a reply ('Operation canceled' after that). Replies within that only make connect()
and unlock_protective_stop() slower; a later one is ConnectionLost naming the dashboard: in
connect() the arm stays as it was (CREATED), in unlock_protective_stop() it is FAULTED (the late
reply would pass for the next request's), and connect() goes on once the controller answers.

Process isolation: `UrArm` runs the ur_rtde objects in a child process of their own
(`drivers/arms/ur/child.py`, one per connect(), requests over `drivers/rpc.py`), where
`UrRtdeArm` (drivers/arms/ur/rtde_driver.py) is the driver proper. ur_rtde 1.6.5 can kill its process (an uncaught
std::length_error on a malformed RTDE frame: SIGABRT; destroying its interfaces during its
background reconnect: SIGSEGV); the caller then gets ConnectionLost naming the signal and
the arm is FAULTED until connect() starts a new child. The child never runs ur_rtde's
destructors (it ends with os._exit). Cost: one local round trip per call (pose() ~0.1 ms).

ur_rtde's constructors hold the GIL (the child's) while they wait for the controller (up
to seconds); the simulator still runs in a process of its own (see `drivers/sim/servers/ur`).
Before constructing, the driver checks that the controller's ports accept within
`connect_timeout_s`, so a wrong address fails fast instead of hanging in C++.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import secrets
import select
import signal
import subprocess
import sys
import threading
from pathlib import Path

from geometry import ur
from geometry.ur_controller import linear_joints, matrix_of_ur_pose, outside_limits, ur_pose_of

from drivers.arms.ur.rtde_driver import LINK_LOST, UrArmSettings
from drivers.interfaces import (
    ConnectionLost,
    DeviceError,
    DeviceState,
    JointState,
    MotionRejected,
    Pose,
    not_ready_error,
)
from drivers.lifecycle import Driver
from drivers.rpc import ObjectClient

log = logging.getLogger(__name__)


class UrArm(Driver):
    """Arm interface on a Universal Robots controller (e-Series or CB3) through ur_rtde.

    The ur_rtde objects live in a child process (drivers/arms/ur/child.py, one per connect()) that runs
    `UrRtdeArm`; every call here is a request to it (drivers/rpc.py) with a time-out. When ur_rtde takes its
    process down (an uncaught C++ exception on a malformed frame, a segfault) or the child stops answering,
    the call raises ConnectionLost naming the signal, the arm is FAULTED, and connect() starts a new child.
    stop() has a connection of its own, so it is served while a move runs."""

    Settings = UrArmSettings
    LINK_LOST = LINK_LOST
    START_TIMEOUT_S = 60.0  # a fresh interpreter importing numpy, scipy, pydantic and ur_rtde

    def __init__(self, name: str, settings: UrArmSettings):
        super().__init__(name, settings)
        self._child: subprocess.Popen | None = None
        self._client: _ChildClient | None = None
        self._stderr_tail: collections.deque[str] = collections.deque(maxlen=8)
        self._stderr_thread: threading.Thread | None = None

    @property
    def max_speed_m_s(self) -> float:
        return self.settings.max_speed_m_s

    def check_target(self, target: Pose) -> None:
        """The box, then, on a UR5e (`model: ur5e`: the kinematics geometry/ur_controller.py knows), the joints the
        controller's own kinematics give the target on the arm's present branch against `joint_limits_rad`."""
        self._ready()
        self.settings.limits.check(target)
        if self.settings.model != "ur5e":
            return
        try:
            q = linear_joints(matrix_of_ur_pose(ur_pose_of(target.x, target.y, target.z, target.alpha,
                                                           target.orientation)), self.joints().positions)
        except (ur.Unreachable, ValueError) as exc:
            raise MotionRejected(f"{self.name}: ({target.x:.4f}, {target.y:.4f}, {target.z:.4f}) m is out of reach "
                                 f"on the arm's present branch: {exc}; nothing moved") from None
        problem = outside_limits(q, self.settings.joint_limits_rad, ur.JOINT_NAMES)
        if problem:
            raise MotionRejected(f"{self.name}: {problem}; nothing moved")

    # -- the child --------------------------------------------------------------------------------
    def _start_child(self) -> None:
        from drivers.arms.ur.child import AUTHKEY_ENV

        authkey = secrets.token_bytes(16)
        root = str(Path(__file__).resolve().parents[2])
        env = {**os.environ, AUTHKEY_ENV: authkey.hex(),
               "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        child = subprocess.Popen([sys.executable, "-m", "drivers.arms.ur.child"], cwd=root, env=env,
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self._child = child
        self._stderr_tail.clear()
        self._stderr_thread = threading.Thread(target=self._relay_stderr, args=(child,), daemon=True,
                                               name=f"{self.name}-ur-stderr")
        self._stderr_thread.start()
        setup = {"name": self.name, "settings": self.settings.model_dump(mode="json")}
        try:
            child.stdin.write((json.dumps(setup) + "\n").encode())
            child.stdin.flush()
            ready, _, _ = select.select([child.stdout], [], [], self.START_TIMEOUT_S)
            line = child.stdout.readline().decode() if ready else ""
        except OSError as exc:
            line = f"({exc})"
        child.stdout.close()
        if not line.startswith("ready "):
            self._end_child()
            raise ConnectionLost(f"{self.name}: ur_rtde's process did not start ({line.strip() or 'no answer'}; "
                                 f"exit code {child.returncode}): {' | '.join(self._stderr_tail)}")
        _, host, port = line.split()
        self._client = _ChildClient(self, (host, int(port)), authkey)

    def _relay_stderr(self, child: subprocess.Popen) -> None:
        """ur_rtde's and the child's messages: on to our stderr, the last lines kept for a crash report."""
        for raw in iter(child.stderr.readline, b""):
            text = raw.decode(errors="replace")
            self._stderr_tail.append(text.strip())
            try:  # keep draining whatever happens here: a full pipe would block the child
                sys.stderr.write(f"[{self.name} ur_rtde] {text}")
            except (AttributeError, OSError, ValueError):
                pass

    def _alive(self) -> bool:
        return self._child is not None and self._child.poll() is None

    def _end_child(self, grace_s: float = 2.0) -> None:
        """Close our end (the child exits on stdin EOF), then terminate, then kill."""
        child, client = self._child, self._client
        self._client = None
        if client is not None:
            client.close()
        if child is None:
            return
        try:
            child.stdin.close()
        except OSError:
            pass
        for end in (lambda: None, child.terminate, child.kill):
            end()
            try:
                child.wait(grace_s)
                break
            except subprocess.TimeoutExpired:
                grace_s = 1.0
        if self._stderr_thread is not None:
            self._stderr_thread.join(1.0)

    def _died(self, call: str, exc: BaseException) -> ConnectionLost:
        """ConnectionLost for a child that died (or hung, then is ended): named with its signal."""
        self._state = DeviceState.FAULTED
        child = self._child
        try:
            code = child.wait(1.0) if child is not None else None
        except subprocess.TimeoutExpired:
            code = None
        if code is None:
            self._end_child(grace_s=0.5)
            return ConnectionLost(f"{self.name}: ur_rtde's process did not answer {call} in time ({exc!r}); "
                                  f"ended it. Check the controller at {self.settings.host}, then call connect() "
                                  "to reconnect")
        if self._stderr_thread is not None:
            self._stderr_thread.join(1.0)
        how = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
        last = " | ".join(line for line in self._stderr_tail if line)
        self._end_child(grace_s=0.5)
        return ConnectionLost(f"{self.name}: ur_rtde's process (pid {child.pid}) died with {how} during {call}"
                              f"{f' ({last})' if last else ''}; the link to the UR controller at "
                              f"{self.settings.host} is lost: call connect() to reconnect")

    def _call(self, name: str, *args, timeout_s: float | None = None):
        if self._client is None:
            raise self._lost_state()
        return self._client.request(name, *args, timeout_s=timeout_s or self._timeout_s)

    @property
    def _timeout_s(self) -> float:
        s = self.settings
        return s.command_timeout_s + s.settle_timeout_s + s.link_timeout_s + 5.0

    def _lost_state(self) -> DeviceError:
        return not_ready_error(self.name, self._state, self.LINK_LOST)

    # -- lifecycle ---------------------------------------------------------------------------------
    def connect(self) -> None:
        if self._state is DeviceState.READY:
            return
        self._end_child(grace_s=0.5)  # a FAULTED link's child: never asked to tidy up (ur_rtde may crash)
        s = self.settings
        state = self._state
        self._start_child()
        try:
            self._call("connect", timeout_s=5 * s.connect_timeout_s + s.command_timeout_s + 30.0)
        except BaseException:
            self._end_child(grace_s=0.5)
            self._state = state  # as before the attempt (CREATED, or FAULTED after a lost link)
            raise
        self._state = DeviceState.READY

    def close(self) -> None:
        if self._state is DeviceState.CLOSED:
            return
        if self._alive() and self._client is not None:
            try:
                self._call("close", timeout_s=2 * self.settings.command_timeout_s + self._timeout_s)
            except DeviceError as exc:
                log.warning("%s: close: %s", self.name, exc)
        self._end_child()
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        """stopL or stopJ (as the last move was), on a connection of its own; safe in any state, never raises."""
        if self._state is not DeviceState.READY:
            return
        try:
            self._call("stop")
        except Exception as exc:  # noqa: BLE001 - a stop must not raise; the next command reports the state
            log.warning("%s: stop failed: %s", self.name, exc)

    # -- the Arm calls, run by UrRtdeArm in the child ----------------------------------------------------
    # No move_through (MovesThrough, issue 31): a via point on a UR is a settled move_linear (move_via falls back).
    # ur_rtde 1.6.5 offers no honest way past a point: its single-target moveL (recipe 1: pose, speed,
    # acceleration, async flag) has no blend radius, so the script's movel ends standing; returning from an async
    # moveL early (once within a blend radius) blends nothing either: the next command kills the move thread
    # (stop_async_move) instead of planning a corner path (the simulator stops the arm there), and the rest of that
    # move would go unwatched (arrival, protective stop). A real blend needs moveL(path) with blend radii, which
    # stops the control script, re-uploads it (~42 kB) with the path injected and waits, with no time-out, for it
    # to run again: per via point that costs more than the settling it saves, it needs the next target up front,
    # and the simulator does not emulate it (a script error).
    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._ready()
        self._call("move_linear", target, speed, timeout_s=self._move_timeout_s)

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        self._ready()
        self._call("move_joints", joints, speed, timeout_s=self._move_timeout_s)

    @property
    def _move_timeout_s(self) -> float:
        return self.settings.move_timeout_s + self.settings.command_timeout_s + self._timeout_s

    def speed_stop(self, deceleration: float | None = None) -> None:
        self._ready()
        self._call("speed_stop", deceleration)

    def pose(self) -> Pose:
        self._ready()
        return self._call("pose")

    def joints(self) -> JointState:
        self._ready()
        return self._call("joints")

    def set_tcp(self, offset) -> None:
        """TCP offset from the flange [x, y, z, rx, ry, rz] (m, rotation vector)."""
        self._ready()
        self._call("set_tcp", list(offset))  # checked in the child (ValueError comes back as such)

    def robot_mode(self) -> str:
        self._ready()
        return self._call("robot_mode")

    def safety_mode(self) -> str:
        self._ready()
        return self._call("safety_mode")

    def trigger_protective_stop(self) -> None:
        """Stop the arm as a safety event (the controller's protective_stop()); unlock it to go on."""
        self._ready()
        self._call("trigger_protective_stop")

    def unlock_protective_stop(self) -> None:
        """Operator action after inspecting the cause: unlock on the dashboard; connect() again to resume."""
        self._ready()
        self._call("unlock_protective_stop")


class _ChildClient(ObjectClient):
    """ObjectClient to ur_process: mirrors the driver's state from each reply, names a dead child's signal."""

    def __init__(self, arm: UrArm, address, authkey: bytes):
        super().__init__(address, authkey, what=f"{arm.name}'s ur_rtde process", alive=arm._alive)
        self.arm = arm
        self.on_reply = self._mirror

    def _mirror(self, reply) -> None:
        self.arm._state = DeviceState(reply[-1])

    def lost(self, name: str, exc: BaseException, unreachable: bool = False) -> ConnectionLost:
        return self.arm._died(name, exc)
