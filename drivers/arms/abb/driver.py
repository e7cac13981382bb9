"""AbbArm: an ABB robot running the cellctl RAPID server module (`rapid/CellctlServer.mod`) or the public
open_abb SERVER.mod.

One TCP link carries motion requests (port 5000), one request in flight at a
time; a second link (port 5001) streams the logger's pose and joint lines and
carries the stop request. Replies are read in either dialect (ended by '#', or
by their field count: protocol.py says how and where that falls short). Every
read has a time-out; a missing, late or malformed reply closes the link and
leaves the arm FAULTED until `connect()`.

Beyond the Arm interface, every code of the public SERVER.mod: external axes (5, 34:
`external_axes()`, `move_external_axes()`), circular moves (35 + 36: `move_circular()`,
the whole arc checked against the workspace box first), the path buffer (30-33), tool,
work object, speed, zone and robot info.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from dataclasses import replace
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from geometry.orientation import alpha_of, quaternion_wxyz, rotation_from_wxyz, tool_down

from drivers import endpoint
from drivers.arms.abb import protocol as wire
from drivers.arms.abb.arc import arc_points
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

Frame7 = tuple[float, float, float, float, float, float, float]
IDENTITY: Frame7 = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


class CommandRejected(DeviceError):
    """The controller answered 'bad message' (ok=0) to a non-motion command."""


class AbbArmSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = Field(..., min_length=1, description="controller address (e.g. 192.168.125.1)")
    model: Literal["irb120", "irb140", "irb1200", "irb1300", "irb1600", "irb2600", "irb4600", "irb6700",
                   "irb910sc"] | None = Field(
        None, description="the robot's model: an `arm` calibration (arm-kinematics) is activated only on a cell "
                          "whose arm is of the model it calibrated; unset: the model is not checked")
    motion_port: int = Field(5000, ge=1, le=65535, description="port of the RAPID motion server")
    logger_port: int | None = Field(
        5001, ge=1, le=65535, description="port of the RAPID logger (also carries stop); null: no logger link, no stop"
    )
    connect_timeout_s: float = Field(3.0, gt=0, le=60, description="time-out of the TCP connect")
    reply_timeout_s: float = Field(2.0, gt=0, le=60, description="time-out of a reply to a non-motion request")
    move_timeout_s: float = Field(120.0, gt=0, le=3600, description="time-out of a move (the reply comes at the fine point)")
    reply_quiet_gap_s: float = Field(
        wire.QUIET_GAP_S, gt=0, le=1.0,
        description="silence that ends an unterminated reply of unknown length (98 robot info from a stock server)")
    max_tcp_speed_mm_s: float = Field(250.0, gt=0, le=7000, description="fastest TCP speed the driver will ask for")
    speed_mm_s: float = Field(100.0, gt=0, le=7000, description="default TCP speed (speeddata v_tcp)")
    speed_ori_deg_s: float = Field(50.0, gt=0, le=1000, description="reorientation speed (v_ori)")
    speed_leax_mm_s: float = Field(50.0, ge=0, le=7000, description="linear external axes (v_leax)")
    speed_reax_deg_s: float = Field(50.0, ge=0, le=1000, description="rotating external axes (v_reax)")
    zone: str = Field("fine", description=f"zonedata of moves: one of {', '.join(wire.ZONE_NAMES)}")
    via_zone: str = Field(
        "z1", description="zonedata of a via point (move_through): a fly-by point, passed within its pzone_tcp "
                          "(z1: 1 mm) without stopping; keep it well under the clearance of the moves that use via "
                          f"points (3 mm over a part); 'fine' makes via points settle. One of {', '.join(wire.ZONE_NAMES)}")
    tool: Frame7 = Field(IDENTITY, description="tool frame on the flange: x, y, z (mm), q1..q4")
    workobject: Frame7 = Field(IDENTITY, description="work object frame: x, y, z (mm), q1..q4")
    linear_axes: tuple[int, ...] = Field(
        (), description="robot axes (1-6) that are linear: mm on the wire, m in JointState (IRB 910SC: [3])"
    )
    joint_limits: tuple[tuple[float, float], ...] | None = Field(
        None, description="optional (min, max) per axis in wire units (deg, mm for linear axes), checked before moving"
    )
    external_linear_axes: tuple[int, ...] = Field(
        (), description="external axes (1-6: eax_a..eax_f) that are linear: mm on the wire, m here; the others "
                        "rotate (deg on the wire, rad here)"
    )
    arc_check_step_mm: float = Field(
        1.0, gt=0, le=100, description="a circular move's arc is checked against the workspace box at points this far apart"
    )
    limits: WorkspaceBox

    @field_validator("zone", "via_zone")
    @classmethod
    def _known_zone(cls, zone, info):
        if zone not in wire.ZONE_NAMES:
            raise ValueError(f"{info.field_name} {zone!r} unknown; allowed: {', '.join(wire.ZONE_NAMES)}")
        return zone

    @field_validator("tool", "workobject")
    @classmethod
    def _unit_quaternion(cls, frame, info):
        q = frame[3:]
        if not math.isclose(math.sqrt(sum(v * v for v in q)), 1.0, abs_tol=1e-3):
            raise ValueError(f"{info.field_name}: quaternion {q} is not of unit length")
        return frame

    @field_validator("linear_axes", "external_linear_axes")
    @classmethod
    def _axes(cls, axes, info):
        if any(not 1 <= a <= 6 for a in axes):
            raise ValueError(f"{info.field_name} {axes}: axis numbers must be 1..6")
        return axes

    @field_validator("joint_limits")
    @classmethod
    def _joint_limits(cls, limits):
        if limits is not None and (len(limits) != 6 or any(not lo < hi for lo, hi in limits)):
            raise ValueError("joint_limits: six (min, max) pairs with min < max")
        return limits

    def endpoints(self) -> list[str]:
        """The controller's motion server (the logger port only reports)."""
        return [endpoint.tcp(self.host, self.motion_port)]


