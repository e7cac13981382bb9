"""The open_abb socket protocol: encoding requests, framing and parsing replies (both reply dialects).

Pure functions, no sockets: `driver.py` moves the bytes, the tests pin them.

Wire format (ASCII, one request in flight at a time):

- request: ``"NN p1 p2 ... #"`` -- a two-digit code, parameters separated by single
  spaces, a final ``#``. Lengths in mm with 4 decimals (0.1 um), quaternions
  (w first) with 6 decimals, angles in degrees with 4 decimals, every number
  signed (``+50.0000``). A request is at most 80 characters: a RAPID ``string``
  holds no more, so the server reads each request into one string.
- reply, in one of two dialects:

  - ``open_abb``, what the public SERVER.mod sends: ``"<code> <ok> <data>"`` with no
    terminator at all (a data-less reply is ``"0 1 "``, with the trailing space);
  - ``cellctl``, what our `rapid/CellctlServer.mod` sends: the same fields and a
    final ``#`` (``"0 1 #"``, ``"3 1 x y z q1 q2 q3 q4 #"``).

Framing a reply (`take_frame`, `needs_quiet_gap`), the rule the driver follows:

1. a reply that ends in ``#`` is complete at the ``#``; once a link has sent one, every
   later reply on it must end so (a split ``"0 1 "`` + ``"#"`` cannot be mistaken for two);
2. otherwise a reply is complete once it holds the code, the status and, for status 1,
   the number of data fields its request code implies (`REPLY_FIELDS`: 7 for 03, 6 for
   04, 1 for 32, none for the rest); any other status carries no data;
3. for 98 (robot info: the robot type may contain spaces) and codes the table does not
   know, only a short quiet gap (`QUIET_GAP_S`, a driver setting) after the last byte ends it.

Limits, all from the stock server giving no terminator: rule 2 cannot see whether the
last number is whole (a ``recv`` returning ``"... 0.70"`` of ``"... 0.7071"``), and rule 3
cuts a reply whose parts arrive further apart than the gap. A reply of at most 80 bytes
sent by one ``SocketSend`` travels in one TCP segment, so neither happens in practice;
the public client assumes even more (one ``recv`` is one reply). The cellctl dialect has
neither limit, which is why our RAPID module ends its replies with ``#``.

The codes of the public SERVER.mod beyond the basic set, all of them served by our module:
5 (external axes: six values, ``9E9`` for an axis the robot does not have), 34 (move the
external axes, the robot's own standing still), 35 + 36 (a circular move: 35 stores the
circle point, 36 moves from where the TCP stands through it to the end point, MoveC).
``9E9`` is RAPID's value for an absent axis; on the wire we send it as ``9E9`` (so six of
them fit in a request), and read any value from `ABSENT_FROM` on as "no axis": the stock
server cuts every value of its reply to 5 to 8 characters, so its 9E9 may come as
``90000000``.

Status codes (the ``ok`` field): 1 done; 0 bad message or refused target;
2 protective stop (the robot stopped for safety: collision detection, or the
controller refuses to move; clear it on the controller); 3 stopped by a stop
request (code 97 on the logger link) before reaching the target. The stock server
only ever sends 0 and 1.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from drivers.interfaces import ConnectionLost

# --- codes -------------------------------------------------------------------

PING = 0
MOVE_LINEAR = 1
MOVE_JOINTS = 2
GET_CARTESIAN = 3
GET_JOINTS = 4
SET_TOOL = 6
SET_WORKOBJECT = 7
SET_SPEED = 8
SET_ZONE = 9
GET_EXTERNAL_AXES = 5
BUFFER_ADD = 30
BUFFER_CLEAR = 31
BUFFER_LENGTH = 32
BUFFER_EXECUTE = 33
MOVE_EXTERNAL_AXES = 34
CIRCLE_POINT = 35  # MoveC, first half: the circle point (stored, nothing moves)
MOVE_CIRCULAR = 36  # MoveC, second half: through the stored circle point to this end point
STOP = 97  # sent on the logger link (the motion task is busy inside its move instruction)
ROBOT_INFO = 98
CLOSE = 99

OK_BAD_MESSAGE = 0
OK_DONE = 1
OK_PROTECTIVE_STOP = 2
OK_STOPPED = 3
STATUS_NAMES = {0: "bad message or refused", 1: "done", 2: "protective stop", 3: "stopped by request"}

MAX_REQUEST_CHARS = 80  # a RAPID string holds at most 80 characters
MAX_REPLY_BYTES = 256  # RAPID sends at most 80; more without a complete reply means the stream is garbage

# Data fields of a successful (ok=1) reply, by request code; 98 and unknown codes: not known (quiet gap).
REPLY_FIELDS: dict[int, int] = {
    PING: 0, MOVE_LINEAR: 0, MOVE_JOINTS: 0, GET_CARTESIAN: 7, GET_JOINTS: 6, SET_TOOL: 0,
    SET_WORKOBJECT: 0, SET_SPEED: 0, SET_ZONE: 0, BUFFER_ADD: 0, BUFFER_CLEAR: 0, BUFFER_LENGTH: 1,
    BUFFER_EXECUTE: 0, STOP: 0, CLOSE: 0, GET_EXTERNAL_AXES: 6, MOVE_EXTERNAL_AXES: 0, CIRCLE_POINT: 0,
    MOVE_CIRCULAR: 0,
}
ABSENT_AXIS = "9E9"  # RAPID's value of an external axis that is not there, as we send it
ABSENT_FROM = 9e7  # a reported value from this on means "no axis" (9E9, or the stock server's 8-character cut of it)
QUIET_GAP_S = 0.02  # silence that ends a reply whose field count is not known (98)
BUFFER_CAPACITY = 512  # targets the server's path buffer holds

# Standard RAPID zonedata (pzone_tcp mm, pzone_ori mm, zone_ori deg), as in the RAPID manual.
ZONES: dict[str, tuple[float, float, float]] = {
    "z0": (0.3, 0.3, 0.03),
    "z1": (1.0, 1.0, 0.1),
    "z5": (5.0, 8.0, 0.8),
    "z10": (10.0, 15.0, 1.5),
    "z15": (15.0, 23.0, 2.3),
    "z20": (20.0, 30.0, 3.0),
    "z30": (30.0, 45.0, 4.5),
    "z50": (50.0, 75.0, 7.5),
    "z100": (100.0, 150.0, 15.0),
    "z200": (200.0, 300.0, 30.0),
}
ZONE_NAMES = ("fine", *ZONES)


class MalformedReply(ConnectionLost):
    """A reply the driver cannot understand: the link is out of step and is closed (connect() again)."""


class ReplyTimeout(ConnectionLost):
    """No (complete) reply within the time-out: a late reply would desynchronise the link, so it is closed."""


# --- requests ----------------------------------------------------------------


def _mm(value: float) -> str:
    return _number(value, 4)


def _quat(value: float) -> str:
    return _number(value, 6)


def _deg(value: float) -> str:
    return _number(value, 4)


def _number(value: float, decimals: int) -> str:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"cannot send {value!r}: every number on the wire must be finite")
    text = f"{value:+.{decimals}f}"
    return "+" + text[1:] if text.startswith("-") and float(text) == 0.0 else text  # no "-0.0000"


def encode(code: int, fields: Sequence[str] = ()) -> bytes:
    """One request: two-digit code, fields, '#'. Refuses anything the RAPID server could not hold."""
    if not 0 <= code <= 99:
        raise ValueError(f"request code {code} out of range 0..99")
    text = " ".join([f"{code:02d}", *fields, "#"])
    if len(text) > MAX_REQUEST_CHARS:
        raise ValueError(
            f"request {text!r} is {len(text)} characters; the RAPID server reads at most {MAX_REQUEST_CHARS}"
            " (a value is too large for the wire format)"
        )
    return text.encode("ascii")


def _frame7(xyz_mm: Sequence[float], quaternion: Sequence[float]) -> list[str]:
    if len(xyz_mm) != 3 or len(quaternion) != 4:
        raise ValueError(f"a frame is x, y, z (mm) and a quaternion q1..q4; got {len(xyz_mm)} + {len(quaternion)} values")
    return [_mm(v) for v in xyz_mm] + [_quat(v) for v in quaternion]


def ping() -> bytes:
    return encode(PING)


def move_linear(xyz_mm: Sequence[float], quaternion: Sequence[float]) -> bytes:
    return encode(MOVE_LINEAR, _frame7(xyz_mm, quaternion))


def move_joints(joints: Sequence[float]) -> bytes:
    """Six robot axes: degrees for rotary axes, mm for linear ones (as RAPID's jointtarget)."""
    if len(joints) != 6:
        raise ValueError(f"MoveAbsJ takes 6 axis values, got {len(joints)}")
    return encode(MOVE_JOINTS, [_deg(v) for v in joints])


def get_cartesian() -> bytes:
    return encode(GET_CARTESIAN)


def get_joints() -> bytes:
    return encode(GET_JOINTS)


def set_tool(xyz_mm: Sequence[float], quaternion: Sequence[float]) -> bytes:
    return encode(SET_TOOL, _frame7(xyz_mm, quaternion))


def set_workobject(xyz_mm: Sequence[float], quaternion: Sequence[float]) -> bytes:
    return encode(SET_WORKOBJECT, _frame7(xyz_mm, quaternion))


def set_speed(tcp_mm_s: float, ori_deg_s: float, leax_mm_s: float, reax_deg_s: float) -> bytes:
    return encode(SET_SPEED, [_mm(tcp_mm_s), _deg(ori_deg_s), _mm(leax_mm_s), _deg(reax_deg_s)])


def set_zone(zone: str) -> bytes:
    """'fine' (stop exactly at each point) or a standard zone z0..z200."""
    if zone == "fine":
        values = (0.0, 0.0, 0.0)
    elif zone in ZONES:
        values = ZONES[zone]
    else:
        raise ValueError(f"zone {zone!r} unknown; allowed: {', '.join(ZONE_NAMES)}")
    return encode(SET_ZONE, ["1" if zone == "fine" else "0", *(_mm(v) for v in values)])


def buffer_add(xyz_mm: Sequence[float], quaternion: Sequence[float]) -> bytes:
    return encode(BUFFER_ADD, _frame7(xyz_mm, quaternion))


def buffer_clear() -> bytes:
    return encode(BUFFER_CLEAR)


def buffer_length() -> bytes:
    return encode(BUFFER_LENGTH)


def buffer_execute() -> bytes:
    return encode(BUFFER_EXECUTE)


def get_external_axes() -> bytes:
    return encode(GET_EXTERNAL_AXES)


def move_external_axes(values: Sequence[float | None]) -> bytes:
    """Six external axes a..f (deg, or mm for linear ones); None for an axis the robot does not have (9E9)."""
    if len(values) != 6:
        raise ValueError(f"an extjoint has 6 axes (eax_a..eax_f), got {len(values)} values")
    return encode(MOVE_EXTERNAL_AXES, [ABSENT_AXIS if v is None else _deg(v) for v in values])


def circle_point(xyz_mm: Sequence[float], quaternion: Sequence[float]) -> bytes:
    return encode(CIRCLE_POINT, _frame7(xyz_mm, quaternion))


def move_circular(xyz_mm: Sequence[float], quaternion: Sequence[float]) -> bytes:
    return encode(MOVE_CIRCULAR, _frame7(xyz_mm, quaternion))


def stop() -> bytes:
    return encode(STOP)


def robot_info() -> bytes:
    return encode(ROBOT_INFO)


def close() -> bytes:
    return encode(CLOSE)


# --- replies -----------------------------------------------------------------


@dataclass(frozen=True)
class Reply:
    code: int
    ok: int
    fields: tuple[str, ...]

    @property
    def status(self) -> str:
        return STATUS_NAMES.get(self.ok, f"unknown status {self.ok}")


def take_frame(buffer: bytes | bytearray, expected_code: int | None = None,
               terminated: bool = False) -> tuple[bytes | None, bytes]:
    """Split one reply off the front of `buffer`: (frame or None while incomplete, rest).

    The framing rule of the module docstring: a '#' ends a reply; without one (the stock
    open_abb server) the field count `REPLY_FIELDS` gives for `expected_code` does. With
    `terminated` (the link has sent '#'-ended replies) only a '#' ends one. A reply that
    only a quiet gap can end (`needs_quiet_gap`) stays None here.
    """
    buffer = bytes(buffer).lstrip(b"# \t\r\n")  # a '#' here is the tail of a reply framed by its fields
    end = buffer.find(b"#")
    if end >= 0:
        return buffer[: end + 1], buffer[end + 1 :]
    if not terminated and _complete_by_count(buffer, expected_code):
        return buffer, b""  # one request in flight: nothing can follow its reply
    if len(buffer) > MAX_REPLY_BYTES:
        what = "without the terminating '#'" if terminated else "without a complete reply"
        raise MalformedReply(
            f"{len(buffer)} bytes {what} ({buffer[:40]!r}...); expected a reply '<code> <ok> [data]'"
            f"{' ended by #' if terminated else ''} of at most {MAX_REPLY_BYTES} bytes"
        )
    return None, buffer


def _complete_by_count(buffer: bytes, expected_code: int | None) -> bool:
    tokens = buffer.split()
    if len(tokens) < 2:
        return False
    try:
        code, ok = int(tokens[0]), int(tokens[1])
    except ValueError:
        return True  # not a reply at all: complete, so that parse_reply says what is wrong
    if code != expected_code or ok != OK_DONE:
        return True  # a wrong code is an error now; other statuses carry no data
    n = REPLY_FIELDS.get(code)
    return n is not None and len(tokens) - 2 >= n


def needs_quiet_gap(buffer: bytes | bytearray, expected_code: int | None, terminated: bool = False) -> bool:
    """True if `buffer` starts a successful reply without '#' whose end only silence can tell
    (98 robot info, codes `REPLY_FIELDS` does not know)."""
    if terminated or b"#" in buffer:
        return False
    tokens = bytes(buffer).split()
    return len(tokens) >= 2 and tokens[1] == b"1" and REPLY_FIELDS.get(expected_code) is None


def parse_reply(frame: bytes, expected_code: int, n_fields: int | None = 0) -> Reply:
    """Check a complete reply frame (either dialect) against the request it answers.

    `n_fields` is the number of data fields a successful reply carries (None: any).
    Raises MalformedReply naming what was wrong and what was expected.
    """
    def bad(why: str) -> MalformedReply:
        return MalformedReply(
            f"malformed reply {frame!r} to request {expected_code:02d}: {why}; "
            f"expected '{expected_code} <ok 0-3> [data]' (the cellctl server ends it with '#'). "
            "The link is closed; connect() again"
        )

    try:
        text = frame.decode("ascii").strip()
    except UnicodeDecodeError:
        raise bad("not ASCII") from None
    if text.endswith("#"):
        text = text[:-1]
    tokens = text.split()
    if len(tokens) < 2:
        raise bad("fewer than two fields (code and status)")
    try:
        code, ok = int(tokens[0]), int(tokens[1])
    except ValueError:
        raise bad("code and status must be integers") from None
    if code != expected_code:
        raise bad(f"it answers code {code}")
    if ok not in STATUS_NAMES:
        raise bad(f"unknown status {ok}")
    fields = tuple(tokens[2:])
    if ok == OK_DONE and n_fields is not None and len(fields) != n_fields:
        raise bad(f"{len(fields)} data fields instead of {n_fields}")
    return Reply(code, ok, fields)


def numbers(reply: Reply, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(f) for f in reply.fields)
    except ValueError:
        raise MalformedReply(
            f"reply to {reply.code:02d} ({what}) has a non-numeric field in {' '.join(reply.fields)!r}; "
            "expected decimal numbers. The link is closed; connect() again"
        ) from None
    if not all(math.isfinite(v) for v in values):
        raise MalformedReply(f"reply to {reply.code:02d} ({what}) has a non-finite value: {values}")
    return values


def parse_cartesian(reply: Reply) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """x, y, z (mm) and the quaternion q1..q4 of the current tool in the current work object."""
    v = numbers(reply, "x y z q1 q2 q3 q4")
    return (v[0], v[1], v[2]), (v[3], v[4], v[5], v[6])


def parse_joints(reply: Reply) -> tuple[float, ...]:
    return numbers(reply, "six axis values")


def parse_external_axes(reply: Reply) -> tuple[float | None, ...]:
    """eax_a..eax_f as sent (deg, or mm for linear axes); None for an axis the robot does not have."""
    return tuple(None if v >= ABSENT_FROM else v for v in numbers(reply, "six external axis values"))


def parse_buffer_length(reply: Reply) -> int:
    (value,) = numbers(reply, "buffer length")
    if value != int(value) or value < 0:
        raise MalformedReply(f"buffer length {value} is not a count; expected a whole number >= 0")
    return int(value)


@dataclass(frozen=True)
class RobotInfo:
    serial: str
    software: str
    robot_type: str


def parse_robot_info(reply: Reply) -> RobotInfo:
    """'serial*SWversion*type'; the fields may contain spaces, so join them back first."""
    parts = " ".join(reply.fields).split("*")
    if len(parts) != 3:
        raise MalformedReply(
            f"robot info {' '.join(reply.fields)!r} has {len(parts)} '*'-separated parts; expected serial*software*type"
        )
    return RobotInfo(*parts)


# --- logger ------------------------------------------------------------------


@dataclass(frozen=True)
class LogSample:
    """One logger line: '# 0 date time t x y z q1 q2 q3 q4' (kind 0) or '# 1 date time t j1..j6' (kind 1)."""

    kind: int
    date: str
    time: str
    t_s: float
    values: tuple[float, ...]


def split_log_lines(buffer: bytes) -> tuple[list[bytes], bytes]:
    """Complete logger lines off the front of `buffer`, and the rest.

    The cellctl logger ends each line with a newline; the public LOGGER.mod sends none,
    but every line starts with '#', so a line also ends where the next begins (its last
    line then waits for the next one).
    """
    lines: list[bytes] = []
    start = 0
    while True:
        newline = buffer.find(b"\n", start)
        following = buffer.find(b"#", start + 1)
        ends = [e for e in (newline, following) if e >= 0]
        if not ends:
            return lines, buffer[start:]
        end = min(ends)
        line = buffer[start:end].strip()
        if line:
            lines.append(line)
        start = end + 1 if end == newline else end


def parse_log_line(line: bytes) -> LogSample:
    """One logger line, without its newline (see `split_log_lines`)."""
    tokens = line.decode("ascii", "replace").split()
    if len(tokens) < 5 or tokens[0] != "#" or tokens[1] not in ("0", "1"):
        raise MalformedReply(f"malformed logger line {line!r}; expected '# 0 date time t x y z q1..q4' or '# 1 date time t j1..j6'")
    kind = int(tokens[1])
    expected = 7 if kind == 0 else 6
    try:
        t_s = float(tokens[4])
        values = tuple(float(v) for v in tokens[5:])
    except ValueError:
        raise MalformedReply(f"malformed logger line {line!r}: non-numeric value") from None
    if len(values) != expected:
        raise MalformedReply(f"logger line {line!r} has {len(values)} values; expected {expected}")
    return LogSample(kind, tokens[2], tokens[3], t_s, values)
