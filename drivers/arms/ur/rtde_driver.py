"""The Universal Robots driver proper, over ur_rtde: it runs inside the child process of
`drivers/arms/ur/child.py`, which `UrArm` (drivers/arms/ur/arm.py) starts for every connect().

Everything about the robot is here (see drivers/arms/ur/arm.py for the whole story): the
settings, the pose conversion, the moves watched for protective stops and a silent link,
stop(), the dashboard. `UrArm` only carries its calls across the process boundary.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from geometry import ur_controller

from drivers import endpoint
from drivers.interfaces import (
    ConnectionLost,
    DeviceError,
    DeviceState,
    JointState,
    MotionRejected,
    MotionStopped,
    Pose,
    ProtectiveStop,
)
from drivers.lifecycle import Driver
from drivers.limits import WorkspaceBox

log = logging.getLogger(__name__)

DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT = 29999, 30003, 30004
JOINT_NAMES = ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
RUNNING = 7
PROTECTIVE_STOP_BIT, EMERGENCY_STOP_BIT = 2, 7
PLAYING = 2
LINK_LOST = "the link to the UR controller was lost (or its control program stopped); call connect() before going on"
# what the receive interface streams (a small recipe: every getter used below reads one of these)
RECEIVE_VARIABLES = ["timestamp", "actual_q", "actual_TCP_pose", "robot_mode", "safety_mode", "runtime_state",
                     "robot_status_bits", "safety_status_bits"]


class UrArmSettings(BaseModel):
    """A UR arm on the network. Speeds and accelerations are the controller's units (m/s, rad/s)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = Field(..., min_length=1, description="controller address (RTDE port 30004 is fixed)")
    model: Literal["ur3", "ur5", "ur10", "ur3e", "ur5e", "ur10e", "ur16e", "ur20", "ur30"] | None = Field(
        None, description="the arm's model: an `arm` calibration (arm-kinematics) is activated only on a cell whose "
                          "arm is of the model it calibrated; unset: the model is not checked")
    limits: WorkspaceBox
    speed_m_s: float = Field(0.25, gt=0, le=3.0, description="default tool speed of move_linear")
    max_speed_m_s: float = Field(1.0, gt=0, le=3.0, description="move_linear refuses faster speeds")
    acceleration_m_s2: float = Field(1.2, gt=0, le=150.0)
    joint_speed_rad_s: float = Field(1.05, gt=0, le=3.14, description="default joint speed of move_joints")
    max_joint_speed_rad_s: float = Field(3.14, gt=0, le=3.14)
    joint_acceleration_rad_s2: float = Field(1.4, gt=0, le=40.0)
    stop_deceleration_m_s2: float = Field(10.0, gt=0, le=40.0, description="stopL deceleration")
    stop_deceleration_rad_s2: float = Field(2.0, gt=0, le=40.0, description="stopJ deceleration")
    tcp_offset_mm: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="TCP from the flange")
    tcp_rotation_rad: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="TCP rotation vector")
    connect_timeout_s: float = Field(5.0, gt=0, le=120, description="time for the controller's ports to accept")
    move_timeout_s: float = Field(120.0, gt=0, le=3600, description="longest a single move may take")
    link_timeout_s: float = Field(0.5, gt=0.01, le=30, description="RTDE silence that counts as a lost link")
    settle_timeout_s: float = Field(2.0, gt=0, le=60, description="after a stop, wait this long at most for "
                                    "the arm to stand still")
    command_timeout_s: float = Field(5.0, gt=0, le=300, description="longest wait for the control script's answer")
    arrival_tolerance_m: float = Field(1e-4, gt=0, le=0.01, description="a finished move must end this close")
    arrival_tolerance_rad: float = Field(1e-3, gt=0, le=0.1, description="a finished joint move must end with "
                                         "every joint this close")
    power_on: bool = Field(False, description="on connect, power on and release the brakes if needed")
    upper_range_registers: bool = Field(False, description="use RTDE registers 24-47 (ur_rtde flag)")
    joint_limits_rad: tuple[tuple[float, float], ...] = Field(
        ((-2 * math.pi, 2 * math.pi),) * 6,
        description="move_joints refuses targets outside these (min, max) per joint. Joint targets are not "
                    "checked against the workspace box: ur_rtde 1.6.5 cannot ask the controller's forward "
                    "kinematics for a given TCP (it sends getForwardKinematics(q, tcp) on a recipe too short "
                    "for it, and the q-only form uses whatever registers 6-11 last held as the TCP)")

    @model_validator(mode="after")
    def _joint_limits(self):
        if len(self.joint_limits_rad) != 6 or any(not lo < hi for lo, hi in self.joint_limits_rad):
            raise ValueError(f"joint_limits_rad: expected 6 (min, max) pairs with min < max, got {self.joint_limits_rad}")
        return self

    def endpoints(self) -> list[str]:
        """The controller, by its RTDE port (fixed; the dashboard and script ports come with it)."""
        return [endpoint.tcp(self.host, 30004)]