def _frame_parts(frame) -> tuple[tuple[float, ...], tuple[float, ...]]:
    frame = tuple(float(v) for v in frame)
    if len(frame) != 7:
        raise ValueError(f"a frame is 7 values x, y, z (mm), q1..q4; got {len(frame)}")
    return frame[:3], frame[3:]


class AbbArm(Driver):
    """Arm driver for an ABB controller running `CellctlServer.mod` or the stock open_abb SERVER.mod.

    Against the stock server: poses come with the decimals its NumToStr calls give (the
    cellctl module sends 4 for mm, 6 for quaternions), it never reports statuses 2 and 3
    (a collision stops its program: the move times out), and its LOGGER.mod takes no stop
    request.

    Units: `Pose` in metres and radians; on the wire mm, degrees and quaternions.
    A `Pose` without `orientation` means the tool pointing down turned by `alpha`
    (geometry/orientation.py). Moves block until the controller replies, which the
    server does after its MoveL/MoveAbsJ returns (at a fine point with the default
    zone 'fine'). Via points (`move_through`, MovesThrough) are MoveL with the fly-by zone
    `via_zone`: the reply comes once RAPID runs on past the move, before the robot stands
    there; SET_ZONE goes out only when the zone changes (the via zone before a via point,
    the ordinary zone before the next other move). A stop() that arrives after a via point's
    reply and before the next move finds no move instruction running: CellctlServer.mod's
    StopTrap then stops the robot and clears its path (the rest of the corner path).
    Quaternions cannot say 'alpha + 360 deg': a cartesian target is
    reached by the controller's nearest configuration (ConfL off); use
    `move_joints` for a given turn.
    """

    Settings = AbbArmSettings
    LINK_LOST = "the link to the controller is down; call connect() again before going on"

    def __init__(self, name: str, settings: AbbArmSettings):
        super().__init__(name, settings)
        self._io = threading.Lock()  # one request in flight on the motion link
        self._sock: socket.socket | None = None
        self._rest = b""
        self._terminated = False  # the server ends its replies with '#' (cellctl dialect)
        self._log_sock: socket.socket | None = None
        self._log_thread: threading.Thread | None = None
        self._log_lock = threading.Lock()
        self._log_samples: dict[int, wire.LogSample] = {}
        self._log_error: str | None = None
        self._speed_sent: tuple[float, float, float, float] | None = None
        self._zone = settings.zone  # the zone of every move but a via point: the cell file's, or set_zone()'s
        self._zone_sent: str | None = None  # the zone the controller holds (None: not known)

    @property
    def max_speed_m_s(self) -> float:
        return self.settings.max_tcp_speed_mm_s * 1e-3

    def check_target(self, target: Pose) -> None:
        """The box, as a move checks it (the joint limits of a Cartesian target are the controller's to check)."""
        self._checked_target(target)

    # -- lifecycle ------------------------------------------------------------
    def connect(self) -> None:
        """Open the links, check the server answers, and load tool, work object, speed and zone."""
        with self._io:
            self._close_links()
            s = self.settings
            where = f"{s.host}:{s.motion_port}"
            try:
                self._sock = socket.create_connection((s.host, s.motion_port), timeout=s.connect_timeout_s)
                self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError as exc:
                self._close_links()
                self._state = DeviceState.FAULTED
                raise ConnectionLost(
                    f"{self.name}: cannot connect to the ABB motion server at {where}: {exc}; "
                    "check the controller runs CellctlServer.mod and the address"
                ) from exc
            self._rest = b""
            self._terminated = False
            self._speed_sent = None
            self._zone, self._zone_sent = s.zone, None
            self._state = DeviceState.READY
            try:
                self._exchange(wire.ping(), wire.PING)
                self._exchange(wire.set_tool(*_frame_parts(s.tool)), wire.SET_TOOL)
                self._exchange(wire.set_workobject(*_frame_parts(s.workobject)), wire.SET_WORKOBJECT)
                self._send_speed((s.speed_mm_s, s.speed_ori_deg_s, s.speed_leax_mm_s, s.speed_reax_deg_s))
                self._send_zone(s.zone)
                if s.logger_port is not None:
                    self._open_logger()
            except DeviceError:
                self._close_links()
                self._state = DeviceState.FAULTED
                raise

    def close(self) -> None:
        """Say goodbye (code 99) if the link is up, then close both links. Idempotent."""
        with self._io:
            if self._state is DeviceState.READY and self._sock is not None:
                try:  # courtesy only: the server also copes with a vanished client
                    self._sock.sendall(wire.close())
                    self._read_frame(min(self.settings.reply_timeout_s, 0.5), wire.close(), wire.CLOSE)
                except (OSError, DeviceError):
                    pass
            self._close_links()
            self._state = DeviceState.CLOSED

    def stop(self) -> None:
        """Ask the controller to abort the move in progress. Always safe; never raises.

        What a socket-only protocol can do: the RAPID motion task is inside its
        MoveL while a move runs and reads nothing from the motion socket, and
        closing that socket is not noticed until the move has ended. So the stop
        request (`97 #`) goes over the logger link, served by the logger's
        background task, which sets a persistent flag; an IPers interrupt in the
        motion task then runs StopMove + ClearPath and ends the move, and the
        move's reply carries status 3, raised here as MotionStopped in the thread
        that called the move. Without a logger link (`logger_port: null`) there is
        no way to interrupt a move from the PC: stop() then does nothing, and the
        emergency stop or the FlexPendant remain the way to stop the robot.

        The logger task reads the request on its own time: one that arrives after
        the move it was meant for has ended stops the next move instead. That
        race only ever stops, and it is kept: sending the request only while a
        move is in flight would close it, but a stop asked for just before a
        move begins would then be dropped and the move run in full.
        """
        sock = self._log_sock
        if sock is None:
            return
        try:
            sock.sendall(wire.stop())
        except OSError:
            pass

    # -- Arm interface ----------------------------------------------------------
    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        """MoveL to `target` (speed in m/s, default from the settings); returns once the controller replied."""
        xyz_mm, quaternion = self._checked_target(target)
        request = wire.move_linear(xyz_mm, quaternion)
        self._move(request, wire.MOVE_LINEAR, speed)

    def move_through(self, target: Pose, speed: float | None = None) -> None:
        """A via point (MovesThrough): MoveL to `target` with the fly-by zone `via_zone` (default z1), so the
        controller replies as soon as its program runs on past the move (by the zone, before the robot stands at
        the target) and blends into the next move; the next ordinary move sets the zone back first. Checked,
        refused, stopped and faulted exactly as move_linear. After the reply the robot may still be on its way:
        nothing is measured or gripped at a via point, and the next move follows at once. A controller whose
        next move comes too late turns the fly-by point into a stop point there (RAPID's corner path warning)."""
        xyz_mm, quaternion = self._checked_target(target)
        self._move(wire.move_linear(xyz_mm, quaternion), wire.MOVE_LINEAR, speed, zone=self.settings.via_zone)

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        """MoveAbsJ to six axis values (rad, or m for `linear_axes`); speed is the TCP speed in m/s."""
        values = self._wire_joints(joints)
        self._move(wire.move_joints(values), wire.MOVE_JOINTS, speed)

    def pose(self) -> Pose:
        """The TCP of the current tool in the current work object, as the controller reports it."""
        reply = self._ok(wire.get_cartesian(), wire.GET_CARTESIAN, 7)
        xyz, q = wire.parse_cartesian(reply)
        try:
            rotation = rotation_from_wxyz(q)
        except ValueError as exc:
            raise self._fault(wire.MalformedReply(f"{self.name}: reported orientation unusable: {exc}")) from None
        return Pose(xyz[0] * 1e-3, xyz[1] * 1e-3, xyz[2] * 1e-3, alpha_of(rotation), tuple(q))

    def joints(self) -> JointState:
        values = wire.parse_joints(self._ok(wire.get_joints(), wire.GET_JOINTS, 6))
        positions = tuple(
            v * 1e-3 if i + 1 in self.settings.linear_axes else math.radians(v) for i, v in enumerate(values)
        )
        return JointState(positions, tuple(f"j{i}" for i in range(1, 7)))

    # -- ABB extras -------------------------------------------------------------
    def ping(self) -> None:
        self._ok(wire.ping(), wire.PING)

    def robot_info(self) -> wire.RobotInfo:
        return wire.parse_robot_info(self._ok(wire.robot_info(), wire.ROBOT_INFO, None))

    def set_tool(self, frame) -> None:
        """Tool frame on the flange: 7 values x, y, z (mm), q1..q4."""
        self._ok(wire.set_tool(*self._unit_frame(frame, "tool")), wire.SET_TOOL)

    def set_workobject(self, frame) -> None:
        """Work object (user frame): 7 values x, y, z (mm), q1..q4."""
        self._ok(wire.set_workobject(*self._unit_frame(frame, "workobject")), wire.SET_WORKOBJECT)

    def set_speed(self, tcp_mm_s: float, ori_deg_s: float | None = None,
                  leax_mm_s: float | None = None, reax_deg_s: float | None = None) -> None:
        """Speed of later moves (speeddata); refuses a TCP speed above `max_tcp_speed_mm_s`."""
        s = self.settings
        if not 0 < tcp_mm_s <= s.max_tcp_speed_mm_s:
            raise ValueError(f"tcp_mm_s={tcp_mm_s}: allowed 0 < tcp_mm_s <= max_tcp_speed_mm_s={s.max_tcp_speed_mm_s}")
        self._ready()
        with self._io:
            self._send_speed((
                tcp_mm_s,
                s.speed_ori_deg_s if ori_deg_s is None else ori_deg_s,
                s.speed_leax_mm_s if leax_mm_s is None else leax_mm_s,
                s.speed_reax_deg_s if reax_deg_s is None else reax_deg_s,
            ))

    def set_zone(self, zone: str) -> None:
        """The zone of every later move but via points, until connect() sets the cell file's again: 'fine' (moves
        return at the target) or z0..z200 (for buffered paths that blend)."""
        if zone not in wire.ZONE_NAMES:
            raise ValueError(f"zone {zone!r} unknown; allowed: {', '.join(wire.ZONE_NAMES)}")
        self._ready()
        with self._io:
            self._send_zone(zone)
            self._zone = zone

    def buffer_add(self, target: Pose) -> None:
        """Append a linear target (at the current speed) to the controller's path buffer."""
        xyz_mm, quaternion = self._checked_target(target)
        request = wire.buffer_add(xyz_mm, quaternion)
        reply = self._exchange_checked(request, wire.BUFFER_ADD, 0, self.settings.reply_timeout_s)
        if reply.ok != wire.OK_DONE:
            raise MotionRejected(f"{self.name}: the controller refused the buffer target (ok={reply.ok}); "
                                 f"its buffer holds at most {wire.BUFFER_CAPACITY} targets")

    def buffer_clear(self) -> None:
        self._ok(wire.buffer_clear(), wire.BUFFER_CLEAR)

    def buffer_length(self) -> int:
        return wire.parse_buffer_length(self._ok(wire.buffer_length(), wire.BUFFER_LENGTH, 1))

    def buffer_execute(self) -> None:
        """Run the buffered targets as MoveL; returns after the last (the buffer is kept)."""
        self._move(wire.buffer_execute(), wire.BUFFER_EXECUTE, None)

    def external_axes(self) -> tuple[float | None, ...]:
        """Where the six external axes eax_a..eax_f are (code 5): m for `external_linear_axes`, else rad;
        None for an axis the robot does not have (RAPID's 9E9). A cell without external axes: six Nones."""
        values = wire.parse_external_axes(self._ok(wire.get_external_axes(), wire.GET_EXTERNAL_AXES, 6))
        return tuple(None if v is None else self._from_wire_external(i, v) for i, v in enumerate(values, start=1))

    def move_external_axes(self, values) -> None:
        """Move the external axes (code 34: MoveAbsJ, the robot's own axes standing still) to six values
        (m for `external_linear_axes`, else rad); None for an axis the robot does not have. The controller
        refuses (MotionRejected, nothing moved) a value for an absent axis and None for a present one."""
        self._ready()
        if len(values) != 6:
            raise MotionRejected(f"{self.name}: an extjoint has 6 axes (eax_a..eax_f), got {len(values)} values; "
                                 "nothing moved")
        wire_values = [None if v is None else self._to_wire_external(i, v) for i, v in enumerate(values, start=1)]
        if not all(v is None or math.isfinite(v) for v in wire_values):
            raise MotionRejected(f"{self.name}: external axis values {tuple(values)} are not all finite; nothing moved")
        try:
            request = wire.move_external_axes(wire_values)
        except ValueError as exc:
            raise MotionRejected(f"{self.name}: {exc}; nothing moved") from None
        self._move(request, wire.MOVE_EXTERNAL_AXES, None,
                   refused="a value for an external axis the robot does not have, or none (None) for one it has; "
                           "external_axes() says which it has")

    def move_circular(self, via: Pose, target: Pose, speed: float | None = None) -> None:
        """MoveC (codes 35 + 36): from where the TCP stands, along the circle through `via`, to `target`
        (speed in m/s, default from the settings). Both points are checked against the workspace box, and
        so is the whole arc (at `arc_check_step_mm`): an arc can leave the box between points inside it.
        The TCP orientation goes from the start's to the target's, as RAPID's MoveC turns it."""
        via_xyz, via_q = self._checked_target(via)
        end_xyz, end_q = self._checked_target(target)
        start = self.pose()
        try:
            points = arc_points(start.xyz * 1e3, via_xyz, end_xyz, self.settings.arc_check_step_mm)
        except ValueError as exc:
            raise MotionRejected(f"{self.name}: no circular move through {via_xyz} to {end_xyz} mm from "
                                 f"{tuple(start.xyz * 1e3)} mm: {exc}; nothing moved") from None
        alpha = alpha_of(rotation_from_wxyz(end_q))
        for x, y, z in points:
            try:
                self.settings.limits.check(Pose(x * 1e-3, y * 1e-3, z * 1e-3, alpha))
            except MotionRejected as exc:
                raise MotionRejected(f"{self.name}: the arc leaves the workspace box at ({x:.3f}, {y:.3f}, {z:.3f}) "
                                     f"mm: {exc}") from None
        self._move(wire.move_circular(end_xyz, end_q), wire.MOVE_CIRCULAR, speed,
                   before=(wire.circle_point(via_xyz, via_q), wire.CIRCLE_POINT),
                   refused="an arc the controller cannot run (out of reach, or its circle point not between)")

    def logged(self) -> tuple[wire.LogSample | None, wire.LogSample | None]:
        """The latest logger samples (cartesian, joints), or None before the first; raises if the stream broke."""
        with self._log_lock:
            if self._log_error:
                raise ConnectionLost(f"{self.name}: logger link: {self._log_error}")
            return self._log_samples.get(0), self._log_samples.get(1)

    # -- internals ----------------------------------------------------------------
    def _fault(self, error: Exception) -> Exception:
        self._close_links()
        self._state = DeviceState.FAULTED
        return error

    def _close_links(self) -> None:
        for sock in (self._sock, self._log_sock):
            if sock is not None:
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()
        self._sock = self._log_sock = None
        thread, self._log_thread = self._log_thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)

    def _unit_frame(self, frame, field: str):
        xyz, q = _frame_parts(frame)
        if not math.isclose(math.sqrt(sum(v * v for v in q)), 1.0, abs_tol=1e-3):
            raise ValueError(f"{field}: quaternion {q} is not of unit length")
        return xyz, q

    def _checked_target(self, target: Pose):
        """Check the target against the workspace box before any byte is sent; return its wire values."""
        self._ready()
        if target.orientation is None:
            rotation = tool_down(target.alpha)
        else:
            try:
                rotation = rotation_from_wxyz(target.orientation)
            except ValueError as exc:
                raise MotionRejected(f"{self.name}: {exc}; nothing moved") from None
            target = replace(target, alpha=alpha_of(rotation))
        self.settings.limits.check(target)
        return (target.x * 1e3, target.y * 1e3, target.z * 1e3), quaternion_wxyz(rotation)

    def _wire_joints(self, joints: JointState) -> list[float]:
        self._ready()
        if len(joints.positions) != 6:
            raise MotionRejected(f"{self.name}: an ABB robot takes 6 axis values, got {len(joints.positions)}; nothing moved")
        values = [
            v * 1e3 if i + 1 in self.settings.linear_axes else math.degrees(v) for i, v in enumerate(joints.positions)
        ]
        if not all(math.isfinite(v) for v in values):
            raise MotionRejected(f"{self.name}: axis values {joints.positions} are not all finite; nothing moved")
        if self.settings.joint_limits is not None:
            for i, (v, (lo, hi)) in enumerate(zip(values, self.settings.joint_limits), start=1):
                if not lo <= v <= hi:
                    raise MotionRejected(f"{self.name}: axis {i} target {v:.4f} is outside joint_limits [{lo}, {hi}]; nothing moved")
        return values

    def _to_wire_external(self, axis: int, value: float) -> float:
        return value * 1e3 if axis in self.settings.external_linear_axes else math.degrees(value)

    def _from_wire_external(self, axis: int, value: float) -> float:
        return value * 1e-3 if axis in self.settings.external_linear_axes else math.radians(value)

    def _move(self, request: bytes, code: int, speed: float | None, before: tuple[bytes, int] | None = None,
              refused: str = "unreachable target or bad message", zone: str | None = None) -> None:
        """Send the speed and the zone (`zone`, default the ordinary moves') if they changed, then `before` (a
        request that must be answered ok=1 first, e.g. the circle point), then the move `request`; map its status
        to the errors of the Arm interface."""
        s = self.settings
        if speed is not None and not 0 < speed * 1e3 <= s.max_tcp_speed_mm_s:
            raise MotionRejected(
                f"{self.name}: speed {speed} m/s outside 0 < speed <= {s.max_tcp_speed_mm_s / 1e3} m/s; nothing moved"
            )
        self._ready()
        with self._io:
            tcp = s.speed_mm_s if speed is None else speed * 1e3
            self._send_speed((tcp, s.speed_ori_deg_s, s.speed_leax_mm_s, s.speed_reax_deg_s))
            self._send_zone(self._zone if zone is None else zone)
            if before is not None:
                first = self._exchange_checked(*before, 0, s.reply_timeout_s)
                if first.ok != wire.OK_DONE:
                    raise MotionRejected(f"{self.name}: the controller refused {before[0].decode()!r} (ok={first.ok}: "
                                         f"{refused}); nothing moved")
            reply = self._exchange_checked(request, code, 0, s.move_timeout_s)
        if reply.ok == wire.OK_DONE:
            return
        if reply.ok == wire.OK_PROTECTIVE_STOP:
            raise ProtectiveStop(f"{self.name}: the controller reports a protective stop; clear it on the controller, then retry")
        if reply.ok == wire.OK_STOPPED:
            raise MotionStopped(f"{self.name}: move stopped by a stop request before its target; the arm stands where it stopped")
        raise MotionRejected(f"{self.name}: the controller refused {request.decode()!r} (ok=0: {refused}); nothing moved")

    def _send_speed(self, speed: tuple[float, float, float, float]) -> None:
        """Send speeddata only when it changes (caller holds the link lock)."""
        if speed != self._speed_sent:
            self._exchange(wire.set_speed(*speed), wire.SET_SPEED)
            self._speed_sent = speed

    def _send_zone(self, zone: str) -> None:
        """Send zonedata only when it changes (caller holds the link lock, or is connect()). Not known after a
        refused or lost exchange: sent again before the next move."""
        if zone != self._zone_sent:
            self._zone_sent = None
            self._exchange(wire.set_zone(zone), wire.SET_ZONE)
            self._zone_sent = zone

    def _ok(self, request: bytes, code: int, n_fields: int | None = 0) -> wire.Reply:
        self._ready()
        with self._io:
            return self._exchange(request, code, n_fields)

    def _exchange(self, request: bytes, code: int, n_fields: int | None = 0) -> wire.Reply:
        reply = self._exchange_checked(request, code, n_fields, self.settings.reply_timeout_s)
        if reply.ok != wire.OK_DONE:
            raise CommandRejected(f"{self.name}: the controller answered {reply.status} (ok={reply.ok}) to {request.decode()!r}")
        return reply

    def _exchange_checked(self, request: bytes, code: int, n_fields: int | None, timeout_s: float) -> wire.Reply:
        """Send one request and read its reply (caller holds the link lock, or is connect())."""
        if self._state is not DeviceState.READY or self._sock is None:
            self._ready()
            raise ConnectionLost(f"{self.name}: the link closed; call connect() again")
        try:
            self._sock.sendall(request)
        except OSError as exc:
            raise self._fault(ConnectionLost(f"{self.name}: connection lost sending {request.decode()!r}: {exc}; "
                                             "call connect() again")) from exc
        frame = self._read_frame(timeout_s, request, code)
        try:
            return wire.parse_reply(frame, code, n_fields)
        except wire.MalformedReply as exc:
            raise self._fault(wire.MalformedReply(f"{self.name}: {exc}")) from None

    def _read_frame(self, timeout_s: float, request: bytes, code: int) -> bytes:
        """One reply, framed as protocol.take_frame says; a reply of unknown length ends after a quiet gap."""
        deadline = time.monotonic() + timeout_s
        buffer = self._rest
        while True:
            try:
                frame, rest = wire.take_frame(buffer, code, self._terminated)
            except wire.MalformedReply as exc:
                raise self._fault(wire.MalformedReply(f"{self.name}: {exc}")) from None
            if frame is not None:
                self._rest = rest
                self._terminated = self._terminated or frame.endswith(b"#")
                return frame
            quiet = wire.needs_quiet_gap(buffer, code, self._terminated)
            remaining = deadline - time.monotonic()
            if remaining <= 0 and not quiet:
                raise self._fault(wire.ReplyTimeout(
                    f"{self.name}: no complete reply to {request.decode()!r} within {timeout_s} s "
                    f"(got {buffer!r}); the link is closed. Check the controller (protective or emergency stop, "
                    "program stopped), then call connect() again"))
            try:
                self._sock.settimeout(max(min(remaining, self.settings.reply_quiet_gap_s) if quiet else remaining, 1e-4))
                chunk = self._sock.recv(4096)
            except TimeoutError:
                if quiet:  # silence after the last byte: that was the whole reply
                    self._rest = b""
                    return bytes(buffer)
                continue
            except OSError as exc:
                raise self._fault(ConnectionLost(f"{self.name}: connection lost waiting for the reply to "
                                                 f"{request.decode()!r}: {exc}; call connect() again")) from exc
            if not chunk:
                raise self._fault(ConnectionLost(f"{self.name}: the controller closed the connection while "
                                                 f"{request.decode()!r} was in flight; call connect() again"))
            buffer += chunk

    # -- logger link ------------------------------------------------------------------
    def _open_logger(self) -> None:
        s = self.settings
        try:
            sock = socket.create_connection((s.host, s.logger_port), timeout=s.connect_timeout_s)
        except OSError as exc:
            raise ConnectionLost(f"{self.name}: cannot connect to the ABB logger at {s.host}:{s.logger_port}: {exc}; "
                                 "check LOGGER task runs, or set logger_port: null (then stop() cannot stop a move)") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(0.5)  # lets the reader notice a closed link
        with self._log_lock:
            self._log_samples.clear()
            self._log_error = None
        self._log_sock = sock
        self._log_thread = threading.Thread(target=self._read_logger, args=(sock,), name=f"{self.name}-abb-logger", daemon=True)
        self._log_thread.start()

    def _read_logger(self, sock: socket.socket) -> None:
        """Drain the logger stream (a full socket would block the controller's logger) and keep the latest samples."""
        buffer = b""
        while self._log_sock is sock:
            try:
                chunk = sock.recv(8192)
            except TimeoutError:
                continue
            except OSError:
                return  # closed by _close_links
            if not chunk:
                if self._log_sock is sock:
                    with self._log_lock:
                        self._log_error = "the controller closed the logger link"
                return
            buffer += chunk
            lines, buffer = wire.split_log_lines(buffer)
            if len(buffer) > 4096:  # no line end in sight: not a logger stream
                with self._log_lock:
                    self._log_error = f"logger sends no line ends ({buffer[:40]!r}...)"
                buffer = b""
            for line in lines:
                try:
                    sample = wire.parse_log_line(line)
                except wire.MalformedReply as exc:
                    with self._log_lock:
                        self._log_error = str(exc)
                    continue
                with self._log_lock:
                    self._log_samples[sample.kind] = sample
