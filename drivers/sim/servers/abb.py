"""ABB protocol simulator: an open_abb RAPID server in front of the simulated world.

Serves the motion link (requests ``"NN p1 ... #"``) in one of two reply dialects
(`reply_dialect`): ``open_abb``, exactly the framing of the public SERVER.mod
(``"<code> <ok> <data>"``, no terminator, ``"0 1 "`` when there is no data), which the
public Python client (one ``recv`` per reply, ``float()`` on every token) needs; and
``cellctl``, our `CellctlServer.mod` (the same, ended by ``" #"``). Numbers are sent
as NumToStr does (no '+', fixed decimals), with our module's 4 (mm, deg) and 6
(quaternion) decimals in both dialects, so the simulated world keeps its resolution.
`start()` and cells' `sim.servers` default to ``cellctl`` (what a cellctl cell's
controller runs); `cellctl sim abb` defaults to ``open_abb`` for independent clients.

It also serves the logger link (lines ``"# 0 date time t x y z q1 q2 q3 q4"`` and
``"# 1 date time t j1..j6"``, each ended by a newline in both dialects, whitespace to a
client that splits; the stock LOGGER.mod sends none); the client may send
``"97 #"`` on it to stop the move in progress) on loopback, one client at a
time on each port, clients in sequence; a client that vanishes never stops
the server. It parses requests on its own (as the RAPID module does), so the
driver's encoder is checked against an independent reader.

The robot is the world's own arm fake (the micro cell's 4-axis `SimArm`, the
IRB 120 cell's `SimSixAxisArm`), so moves take simulated time, are refused
outside its box or joint limits, and obey the world's fault settings.
`abb_robots.py` says how each looks as a six-axis controller. On the wire:

- cartesian poses are mm and quaternions (w first) of the tool in the work
  object; tool (code 6) and work object (code 7) frames are applied to the
  flange (tool0) as on a controller. Micro cell: a MoveL/buffer target whose
  flange is not tool-down within `max_tilt_deg` is refused (ok=0). IRB 120:
  any orientation its nominal inverse kinematics reaches within the joint limits;
- joints: IRB 120, the six axes in degrees; micro cell, x, y, z (mm), alpha
  (deg), 0, 0 -- a jointtarget whose last two axes the 4-axis arm does not have
  (a MoveAbsJ with j5 or j6 not 0 is refused);
- zones (code 9): a MoveL (1, each buffered target of 33, 36) with a fly-by zone returns
  without settling, as RAPID runs on at a fly-by point (the world counts the motion, not
  the settling: the arm fake's `move_through`); with `fine` it returns settled. The reply
  still comes after the whole motion (a real controller's comes earlier, at the zone or
  before): the simulated time never undercounts. MoveAbsJ (2, 34) always settles here;
- status codes: 1 done, 0 bad message or refused, 2 protective stop (the arm
  refuses to move until `clear_protective_stop()`), 3 stopped by a stop request
  (the stock server sends only 0 and 1; the simulator sends 2 and 3 in both dialects);
- the codes of the public SERVER.mod beyond the basic set, as our RAPID module serves them.
  Neither simulated robot has external axes (a track, a positioner): code 5 answers six
  ``9E9`` (RAPID's "no such axis"; the micro cell's four axes are robot axes, reported by
  code 4); code 34 with six ``9E9`` is a MoveAbsJ that moves nothing (ok=1), with any
  value for an axis that is not there it is refused (ok=0). Codes 35 + 36 are MoveC: 35
  keeps the circle point (ok=0 for a bad quaternion or, on the micro cell, a tilted
  tool), 36 runs the arc from where the TCP stands through it to the end point; a 36
  with no 35 before it since the last 36 (or on this connection) is refused, as are
  three points that make no arc (`drivers/arms/abb/arc.py`: closer than 0.1 mm, or on
  one line) and an arc that leaves the arm's box anywhere (checked every mm). On the
  micro cell the arc lies in x, y, z with the tool down, alpha going to the end's. The
  world models where a move ends and how long it takes, not its path: the arm arrives
  at the end point as after a MoveL, and a stop part way leaves it on the chord.

Fault knobs (`AbbFaults`, changeable while serving): drop the motion connection
instead of answering once N messages were answered on it, delay every reply,
send malformed replies, protective stop (refuse every move), and a protective
stop part way along the next move (collision detection: the arm stands short of
its target, then refuses to move until cleared).
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
from dataclasses import dataclass, field, fields
from typing import Self

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from geometry.orientation import quaternion_wxyz

from drivers.arms.abb.arc import arc_points
from drivers.interfaces import (
    ConnectionLost,
    DeviceError,
    JointState,
    MotionRejected,
    MotionStopped,
    Pose,
    ProtectiveStop,
)
from drivers.limits import WorkspaceBox
from drivers.sim.servers import ANY_TURN, accepted, run_until, sim_device, world_of
from drivers.sim.servers.abb_robots import wire_robot
from drivers.sim.servers.knobs import check_link_knobs

MOTION_PORT = 5000
LOGGER_PORT = 5001
BUFFER_CAPACITY = 512
MAX_MESSAGE = 80  # a RAPID string: a longer request is a bad message
NO_AXIS_FROM = 1e9  # a requested value from this on means "no axis" (as CellctlServer.mod reads it)
ARC_CHECK_STEP_MM = 1.0

OK_BAD, OK_DONE, OK_PSTOP, OK_STOPPED = 0, 1, 2, 3
DIALECTS = ("open_abb", "cellctl")
DEFAULT_DIALECT = "cellctl"
SETTINGS = ("max_tilt_deg", "log_period_s", "reply_dialect")  # start() options that are not fault knobs


@dataclass
class AbbFaults:
    drop_after_messages: int | None = None  # close the motion link instead of answering message N+1 on a connection
    reply_delay_s: float = 0.0  # wait this long before every motion reply
    malformed_replies: bool = False  # answer every request with garbage
    protective_stop: bool = False  # the arm refuses to move (ok=2) until cleared
    # the next move stops with ok=2 at this fraction (0..1) of its way, then protective_stop is set
    protective_stop_mid_move: float | None = None

    @classmethod
    def from_options(cls, options: dict) -> AbbFaults:
        known = {f.name for f in fields(cls)}
        unknown = set(options) - known
        if unknown:
            allowed = sorted(known | set(SETTINGS))
            raise ValueError(f"unknown ABB simulator option(s) {sorted(unknown)}; allowed: {allowed}")
        faults = cls(**options)
        faults.check()
        return faults

    def check(self) -> None:
        check_link_knobs(self)
        if type(self.protective_stop) is not bool:
            raise ValueError(f"protective_stop={self.protective_stop!r}: true or false")
        f = self.protective_stop_mid_move
        if f is not None and type(f) not in (int, float):
            raise ValueError(f"protective_stop_mid_move={f!r}: the fraction of the move's way, 0 < f < 1")
        if f is not None and not 0.0 < f < 1.0:
            raise ValueError(f"protective_stop_mid_move={f}: the fraction of the move's way, 0 < f < 1")


@dataclass
class _Frame:
    """A rigid frame: position (mm) and rotation, as a tooldata/wobjdata frame."""

    p: np.ndarray = field(default_factory=lambda: np.zeros(3))
    r: Rotation = field(default_factory=Rotation.identity)


def _frame(values) -> _Frame | None:
    q = np.asarray(values[3:], dtype=float)
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        return None
    return _Frame(np.asarray(values[:3], dtype=float), Rotation.from_quat([q[1], q[2], q[3], q[0]]))


def _xyzw(q) -> list[float]:
    return [q[1], q[2], q[3], q[0]]


def _num(value: float, decimals: int) -> str:
    """Like RAPID NumToStr: fixed decimals, no '+', no '-0'."""
    text = f"{value:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0.0 else text


class AbbServer:
    """The simulator, in-process: `AbbServer(arm).start()`, then `close()` (or use it as a context manager).

    `arm` is a connected-or-not simulated arm (`SimArm`, `SimSixAxisArm`) on the world the test
    shares with its cameras. Ports 0 pick free ephemeral ports (see `motion_port`, `logger_port`).
    `info` is (serial, software, robot type); default: a simulator serial and the arm's type.
    `reply_dialect`: "open_abb" (the public server's replies) or "cellctl" (ended by '#'); an attribute,
    changeable while serving.
    """

    def __init__(self, arm, host: str = "127.0.0.1", motion_port: int = 0, logger_port: int = 0,
                 faults: AbbFaults | None = None, max_tilt_deg: float = 0.05, log_period_s: float = 0.01,
                 info: tuple[str, str, str] | None = None, reply_dialect: str = DEFAULT_DIALECT):
        if reply_dialect not in DIALECTS:
            raise ValueError(f"reply_dialect {reply_dialect!r} unknown; allowed: {', '.join(DIALECTS)}")
        self.reply_dialect = reply_dialect
        self.arm = arm
        self.robot = wire_robot(arm, math.radians(max_tilt_deg))
        self.faults = faults or AbbFaults()
        self.log_period_s = log_period_s
        self.info = info or ("SIM-0001", "6.99.0 cellctl-sim", self.robot.robot_type)
        self._closing = threading.Event()
        self._listeners = [self._listen(host, motion_port), self._listen(host, logger_port)]
        self.motion_port = self._listeners[0].getsockname()[1]
        self.logger_port = self._listeners[1].getsockname()[1]
        self.host = host
        self._threads: list[threading.Thread] = []
        self.messages_on_connection = 0  # requests answered on the current motion connection
        self.clients_served = 0
        self.moving = threading.Event()  # set while a move runs (tests wait on it before stopping)
        self._reset_controller()

    # -- lifecycle ----------------------------------------------------------------
    @staticmethod
    def _listen(host: str, port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(1)
        sock.settimeout(0.1)  # accept wakes up to notice close()
        return sock

    def start(self) -> AbbServer:
        for target, sock in ((self._serve_motion, self._listeners[0]), (self._serve_logger, self._listeners[1])):
            thread = threading.Thread(target=self._accept_loop, args=(sock, target), daemon=True,
                                      name=f"abb-sim-{sock.getsockname()[1]}")
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        self._closing.set()
        self.arm.stop()  # a move in progress ends
        for thread in self._threads:
            thread.join(timeout=5.0)
        for sock in self._listeners:
            sock.close()
        self._threads.clear()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def clear_protective_stop(self) -> None:
        self.faults.protective_stop = False
        self.faults.protective_stop_mid_move = None

    def _reset_controller(self) -> None:
        """What the RAPID module's Initialize sets at start: identity frames, v100, fine, empty buffer."""
        self.tool = _Frame()
        self.wobj = _Frame()
        self.speed = [100.0, 50.0, 0.0, 0.0]
        self.zone = (True, 0.0, 0.0, 0.0)
        self.buffer: list[tuple[np.ndarray, Rotation, float]] = []
        self.circle_point: tuple[np.ndarray, list[float]] | None = None  # code 35's, until a 36 uses it

    def _accept_loop(self, listener: socket.socket, serve) -> None:
        for client, _ in accepted(listener, self._closing):
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client.settimeout(0.1)
            try:
                serve(client)
            except OSError:
                pass  # the client vanished: serve the next one
            finally:
                client.close()

    # -- motion link ------------------------------------------------------------------
    def _serve_motion(self, client: socket.socket) -> None:
        self.clients_served += 1
        self.messages_on_connection = 0
        self.circle_point = None  # a circle point is never carried over to the next client
        if self.arm.state.value != "ready":  # a new client: the fake's link comes up again (after a drop too)
            self.arm.connect()
        buffer = b""
        while not self._closing.is_set():
            end = buffer.find(b"#")
            if end < 0:
                if len(buffer) > MAX_MESSAGE:  # RAPID would have cut it into strings: a bad message
                    buffer = b""
                    self._send(client, self._reply(-1, OK_BAD))
                try:
                    chunk = client.recv(1024)
                except TimeoutError:
                    continue
                if not chunk:
                    return
                buffer += chunk
                continue
            message, buffer = buffer[: end + 1], buffer[end + 1 :]
            drop = self.faults.drop_after_messages
            if drop is not None and self.messages_on_connection >= drop:
                return  # the link drops: no reply
            code, reply, close_after = self._handle(message)
            if code is None:
                return  # the arm fake lost its link (world fault): the controller link drops
            if self.faults.reply_delay_s > 0 and self._closing.wait(self.faults.reply_delay_s):
                return  # closing while a slow reply waits
            if self.faults.malformed_replies:
                reply = "?? garbled reply" + (" #" if self.reply_dialect == "cellctl" else "")
            # counted before it is sent: a client that has read the reply must find it counted (a test reads the
            # count right after a reply to set drop_after_messages; under load it read one too few)
            self.messages_on_connection += 1
            self._send(client, reply)
            if close_after:
                return

    @staticmethod
    def _send(client: socket.socket, text: str) -> None:
        client.sendall(text.encode("ascii"))  # one send per reply, as RAPID's SocketSend

    def _reply(self, code: int, ok: int, data: list[str] = ()) -> str:
        """open_abb: "<code> <ok> <data>" exactly as the public SERVER.mod builds it (so "0 1 " without data);
        cellctl: the same fields ended by " #"."""
        if self.reply_dialect == "cellctl":
            return " ".join([str(code), str(ok), *data, "#"])
        return f"{code} {ok} " + " ".join(data)

    def _handle(self, message: bytes) -> tuple[int | None, str, bool]:
        """One request -> (code, reply text, close the link after replying). code None: drop the link."""
        tokens = message.decode("ascii", "replace")[:-1].split()
        try:
            code = int(float(tokens[0]))
        except (IndexError, ValueError):
            return -1, self._reply(-1, OK_BAD), False  # no code to echo
        try:
            params = [float(t) for t in tokens[1:]]
        except ValueError:
            return code, self._reply(code, OK_BAD), False
        if not all(math.isfinite(p) for p in params):
            return code, self._reply(code, OK_BAD), False
        try:
            ok, data = self._execute(code, params)
        except ConnectionLost:
            return None, "", True
        return code, self._reply(code, ok, data), code == 99

    def _execute(self, code: int, p: list[float]) -> tuple[int, list[str]]:
        n = len(p)
        if code in (0, 31, 32, 33, 3, 4, 5, 97, 98, 99) and n != 0:
            return OK_BAD, []
        if code == 0 or code == 97 or code == 99:  # ping; stop with nothing moving; close
            return OK_DONE, []
        if code == 1 and n == 7:
            return self._move_cartesian([(np.array(p[:3]), p[3:])]), []
        if code == 2 and n == 6:
            return self._move_joints(p), []
        if code == 3:
            return OK_DONE, self._cartesian()
        if code == 4:
            return OK_DONE, self._joints()
        if code in (6, 7) and n == 7:
            frame = _frame(p)
            if frame is None:
                return OK_BAD, []
            if code == 6:
                self.tool = frame
            else:
                self.wobj = frame
            return OK_DONE, []
        if code == 8 and n in (2, 4):
            if p[0] <= 0 or p[1] <= 0:
                return OK_BAD, []
            self.speed[:n] = p
            return OK_DONE, []
        if code == 9 and n == 4:
            self.zone = (True, 0.0, 0.0, 0.0) if p[0] == 1 else (False, *p[1:])  # fine, or fly-by: _linear()
            return OK_DONE, []
        if code == 30 and n == 7:
            q = np.asarray(p[3:])
            if len(self.buffer) >= BUFFER_CAPACITY or abs(np.linalg.norm(q) - 1.0) > 1e-3:
                return OK_BAD, []
            self.buffer.append((np.array(p[:3]), p[3:], self.speed[0]))
            return OK_DONE, []
        if code == 31:
            self.buffer.clear()
            return OK_DONE, []
        if code == 32:
            return OK_DONE, [str(len(self.buffer))]
        if code == 33:
            for xyz, q, speed in self.buffer:
                ok = self._move_cartesian([(xyz, q)], speed)
                if ok != OK_DONE:
                    return ok, []
            return OK_DONE, []
        if code == 5:  # external axes: none on either simulated robot
            return OK_DONE, ["9E9"] * 6
        if code == 34 and n == 6:  # MoveAbsJ of the external axes: only "no axis" for each is possible here
            if any(v < NO_AXIS_FROM for v in p):
                return OK_BAD, []
            return (OK_PSTOP if self.faults.protective_stop else OK_DONE), []  # a MoveAbsJ that moves nothing
        if code == 35 and n == 7:  # MoveC's circle point: kept for the next 36
            if self._flange_for(np.array(p[:3]), p[3:]) is None:
                return OK_BAD, []
            self.circle_point = (np.array(p[:3]), p[3:])
            return OK_DONE, []
        if code == 36 and n == 7:
            return self._move_circular(np.array(p[:3]), p[3:]), []
        if code == 98:
            return OK_DONE, ["*".join(self.info)]
        return OK_BAD, []

    # -- tool and work object frames around the robot's flange (tool0) ------------------------
    def _flange_for(self, xyz_mm: np.ndarray, q) -> Pose | None:
        """The arm pose that puts the current tool at a target given in the current work object
        (None: a bad quaternion, or a flange orientation this robot cannot take)."""
        target = _frame([*xyz_mm, *q])
        if target is None:
            return None
        r_tcp = self.wobj.r * target.r
        p_tcp = self.wobj.p + self.wobj.r.apply(target.p)
        r_flange = r_tcp * self.tool.r.inv()
        p_flange = p_tcp - r_flange.apply(self.tool.p)
        return self.robot.flange_target(p_flange, r_flange)

    def _tcp(self) -> tuple[np.ndarray, np.ndarray]:
        """The current tool's position (mm) and quaternion (w first, w >= 0) in the current work object."""
        p_flange, r_flange = self.robot.flange()
        p_tcp = p_flange + r_flange.apply(self.tool.p)
        r_tcp = r_flange * self.tool.r
        inv = self.wobj.r.inv()
        q = np.array(quaternion_wxyz(inv * r_tcp))
        return inv.apply(p_tcp - self.wobj.p), (-q if q[0] < 0 else q)  # one sign for the same rotation

    def _cartesian(self) -> list[str]:
        p, q = self._tcp()
        return [_num(v, 4) for v in p] + [_num(v, 6) for v in q]

    def _joints(self) -> list[str]:
        return [_num(v, 4) for v in self.robot.wire_joints()]

    def _linear(self):
        """The arm fake's linear move under the current zone: settled at a fine point, passed (its motion
        counted, no settling) at a fly-by point; an arm fake that cannot pass settles."""
        if not self.zone[0] and hasattr(self.arm, "move_through"):
            return self.arm.move_through
        return self.arm.move_linear

    def _move_cartesian(self, targets, speed_mm_s: float | None = None) -> int:
        for xyz, q in targets:
            pose = self._flange_for(xyz, q)
            if pose is None:
                return OK_BAD
            ok = self._move(self._linear(), pose, (speed_mm_s or self.speed[0]) * 1e-3)
            if ok != OK_DONE:
                return ok
        return OK_DONE

    def _move_circular(self, end_xyz: np.ndarray, end_q) -> int:
        """36: MoveC from where the TCP stands through the kept circle point to the end point (all in the
        work object); refused (ok=0) without a circle point, for three points that make no arc, and for an
        arc that leaves the arm's box. The arm then moves to the end point (see the module docstring)."""
        if self.circle_point is None:
            return OK_BAD  # a 36 without its 35
        (via_xyz, _), self.circle_point = self.circle_point, None
        end = self._flange_for(end_xyz, end_q)
        if end is None:
            return OK_BAD
        try:
            points = arc_points(self._tcp()[0], via_xyz, end_xyz, ARC_CHECK_STEP_MM)
        except ValueError:
            return OK_BAD
        for point in points:
            pose = self._flange_for(point, end_q)
            if pose is None:
                return OK_BAD
            try:
                self.arm.settings.limits.check(pose)
            except MotionRejected:
                return OK_BAD
        return self._move(self._linear(), end, self.speed[0] * 1e-3)

    def _move_joints(self, p: list[float]) -> int:
        joints = self.robot.joints_from_wire(p)
        if joints is None:
            return OK_BAD  # axes this robot does not have
        return self._move(self.arm.move_joints, joints, self.speed[0] * 1e-3)

    def _move(self, move, target, speed_m_s: float) -> int:
        if self.faults.protective_stop:
            return OK_PSTOP
        fraction = self.faults.protective_stop_mid_move
        if fraction is not None:  # collision detection trips on the way: only part of it is travelled
            self.faults.protective_stop_mid_move = None
            target = self._part_way(target, fraction)
            if move == getattr(self.arm, "move_through", None):
                move = self.arm.move_linear  # the robot comes to a stand there, whatever the zone
        self.moving.set()
        try:
            move(target, speed_m_s)
        except MotionRejected:
            return OK_BAD
        except ProtectiveStop:
            return OK_PSTOP
        except MotionStopped:
            return OK_STOPPED
        finally:
            self.moving.clear()
        if fraction is not None:
            self.faults.protective_stop = True  # it stays stopped until cleared, as a controller does
            return OK_PSTOP
        return OK_DONE

    def _part_way(self, target, fraction: float):
        """The point `fraction` of the way from where the arm stands to `target` (a Pose or a JointState)."""
        if isinstance(target, JointState):
            now = self.arm.joints().positions
            return JointState(tuple(a + fraction * (b - a) for a, b in zip(now, target.positions)), target.names)
        now = self.arm.pose()
        xyz = now.xyz + fraction * (target.xyz - now.xyz)
        alpha = now.alpha + fraction * (target.alpha - now.alpha)
        orientation = None
        if target.orientation is not None and now.orientation is not None:
            ends = Rotation.from_quat([_xyzw(now.orientation), _xyzw(target.orientation)])
            orientation = quaternion_wxyz(Slerp([0.0, 1.0], ends)(fraction))
        return Pose(float(xyz[0]), float(xyz[1]), float(xyz[2]), float(alpha), orientation)

    # -- logger link ----------------------------------------------------------------------
    def _serve_logger(self, client: socket.socket) -> None:
        start = time.monotonic()
        now = time.gmtime()
        date, clock = time.strftime("%Y-%m-%d", now), time.strftime("%H:%M:%S", now)
        kind = 0
        incoming = b""
        while not self._closing.is_set():
            try:
                pose = self.arm.pose()
            except DeviceError:
                pose = None  # the fake's link is down: nothing to report this period
            if pose is not None:
                t = _num(time.monotonic() - start, 2)
                if kind == 0:
                    values = self._cartesian()
                else:
                    values = self._joints()
                self._send(client, " ".join(["#", str(kind), date, clock, t, *values]) + "\n")
                kind = 1 - kind
            readable, _, _ = select.select([client], [], [], self.log_period_s)
            if readable:
                chunk = client.recv(256)
                if not chunk:
                    return
                incoming += chunk
                while b"#" in incoming:
                    message, _, incoming = incoming.partition(b"#")
                    if message.split() == [b"97"]:
                        self.arm.stop()  # the motion link's move ends with status 3


def start(world, host: str = "127.0.0.1", port: int = MOTION_PORT, logger_port: int | None = None,
          options: dict | None = None, limits: dict | None = None) -> AbbServer:
    """Serve the arm of `world` (a micro cell or an IRB 120 cell, shared with the caller's cameras):
    motion on `port`, logger on `logger_port` (default port + 1). `limits` is the arm's workspace box
    (default: +-10 m, any turn). `options` are `AbbFaults` fields and the server settings `max_tilt_deg`
    (micro cell only), `log_period_s`, `reply_dialect` (default "cellctl"). Returns the running server;
    close() stops it."""
    arm = sim_device("arm", world, {"limits": WorkspaceBox(**(limits or ANY_TURN))})
    if logger_port is None:
        logger_port = port + 1 if port else 0
    options = dict(options or {})
    settings = {key: float(options.pop(key)) for key in ("max_tilt_deg", "log_period_s") if key in options}
    dialect = str(options.pop("reply_dialect", DEFAULT_DIALECT))
    return AbbServer(arm, host, port, logger_port, faults=AbbFaults.from_options(options), reply_dialect=dialect,
                     **settings).start()


def start_for_cell(world, spec, arm_limits: dict | None = None) -> AbbServer:
    """The simulator of a cell file's `sim.servers` entry (protocol abb), its logger on the next port."""
    return start(world, spec.host, MOTION_PORT if spec.port is None else spec.port, options=spec.options,
                 limits=arm_limits)


def serve(world_config=None, host: str = "127.0.0.1", port: int = MOTION_PORT, logger_port: int | None = None,
          options: dict | None = None, stop: threading.Event | None = None, world=None, limits: dict | None = None) -> None:
    """Serve until `stop` is set (see `start`); the world is `world` or one built from `world_config`."""
    run_until(start(world_of(world_config, world), host, port, logger_port, options, limits), stop)