def ur_pose_of(target: Pose) -> list[float]:
    """[x, y, z, rx, ry, rz] for a Pose: its own orientation if given, else tool down turned by alpha."""
    return ur_controller.ur_pose_of(target.x, target.y, target.z, target.alpha, target.orientation)


def pose_of(ur_pose) -> Pose:
    """The Pose of a reported UR pose: position (m), alpha (the tool's turn about the vertical) and the full
    orientation (quaternion w, x, y, z), as the simulated UR5e reports it in-process (geometry/ur_controller.py)."""
    return Pose(*ur_controller.pose_parts(ur_pose))


class UrRtdeArm(Driver):
    """The ur_rtde driver itself, run in the child process of drivers/arms/ur/child.py (see UrArm)."""

    Settings = UrArmSettings
    LINK_LOST = LINK_LOST

    def __init__(self, name: str, settings: UrArmSettings):
        super().__init__(name, settings)
        self._receive = None
        self._control = None
        self._dashboard = None
        self._command_lock = threading.Lock()  # ur_rtde's command handshake is not re-entrant
        self._stop_requested = threading.Event()
        self._stop_done = threading.Event()  # the stop command has been answered
        self._stop_done.set()
        self._last_move = "linear"
        self._last_timestamp = (None, 0.0)  # (RTDE timestamp, monotonic time it was first seen)
        self._alpha_hint: float | None = None  # last commanded alpha: pose() reports the turn nearest to it
        self._leftovers: list = []  # ur_rtde objects never destroyed (see _release)

    # -- lifecycle ---------------------------------------------------------------------------
    def connect(self) -> None:
        if self._state is DeviceState.READY:
            return
        self._release()  # a FAULTED link's leftovers
        import dashboard_client
        import rtde_control
        import rtde_receive

        s = self.settings
        for port in (DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT):
            self._probe(port)
        stage = f"the dashboard (port {DASHBOARD_PORT})"
        try:
            self._dashboard = dashboard_client.DashboardClient(s.host)
            self._dashboard.connect(int(s.connect_timeout_s * 1000))
            self._ensure_running()
            stage = f"RTDE (port {RTDE_PORT}): the receive interface"
            self._receive = rtde_receive.RTDEReceiveInterface(s.host, -1.0, RECEIVE_VARIABLES, False,
                                                              s.upper_range_registers)
            stage = (f"the control interface (RTDE, its control script on port {SCRIPT_PORT}, and its own "
                     f"dashboard connection for the PolyScope version)")
            flags = int(rtde_control.RTDEControlInterface.Flags.FLAG_UPLOAD_SCRIPT)
            if s.upper_range_registers:
                flags |= int(rtde_control.RTDEControlInterface.Flags.FLAG_UPPER_RANGE_REGISTERS)
            self._control = rtde_control.RTDEControlInterface(s.host, -1.0, flags)
        except DeviceError:
            self._release()
            raise
        except RuntimeError as exc:  # ur_rtde reports every connection problem as a RuntimeError
            self._release()
            hint = f" ({TIMED_OUT_HINT})" if _timed_out(exc) else ""
            raise ConnectionLost(f"{self.name}: cannot connect to the UR controller at {s.host}, at {stage}: "
                                 f"{exc}{hint}") from exc
        self._last_timestamp = (None, time.monotonic())
        self._state = DeviceState.READY
        try:
            self.set_tcp([*(v * 1e-3 for v in s.tcp_offset_mm), *s.tcp_rotation_rad])
        except DeviceError:
            self._state = DeviceState.CREATED
            self._release()
            raise
        log.info("%s: connected to UR at %s", self.name, s.host)

    def _probe(self, port: int) -> None:
        host = self.settings.host
        try:
            with socket.create_connection((host, port), timeout=self.settings.connect_timeout_s):
                pass
        except OSError as exc:
            raise ConnectionLost(f"{self.name}: the UR controller at {host} does not accept on port {port} ({exc}); "
                                 "check the address, the network and that the robot is switched on") from exc

    def _ensure_running(self) -> None:
        """Robot mode RUNNING (powered, brakes released) and no protective stop, or a clear error."""
        mode = self._dashboard.robotmode()
        safety = self._dashboard.safetymode()
        if "PROTECTIVE_STOP" in safety:
            raise ProtectiveStop(f"{self.name}: the robot is in a protective stop ({safety}); inspect the cause, "
                                 "unlock it on the pendant (or unlock_protective_stop()), then connect again")
        if "RUNNING" in mode:
            return
        if not self.settings.power_on:
            raise DeviceError(f"{self.name}: robot mode is '{mode}', not RUNNING; power on and release the brakes "
                              "on the pendant, or set power_on: true in the arm settings")
        self._dashboard.powerOn()
        self._dashboard.brakeRelease()
        deadline = time.monotonic() + self.settings.connect_timeout_s
        while "RUNNING" not in (mode := self._dashboard.robotmode()):
            if time.monotonic() > deadline:
                raise DeviceError(f"{self.name}: robot mode still '{mode}' {self.settings.connect_timeout_s} s "
                                  "after power on and brake release")
            time.sleep(0.05)

    def close(self) -> None:
        if self._state is DeviceState.CLOSED:
            return
        self.stop()
        if self._state is DeviceState.READY and self._control is not None:
            try:
                self._command("stopScript", self._control.stopScript)
            except DeviceError as exc:
                log.warning("%s: stopScript on close failed: %s", self.name, exc)
        self._release()
        self._state = DeviceState.CLOSED

    def _release(self) -> None:
        """Set the ur_rtde objects aside without destroying them: destroying an RTDEControlInterface while
        ur_rtde reconnects in the background segfaults (1.6.5). This runs in ur_process's child, which ends
        with os._exit: the kernel closes the sockets, no destructor runs."""
        if self._dashboard is not None:
            _quiet_disconnect(self._dashboard)
        self._leftovers += [p for p in (self._control, self._receive, self._dashboard) if p is not None]
        self._control = self._receive = self._dashboard = None

    # -- state checks ----------------------------------------------------------------------------
    def _lost(self, why: str) -> ConnectionLost:
        self._state = DeviceState.FAULTED
        return ConnectionLost(f"{self.name}: lost the link to the UR controller at {self.settings.host} ({why}); "
                              "check the network and the controller, then call connect()")

    def _check_link(self) -> None:
        """The RTDE stream must be connected and fresh; ur_rtde's background reconnect does not count."""
        if not (self._receive.isConnected() and self._control.isConnected()):
            raise self._lost("RTDE connection closed")
        stamp = self._receive.getTimestamp()
        last, since = self._last_timestamp
        now = time.monotonic()
        if stamp != last:
            if last is not None and stamp < last:
                raise self._lost("the controller's RTDE clock went backwards: the link was re-established")
            self._last_timestamp = (stamp, now)
        elif now - since > self.settings.link_timeout_s:
            raise self._lost(f"no RTDE data for {now - since:.2f} s")

    def _check_safety(self) -> None:
        bits = int(self._receive.getSafetyStatusBits())
        if bits & (1 << PROTECTIVE_STOP_BIT):
            raise ProtectiveStop(f"{self.name}: the robot is in a protective stop (safety mode "
                                 f"{self.safety_mode()}); inspect the cause and unlock it on the pendant")
        if bits & (1 << EMERGENCY_STOP_BIT):
            raise ProtectiveStop(f"{self.name}: the robot is emergency-stopped; release the e-stop and reset it")

    def _command(self, what: str, call):
        """Run one ur_rtde command while watching the link.

        ur_rtde waits for the control script's answer without noticing a dropped link (up to 300 s), so the
        call runs on a helper thread: a dead or silent link raises ConnectionLost at once and the helper is
        left to ur_rtde's own time-out (it holds nothing of ours)."""
        with self._command_lock:
            outcome: dict = {}
            done = threading.Event()

            def run():
                try:
                    outcome["value"] = call()
                except BaseException as exc:  # noqa: BLE001 - handed to the caller below
                    outcome["error"] = exc
                finally:
                    done.set()

            threading.Thread(target=run, name=f"{self.name}-{what}", daemon=True).start()
            deadline = time.monotonic() + self.settings.command_timeout_s
            while not done.wait(0.002):
                self._check_link()
                if time.monotonic() > deadline:
                    raise self._lost(f"no answer to {what} within {self.settings.command_timeout_s} s")
        if "error" in outcome:
            error = outcome["error"]
            if isinstance(error, RuntimeError):
                self._check_link()
                raise DeviceError(f"{self.name}: {what} failed: {error}") from error
            raise error
        return outcome["value"]

    # -- motion ----------------------------------------------------------------------------------------
    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._ready()
        self.settings.limits.check(target)
        speed = self._speed(speed, self.settings.speed_m_s, self.settings.max_speed_m_s, "m/s")
        ur_target = ur_pose_of(target)
        # a six-axis target's orientation is the whole answer: pose() reports alpha as the controller's pose gives it
        self._alpha_hint = target.alpha if target.orientation is None else None
        self._run_move("linear", lambda: self._control.moveL(ur_target, speed, self.settings.acceleration_m_s2, True),
                       ur_target)

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        """Joint move; targets are checked against `joint_limits_rad` (see the settings for why not the box)."""
        self._ready()
        q = [float(v) for v in joints.positions]
        if len(q) != 6 or not all(math.isfinite(v) for v in q):
            raise MotionRejected(f"{self.name}: expects 6 finite joint positions (rad), got {joints.positions}")
        for i, (value, (lo, hi)) in enumerate(zip(q, self.settings.joint_limits_rad)):
            if not lo <= value <= hi:
                raise MotionRejected(f"{self.name}: joint {JOINT_NAMES[i]}={value:.4f} is outside its limits "
                                     f"[{lo}, {hi}] rad; nothing moved")
        speed = self._speed(speed, self.settings.joint_speed_rad_s, self.settings.max_joint_speed_rad_s, "rad/s")
        self._alpha_hint = None
        self._run_move("joint", lambda: self._control.moveJ(q, speed, self.settings.joint_acceleration_rad_s2, True),
                       q)

    def _speed(self, speed, default: float, maximum: float, unit: str) -> float:
        if speed is None:
            return default
        if not (math.isfinite(speed) and 0 < speed <= maximum):
            raise MotionRejected(f"{self.name}: speed {speed} {unit} is outside (0, {maximum}]; nothing moved")
        return float(speed)

    def _run_move(self, kind: str, send, target) -> None:
        """Send an asynchronous move and watch it to its end (or a stop, a protective stop, a lost link).
        `target`: the UR pose of a linear move, the joints of a joint move."""
        self._check_link()
        self._check_safety()
        self._stop_requested.clear()
        self._last_move = kind
        before = self._control.getAsyncOperationProgressEx().operationId()
        accepted = self._command(f"move{'L' if kind == 'linear' else 'J'}", send)
        if not accepted:
            self._explain_refusal()
        deadline = time.monotonic() + self.settings.move_timeout_s
        started = False
        while True:
            self._check_link()
            try:
                self._check_safety()
            except ProtectiveStop:
                self._settle()
                raise
            status = self._control.getAsyncOperationProgressEx()
            started = started or status.operationId() != before
            if started and not status.isAsyncOperationRunning():
                break
            if self._stop_requested.is_set():
                self._stop_done.wait(self.settings.command_timeout_s)
                self._settle()
                raise MotionStopped(f"{self.name}: stop() ended the move; the arm stands where it stopped")
            if time.monotonic() > deadline:
                self.stop()
                self._settle()
                raise MotionStopped(f"{self.name}: the move took longer than {self.settings.move_timeout_s} s; "
                                    "stopped it")
            time.sleep(0.002)
        self._check_arrival(kind, target)

    def _settle(self) -> None:
        """After a stop, wait (bounded) until the reported pose stands still, so pose() tells where it stopped."""
        deadline = time.monotonic() + self.settings.settle_timeout_s
        try:
            last = self._receive.getActualTCPPose()
            still_since = time.monotonic()
            while time.monotonic() < deadline and self._receive.isConnected():
                time.sleep(0.002)
                pose = self._receive.getActualTCPPose()
                if math.dist(pose[:3], last[:3]) > 1e-6 or abs(pose[5] - last[5]) > 1e-6:
                    last, still_since = pose, time.monotonic()
                elif time.monotonic() - still_since >= 0.02:
                    return
        except RuntimeError as exc:  # the caller's error says more than this one
            log.debug("%s: settle: %s", self.name, exc)

    def _explain_refusal(self) -> None:
        """ur_rtde returned False: say why (link, safety, control script) in the typed error, from packages sent
        after the refusal (the receive stream may lag the control stream that refused). Either way the control
        script is gone or out of step with us: the arm is FAULTED until connect() uploads it again."""
        self._await_packages(2)
        self._check_safety()
        self._state = DeviceState.FAULTED
        if self._receive.getRuntimeState() != PLAYING:
            raise MotionStopped(f"{self.name}: the controller refused the move and its control script is not running "
                                "(stopped by a script error: a target out of reach or outside the joint limits; or "
                                "from the pendant); nothing moved, and nothing more will until connect() uploads "
                                "the script again")
        raise MotionStopped(f"{self.name}: the controller refused the move (its control script did not accept the "
                            "command); nothing moved; call connect() to upload the script again")

    def _check_arrival(self, kind: str, target) -> None:
        """The reported pose (a linear move) or joints (a joint move) after the move, once two more RTDE packages
        have arrived (the receive stream may lag the control stream that reported the end of the move); and the
        control script still running: a controller that refused the target once the move was under way (the arm
        behind it said no) stops it with a script error."""
        self._await_packages(2)
        self._check_safety()
        s = self.settings
        if kind == "linear":
            error = float(np.linalg.norm(np.subtract(self._receive.getActualTCPPose()[:3], target[:3])))
            missed = f"{error * 1e3:.3f} mm" if error > s.arrival_tolerance_m else None
            tolerance = f"{s.arrival_tolerance_m * 1e3} mm"
        else:
            errors = np.abs(np.subtract(self._receive.getActualQ(), target))
            worst = int(np.argmax(errors))
            missed = (f"{math.degrees(errors[worst]):.4f} deg (joint {JOINT_NAMES[worst]})"
                      if errors[worst] > s.arrival_tolerance_rad else None)
            tolerance = f"{math.degrees(s.arrival_tolerance_rad):.4f} deg"
        # the link is fine and pose() and joints() still tell where the arm stands; the next move finds the script
        # stopped and leaves the arm FAULTED (_explain_refusal)
        script_stopped = self._receive.getRuntimeState() != PLAYING
        if missed is None and not script_stopped:
            return
        what = f"the move ended {missed} from its target (tolerance {tolerance})" if missed else "the move ended"
        if script_stopped:
            raise MotionStopped(f"{self.name}: {what}; the controller stopped its control script (a script error: "
                                "it refused the target, e.g. outside the joint limits, out of reach or outside "
                                "the safety limits; its log says which). The arm stands there; nothing more will "
                                "move until connect() uploads the script again")
        raise MotionStopped(f"{self.name}: {what}; the arm stands there")

    def _await_packages(self, count: int) -> None:
        """Wait until `count` more RTDE packages have arrived (ConnectionLost if they stop within the link time-out)."""
        seen, updates = self._receive.getTimestamp(), 0
        deadline = time.monotonic() + self.settings.link_timeout_s
        while updates < count:
            self._check_link()
            if time.monotonic() > deadline:
                raise self._lost("RTDE timestamps stopped advancing")
            time.sleep(0.001)
            stamp = self._receive.getTimestamp()
            if stamp != seen:
                seen, updates = stamp, updates + 1

    def stop(self) -> None:
        """stopL or stopJ (as the last move was); safe in any state, never raises."""
        if self._state is not DeviceState.READY or self._control is None:
            return
        self._stop_done.clear()
        self._stop_requested.set()
        control = self._control
        try:
            if self._last_move == "joint":
                self._command("stopJ", lambda: control.stopJ(self.settings.stop_deceleration_rad_s2, False))
            else:
                self._command("stopL", lambda: control.stopL(self.settings.stop_deceleration_m_s2, False))
        except Exception as exc:  # noqa: BLE001 - a stop must not raise; the next command reports the state
            log.warning("%s: stop failed: %s", self.name, exc)
        finally:
            self._stop_done.set()

    def speed_stop(self, deceleration: float | None = None) -> None:
        """speedStop (ends speedL/speedJ motion)."""
        self._ready()
        control = self._control
        self._command("speedStop", lambda: control.speedStop(deceleration or self.settings.stop_deceleration_m_s2))

    # -- state -------------------------------------------------------------------------------------
    def pose(self) -> Pose:
        """The reported TCP pose (actual_TCP_pose) with its full orientation (quaternion w, x, y, z). After a
        tool-down move given by alpha, alpha is the turn nearest the commanded one (a rotation vector cannot tell
        350 deg from -10 deg, a routine that commanded 350 deg expects 350 back)."""
        self._ready()
        self._check_link()
        pose = pose_of(self._receive.getActualTCPPose())
        if self._alpha_hint is None:
            return pose
        alpha = self._alpha_hint + math.remainder(pose.alpha - self._alpha_hint, math.tau)
        return Pose(pose.x, pose.y, pose.z, alpha, pose.orientation)

    def joints(self) -> JointState:
        """actual_q: the six joint angles (rad), base to wrist 3."""
        self._ready()
        self._check_link()
        return JointState(tuple(float(v) for v in self._receive.getActualQ()), JOINT_NAMES)

    def set_tcp(self, offset) -> None:
        """TCP offset from the flange [x, y, z, rx, ry, rz] (m, rotation vector)."""
        self._ready()
        values = [float(v) for v in offset]
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"tcp offset must be 6 finite numbers [x, y, z, rx, ry, rz], got {offset}")
        control = self._control
        if not self._command("setTcp", lambda: control.setTcp(values)):
            self._check_link()
            raise DeviceError(f"{self.name}: the controller did not accept the TCP offset {values}")

    def robot_mode(self) -> str:
        self._ready()
        mode = int(self._receive.getRobotMode())
        return ROBOT_MODES.get(mode, f"UNKNOWN({mode})")

    def safety_mode(self) -> str:
        self._ready()
        mode = int(self._receive.getSafetyMode())
        return SAFETY_MODES.get(mode, f"UNKNOWN({mode})")

    def trigger_protective_stop(self) -> None:
        """Stop the arm as a safety event (the controller's protective_stop()); unlock it to go on. Returns once
        the receive stream has caught up with the stop, so safety_mode() reports it."""
        self._ready()
        control = self._control
        self._command("triggerProtectiveStop", control.triggerProtectiveStop)
        self._await_packages(2)

    def unlock_protective_stop(self) -> None:
        """Operator action after inspecting the cause: unlock on the dashboard; connect() again to resume."""
        self._ready()
        for request, call in (("close safety popup", self._dashboard.closeSafetyPopup),
                              ("unlock protective stop", self._dashboard.unlockProtectiveStop)):
            try:
                call()
            except RuntimeError as exc:
                if _timed_out(exc):  # a late reply would be read as the next request's: the link is spent
                    raise self._lost(f"the dashboard did not answer '{request}' in time: {exc}; "
                                     f"{TIMED_OUT_HINT}") from exc
                # ur_rtde raises with the controller's reply (e.g. "wait 5 s")
                raise ProtectiveStop(f"{self.name}: the controller refused to unlock: {exc}") from exc
        self._state = DeviceState.FAULTED  # the control program was paused by the stop: connect() re-uploads it


TIMED_OUT_HINT = ("ur_rtde 1.6.5's dashboard client gives up on a reply after about 2.5 s: the controller or the "
                  "network is too slow or busy")


def _timed_out(exc: BaseException) -> bool:
    """ur_rtde's time-outs surface as RuntimeErrors carrying boost's 'Operation canceled' (or 'timed out')."""
    text = str(exc).lower()
    return "operation canceled" in text or "timed out" in text or "timeout" in text


def _quiet_disconnect(part) -> None:
    try:
        part.disconnect()
    except Exception as exc:  # noqa: BLE001 - closing a dead link may fail; nothing left to do about it
        log.debug("disconnect failed: %s", exc)
