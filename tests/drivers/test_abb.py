"""AbbArm against the ABB protocol simulator, and the exact bytes it exchanges with a controller.

- the Arm contract over real sockets (driver <-> drivers/sim/servers/abb.py in a thread), in both
  reply dialects of the simulator (open_abb: no terminator; cellctl: ended by '#');
- pinned wire exchanges against a scripted controller (what the driver sends, what it parses);
- independent peers: a client that talks as the public open_abb Python client does, against
  `cellctl sim abb`; a stand-in for the stock SERVER.mod / LOGGER.mod, driven by AbbArm;
- faults: dropped link, protective stop (before and part way along a move), slow and malformed
  replies, stop, refusals before sending.
"""

from __future__ import annotations

import math
import re
import select
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager

import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from drivers.arms.abb import AbbArm, MalformedReply, ReplyTimeout
from drivers.arms.abb.driver import CommandRejected
from drivers.arms.abb import protocol as wire
from drivers.interfaces import (
    ConnectionLost,
    DeviceState,
    JointState,
    MotionRejected,
    MotionStopped,
    NotConnected,
    Pose,
    ProtectiveStop,
)
from drivers.registry import DriverContext, backend_class
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.servers import connect_when_up
from ports import free_ports
from drivers.sim.servers.abb import DIALECTS, AbbFaults, AbbServer, serve
from geometry.orientation import quaternion_wxyz, tool_down
from tests.conftest import MICROCELL, ROOT, microcell_data
from tests.drivers.contract import ArmContract

DATA = microcell_data()
LIMITS = DATA["arm"]["limits"]


def _sim_arm(config: SimWorldConfig):
    return backend_class("arm", "sim").create("arm", {"limits": LIMITS}, DriverContext(sim_config=config))


def _abb(server: AbbServer, **options) -> AbbArm:
    settings = {"host": "127.0.0.1", "motion_port": server.motion_port, "logger_port": server.logger_port,
                "limits": LIMITS, "linear_axes": [1, 2, 3], "reply_timeout_s": 2.0, "move_timeout_s": 10.0}
    return AbbArm.create("abb", {**settings, **options}, None)


@pytest.fixture(autouse=True)
def no_leftover_threads():
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        left = [t for t in set(threading.enumerate()) - before if t.is_alive()]
        if not left:
            return
        time.sleep(0.02)
    pytest.fail(f"threads left running: {[t.name for t in left]}")


@pytest.fixture(params=DIALECTS)
def server(request, microcell_sim):
    """The simulator in each reply dialect: every test of the driver against it runs in both."""
    with AbbServer(_sim_arm(microcell_sim), reply_dialect=request.param) as srv:
        yield srv


def _reply(server: AbbServer, fields: str) -> bytes:
    """What `server` sends for a reply of these fields, in its dialect."""
    return (fields + (" #" if server.reply_dialect == "cellctl" else " ")).encode()


@pytest.fixture
def arm(server):
    device = _abb(server)
    device.connect()
    yield device
    device.close()


class TestAbbOverSimServer(ArmContract):
    @pytest.fixture
    def make_device(self, server):
        return lambda: _abb(server)


def test_registry_path_and_settings_errors():
    assert backend_class("arm", "abb") is AbbArm
    with pytest.raises(ValidationError, match="zone 'z7' unknown; allowed: fine, z0"):
        AbbArm.create("abb", {"host": "h", "limits": LIMITS, "zone": "z7"})
    with pytest.raises(ValidationError, match="tool: quaternion"):
        AbbArm.create("abb", {"host": "h", "limits": LIMITS, "tool": (0, 0, 0, 2, 0, 0, 0)})
    with pytest.raises(ValidationError, match="motion_port"):
        AbbArm.create("abb", {"host": "h", "limits": LIMITS, "motion_port": 70000})
    with pytest.raises(ValidationError, match="Extra inputs"):
        AbbArm.create("abb", {"host": "h", "limits": LIMITS, "speed": 3})


# --- the protocol, pure ----------------------------------------------------------------


def test_requests_are_pinned_bytes():
    q = quaternion_wxyz(tool_down(math.radians(90)))
    assert wire.ping() == b"00 #"
    assert wire.move_linear((50, 40, 10), q) == b"01 +50.0000 +40.0000 +10.0000 +0.000000 +0.707107 +0.707107 +0.000000 #"
    assert wire.move_joints((1, -2.5, 3, 45, 0, -0.00001)) == b"02 +1.0000 -2.5000 +3.0000 +45.0000 +0.0000 +0.0000 #"
    assert wire.get_cartesian() == b"03 #" and wire.get_joints() == b"04 #"
    assert wire.set_tool((0, 0, 120.5), (1, 0, 0, 0)) == b"06 +0.0000 +0.0000 +120.5000 +1.000000 +0.000000 +0.000000 +0.000000 #"
    assert wire.set_workobject((-300, 0, 0), (1, 0, 0, 0)).startswith(b"07 -300.0000 ")
    assert wire.set_speed(100, 50, 50, 50) == b"08 +100.0000 +50.0000 +50.0000 +50.0000 #"
    assert wire.set_zone("fine") == b"09 1 +0.0000 +0.0000 +0.0000 #"
    assert wire.set_zone("z5") == b"09 0 +5.0000 +8.0000 +0.8000 #"
    assert wire.buffer_add((1, 2, 3), (1, 0, 0, 0)).startswith(b"30 +1.0000 ")
    assert (wire.buffer_clear(), wire.buffer_length(), wire.buffer_execute()) == (b"31 #", b"32 #", b"33 #")
    assert (wire.stop(), wire.robot_info(), wire.close()) == (b"97 #", b"98 #", b"99 #")


def test_requests_that_a_rapid_string_cannot_hold_are_refused():
    longest = wire.move_linear((-2999.9999, -2999.9999, -2999.9999), (-0.5, -0.5, -0.5, -0.5))
    assert len(longest) <= wire.MAX_REQUEST_CHARS
    with pytest.raises(ValueError, match="at most 80"):
        wire.move_linear((-123456.0, -123456.0, -123456.0), (1, 0, 0, 0))
    with pytest.raises(ValueError, match="finite"):
        wire.move_linear((math.nan, 0, 0), (1, 0, 0, 0))
    with pytest.raises(ValueError, match="allowed: fine, z0"):
        wire.set_zone("z7")


def test_replies_ended_by_a_hash_are_framed_at_it():
    assert wire.take_frame(b"0 1 #8 1 #", 0) == (b"0 1 #", b"8 1 #")
    assert wire.take_frame(b"3 1 1.0", 3, terminated=True) == (None, b"3 1 1.0")
    assert wire.take_frame(b"0 1 ", 0, terminated=True) == (None, b"0 1 ")  # this link ends replies with '#'
    assert wire.take_frame(b"#8 1 #", 8) == (b"8 1 #", b"")  # the '#' of a reply framed by its fields
    reply = wire.parse_reply(b"3 1 50.0000 40.0000 10.0000 0.000000 1.000000 0.000000 0.000000 #", 3, 7)
    assert wire.parse_cartesian(reply) == ((50.0, 40.0, 10.0), (0.0, 1.0, 0.0, 0.0))
    assert wire.parse_robot_info(wire.parse_reply(b"98 1 120-505050*6.10.1 RW*IRB 120-3/0.6 #", 98, None)) == \
        wire.RobotInfo("120-505050", "6.10.1 RW", "IRB 120-3/0.6")
    assert wire.parse_reply(b"1 2 #", 1).status == "protective stop"
    with pytest.raises(MalformedReply, match="without the terminating '#'"):
        wire.take_frame(b"3 1 " + b"1.0 " * 100, 3, terminated=True)


def test_replies_without_terminator_are_framed_by_their_field_count():
    cartesian = b"3 1 50.00 40.00 10.00 0.000 0.707 0.707 0.000"
    assert wire.take_frame(cartesian, 3) == (cartesian, b"")
    assert wire.take_frame(cartesian[:20], 3) == (None, cartesian[:20])  # 2 of 7 fields
    assert wire.take_frame(b"0 1 ", 0) == (b"0 1 ", b"") and wire.take_frame(b"0 1", 0) == (b"0 1", b"")
    assert wire.take_frame(b"0", 0) == (None, b"0")
    assert wire.take_frame(b"32 1 3", 32) == (b"32 1 3", b"")
    assert wire.take_frame(b"3 0 ", 3) == (b"3 0 ", b"")  # refused: no data follows
    assert wire.take_frame(b"4 1 1 2 3 4 5 6", 4)[0] is not None
    assert wire.parse_reply(b"0 1 ", 0) == wire.Reply(0, 1, ())
    assert wire.parse_joints(wire.parse_reply(b"4 1 1 2 3 4 5 6", 4, 6)) == (1, 2, 3, 4, 5, 6)
    for garbage, code, why in ((b"?? garbled reply", 3, "code and status must be integers"),
                               (b"5 1 ", 4, "it answers code 5")):
        frame, _ = wire.take_frame(garbage, code)  # complete at once, so the error comes now, not at a time-out
        with pytest.raises(MalformedReply, match=why):
            wire.parse_reply(frame, code, wire.REPLY_FIELDS[code])
    with pytest.raises(MalformedReply, match="without a complete reply"):
        wire.take_frame(b"3 1 " + b"1.0 " * 2 + b"x" * 300, 3)


def test_robot_info_without_terminator_waits_for_a_quiet_gap():
    info = b"98 1 120-505050*6.10.1*IRB 120-3/0.6"
    assert wire.take_frame(info, 98) == (None, info)  # the type may hold spaces: no count can end it
    assert wire.needs_quiet_gap(info, 98)
    assert not wire.needs_quiet_gap(info + b" #", 98) and not wire.needs_quiet_gap(info, 98, terminated=True)
    assert not wire.needs_quiet_gap(b"98", 98) and not wire.needs_quiet_gap(b"3 1 50.0", 3)
    assert wire.take_frame(b"98 0 ", 98) == (b"98 0 ", b"")


def test_logger_lines_end_at_a_newline_or_where_the_next_begins():
    line0 = b"# 0 2026-11-22 10:00:00 1.00 50.0000 40.0000 10.0000 0.000000 1.000000 0.000000 0.000000"
    line1 = b"# 1 2026-11-22 10:00:00 1.01 50.0000 40.0000 10.0000 90.0000 0.0000 0.0000"
    assert wire.split_log_lines(line0 + b"\n" + line1 + b"\n") == ([line0, line1], b"")
    assert wire.split_log_lines(line0 + line1) == ([line0], line1)  # stock LOGGER.mod: no newline
    assert wire.split_log_lines(line0[:30]) == ([], line0[:30])
    assert [wire.parse_log_line(x).kind for x in wire.split_log_lines(line0 + line1 + b"# 0")[0]] == [0, 1]


@pytest.mark.parametrize("frame, code, n, why", [
    (b"3 1 50.0 #", 3, 7, "1 data fields instead of 7"),
    (b"5 1 #", 4, 6, "it answers code 5"),
    (b"?? garbled #", 3, 7, "code and status must be integers"),
    (b"3 7 #", 3, 7, "unknown status 7"),
    (b"3 #", 3, 7, "fewer than two fields"),
    (b"3 1 \xff #", 3, None, "not ASCII"),
])
def test_malformed_replies_name_what_was_wrong(frame, code, n, why):
    with pytest.raises(MalformedReply, match=why) as error:
        wire.parse_reply(frame, code, n)
    assert f"expected '{code} <ok 0-3>" in str(error.value)


def test_non_numeric_data_is_malformed():
    reply = wire.parse_reply(b"4 1 1 2 x 4 5 6 #", 4, 6)
    with pytest.raises(MalformedReply, match="non-numeric"):
        wire.parse_joints(reply)


def test_logger_lines():
    sample = wire.parse_log_line(b"# 0 2026-11-22 10:00:00 12.34 50.0000 40.0000 10.0000 0.000000 1.000000 0.000000 0.000000")
    assert (sample.kind, sample.t_s, sample.values[:3]) == (0, 12.34, (50.0, 40.0, 10.0))
    with pytest.raises(MalformedReply, match="expected 6"):
        wire.parse_log_line(b"# 1 d t 1.0 1 2 3")


# --- pinned exchanges with a scripted controller -------------------------------------------

CONNECT_SCRIPT = [
    (b"00 #", b"0 1 #"),
    (b"06 +0.0000 +0.0000 +0.0000 +1.000000 +0.000000 +0.000000 +0.000000 #", b"6 1 #"),
    (b"07 +0.0000 +0.0000 +0.0000 +1.000000 +0.000000 +0.000000 +0.000000 #", b"7 1 #"),
    (b"08 +100.0000 +50.0000 +50.0000 +50.0000 #", b"8 1 #"),
    (b"09 1 +0.0000 +0.0000 +0.0000 #", b"9 1 #"),
]


class ScriptedController:
    """Accepts one client; for each expected request replies with the scripted bytes (chunks allowed).

    Records everything received; a request that differs from the script is recorded and left unanswered."""

    def __init__(self, script):
        self.script = list(script)
        self.received: list[bytes] = []
        self.mismatch: str | None = None
        self._listener = socket.socket()
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(1)
        self._listener.settimeout(5.0)
        self.port = self._listener.getsockname()[1]
        self._thread = threading.Thread(target=self._run, name="abb-scripted")
        self._thread.start()

    def _run(self):
        try:
            client, _ = self._listener.accept()
        except OSError:
            return
        client.settimeout(5.0)
        buffer = b""
        with client:
            while True:
                while b"#" not in buffer:
                    try:
                        chunk = client.recv(1024)
                    except OSError:
                        return
                    if not chunk:
                        return
                    buffer += chunk
                message, _, buffer = buffer.partition(b"#")
                message += b"#"
                self.received.append(message)
                if not self.script:
                    continue
                expected, reply = self.script.pop(0)
                if message != expected:
                    self.mismatch = f"expected {expected!r}, got {message!r}"
                    continue
                for chunk in reply if isinstance(reply, list) else [reply]:
                    client.sendall(chunk)
                    time.sleep(0.005)  # let a split reply arrive in pieces

    def arm(self, **options) -> AbbArm:
        settings = {"host": "127.0.0.1", "motion_port": self.port, "logger_port": None, "limits": LIMITS,
                    "reply_timeout_s": 1.0, "move_timeout_s": 1.0, **options}
        return AbbArm.create("abb", settings)

    def finish(self):
        self._thread.join(timeout=5.0)
        self._listener.close()
        assert self.mismatch is None, self.mismatch


def test_pinned_exchange_of_every_command():
    controller = ScriptedController(CONNECT_SCRIPT + [
        (b"01 +50.0000 +40.0000 +10.0000 +0.000000 +0.707107 +0.707107 +0.000000 #", b"1 1 #"),
        (b"03 #", [b"3 1 50.0000 40.00", b"00 10.0000 0.000000 0.707107 0.707107 0.000000 #"]),
        (b"04 #", b"4 1 10.0000 -20.0000 30.0000 0.0000 90.0000 0.0000 #"),
        (b"08 +20.0000 +50.0000 +50.0000 +50.0000 #", b"8 1 #"),
        (b"02 +10.0000 -20.0000 +30.0000 +0.0000 +90.0000 +0.0000 #", b"2 1 #"),
        (b"08 +100.0000 +50.0000 +50.0000 +50.0000 #", b"8 1 #"),
        (b"01 +50.0000 +40.0000 +10.0000 +0.000000 +0.707107 +0.707107 +0.000000 #", b"1 1 #"),
        (b"06 +0.0000 +0.0000 +120.5000 +1.000000 +0.000000 +0.000000 +0.000000 #", b"6 1 #"),
        (b"07 +300.0000 +0.0000 +0.0000 +1.000000 +0.000000 +0.000000 +0.000000 #", b"7 1 #"),
        (b"09 0 +5.0000 +8.0000 +0.8000 #", b"9 1 #"),
        (b"31 #", b"31 1 #"),
        (b"30 +60.0000 +40.0000 +10.0000 +0.000000 +1.000000 +0.000000 +0.000000 #", b"30 1 #"),
        (b"32 #", b"32 1 1 #"),
        (b"33 #", b"33 1 #"),
        (b"98 #", b"98 1 120-505050*6.10.1*IRB 120-3/0.6 #"),
        (b"00 #", b"0 1 #"),
        (b"99 #", b"99 1 #"),
    ])
    arm = controller.arm()
    arm.connect()
    arm.move_linear(Pose(0.050, 0.040, 0.010, math.radians(90)))
    pose = arm.pose()
    assert (pose.x, pose.y, pose.z) == pytest.approx((0.05, 0.04, 0.01), abs=1e-12)
    assert pose.alpha == pytest.approx(math.pi / 2, abs=1e-5)
    assert pose.orientation == (0.0, 0.707107, 0.707107, 0.0)
    joints = arm.joints()
    assert joints.positions == pytest.approx([math.radians(v) for v in (10, -20, 30, 0, 90, 0)])
    arm.move_joints(joints, speed=0.020)  # a speed of its own, then back to the default
    arm.move_linear(Pose(0.050, 0.040, 0.010, math.radians(90)))  # default speed sent again first
    arm.set_tool((0, 0, 120.5, 1, 0, 0, 0))
    arm.set_workobject((300, 0, 0, 1, 0, 0, 0))
    arm.set_zone("z5")
    arm.buffer_clear()
    arm.buffer_add(Pose(0.060, 0.040, 0.010))
    assert arm.buffer_length() == 1
    arm.buffer_execute()
    assert arm.robot_info().robot_type == "IRB 120-3/0.6"
    arm.ping()
    arm.close()
    controller.finish()


def test_out_of_box_target_is_refused_before_any_byte_is_sent():
    controller = ScriptedController(CONNECT_SCRIPT + [(b"99 #", b"99 1 #")])
    arm = controller.arm()
    arm.connect()
    for target in (Pose(0.5, 0.04, 0.01), Pose(0.05, 0.04, math.nan)):
        with pytest.raises(MotionRejected, match="nothing moved"):
            arm.move_linear(target)
        with pytest.raises(MotionRejected, match="nothing moved"):
            arm.buffer_add(target)
    with pytest.raises(MotionRejected, match="speed"):
        arm.move_linear(Pose(0.05, 0.04, 0.01), speed=1.0)  # above max_tcp_speed_mm_s
    with pytest.raises(MotionRejected, match="6 axis values"):
        arm.move_joints(JointState((0.0, 0.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match="tcp_mm_s=9000"):
        arm.set_speed(9000)
    arm.close()
    controller.finish()
    assert controller.received[len(CONNECT_SCRIPT):] == [b"99 #"]


@pytest.mark.parametrize("reply, match", [
    (b"3 1 50.0000 40.0000 #", "2 data fields instead of 7"),
    (b"4 1 1 2 3 4 5 6 #", "it answers code 4"),
    (b"3 1 50 40 10 0.5 0.5 0.5 0.9 #", "orientation unusable"),
    (b"this is not an ABB controller " * 10, "without the terminating '#'"),
])
def test_malformed_reply_faults_the_link(reply, match):
    controller = ScriptedController(CONNECT_SCRIPT + [(b"03 #", reply)])
    arm = controller.arm()
    arm.connect()
    with pytest.raises(MalformedReply, match=match):
        arm.pose()
    assert arm.state is DeviceState.FAULTED
    with pytest.raises(ConnectionLost, match="connect"):
        arm.pose()
    arm.close()
    controller.finish()


# --- against the simulator -----------------------------------------------------------------


def test_dropped_link_faults_until_connect(server, arm):
    server.faults.drop_after_messages = server.messages_on_connection + 1
    arm.pose()  # the last answered message
    with pytest.raises(ConnectionLost, match="connect"):
        arm.pose()
    assert arm.state is DeviceState.FAULTED
    server.faults.drop_after_messages = None
    for command in (arm.pose, lambda: arm.move_linear(Pose(0.05, 0.04, 0.01))):
        with pytest.raises(ConnectionLost, match="connect"):  # never reconnects by itself
            command()
    arm.connect()
    assert arm.state is DeviceState.READY
    arm.move_linear(Pose(0.06, 0.04, 0.01))
    assert arm.pose().x == pytest.approx(0.06, abs=1e-9)


def test_world_fault_drop_after_moves(microcell_sim):
    config = microcell_sim.model_copy(update={"faults": microcell_sim.faults.model_copy(update={"arm_drop_after_moves": 1})})
    with AbbServer(_sim_arm(config)) as srv:
        arm = _abb(srv)
        arm.connect()
        arm.move_linear(Pose(0.05, 0.04, 0.01))
        with pytest.raises(ConnectionLost):
            arm.move_linear(Pose(0.06, 0.04, 0.01))
        assert arm.state is DeviceState.FAULTED
        arm.close()


def test_protective_stop(server, arm):
    home = arm.pose()
    server.faults.protective_stop = True
    with pytest.raises(ProtectiveStop, match="clear it on the controller"):
        arm.move_linear(Pose(0.06, 0.04, 0.01))
    with pytest.raises(ProtectiveStop):
        arm.move_joints(JointState((0.06, 0.04, 0.01, 0.0, 0.0, 0.0)))
    assert arm.state is DeviceState.READY  # the link is fine; the robot is not
    assert arm.pose().xyz == pytest.approx(home.xyz, abs=1e-9)  # did not move
    server.clear_protective_stop()
    arm.move_linear(Pose(0.06, 0.04, 0.01))
    assert arm.pose().x == pytest.approx(0.06, abs=1e-9)


def test_world_protective_stop_maps_to_protective_stop(microcell_sim):
    faults = microcell_sim.faults.model_copy(update={"protective_stop_after_moves": 1})
    with AbbServer(_sim_arm(microcell_sim.model_copy(update={"faults": faults}))) as srv:
        arm = _abb(srv)
        arm.connect()
        arm.move_linear(Pose(0.05, 0.04, 0.01))
        with pytest.raises(ProtectiveStop):
            arm.move_linear(Pose(0.06, 0.04, 0.01))
        arm.close()


def test_slow_reply_is_an_error_not_a_hang(server):
    arm = _abb(server, reply_timeout_s=0.2)
    arm.connect()
    server.faults.reply_delay_s = 2.0
    start = time.monotonic()
    with pytest.raises(ReplyTimeout, match="no complete reply to '03 #' within 0.2 s"):
        arm.pose()
    assert time.monotonic() - start < 1.0
    assert arm.state is DeviceState.FAULTED
    server.faults.reply_delay_s = 0.0
    arm.close()


def test_malformed_replies_from_the_simulator(server, arm):
    server.faults.malformed_replies = True
    with pytest.raises(MalformedReply, match="code and status must be integers"):
        arm.pose()
    assert arm.state is DeviceState.FAULTED
    server.faults.malformed_replies = False
    arm.connect()
    arm.pose()


def test_stop_ends_a_move_in_progress(microcell_sim):
    config = microcell_sim.model_copy(update={"motion": microcell_sim.motion.model_copy(update={"realtime_factor": 1.0})})
    with AbbServer(_sim_arm(config)) as srv:
        arm = _abb(srv)
        arm.connect()
        outcome = {}

        def move():
            try:
                arm.move_linear(Pose(0.150, 0.100, 0.020))  # about 1.8 s of real time
            except Exception as exc:  # noqa: BLE001 - handed to the test thread
                outcome["error"] = exc

        mover = threading.Thread(target=move)
        mover.start()
        assert srv.moving.wait(timeout=3.0)
        asked = time.monotonic()
        arm.stop()
        mover.join(timeout=5.0)
        assert isinstance(outcome.get("error"), MotionStopped)
        assert time.monotonic() - asked < 1.0  # stop, then settle (0.25 s); the rest of the move took ~1.7 s more
        stopped = arm.pose()
        assert stopped.x < 0.150 - 0.01  # short of the target
        arm.stop()  # idle: harmless
        arm.close()


def test_stop_without_a_logger_link_is_safe(server):
    arm = _abb(server, logger_port=None)
    arm.stop()
    arm.connect()
    arm.stop()
    arm.pose()
    arm.close()


def test_tool_down_only_and_four_axis_joints(arm):
    tilted = tool_down(0.0) * Rotation.from_euler("x", 5, degrees=True)
    with pytest.raises(MotionRejected, match="refused"):
        arm.move_linear(Pose(0.05, 0.04, 0.01, orientation=quaternion_wxyz(tilted)))
    arm.move_joints(JointState((0.060, 0.050, 0.015, math.radians(45), 0.0, 0.0)))
    pose = arm.pose()
    assert (pose.x, pose.y, pose.z) == pytest.approx((0.060, 0.050, 0.015), abs=1e-9)
    assert pose.alpha == pytest.approx(math.radians(45), abs=1e-5)
    assert arm.joints().positions == pytest.approx((0.060, 0.050, 0.015, math.radians(45), 0.0, 0.0), abs=1e-9)
    with pytest.raises(MotionRejected, match="refused"):
        arm.move_joints(JointState((0.060, 0.050, 0.015, 0.0, math.radians(10), 0.0)))


def test_tool_and_work_object_frames(arm):
    arm.move_linear(Pose(0.050, 0.040, 0.010))
    arm.set_workobject((10, 0, 0, 1, 0, 0, 0))
    assert arm.pose().x == pytest.approx(0.040, abs=1e-9)
    arm.set_tool((0, 0, 5, 1, 0, 0, 0))  # 5 mm along the tool axis, which points down
    assert arm.pose().z == pytest.approx(0.005, abs=1e-9)
    arm.move_linear(Pose(0.030, 0.040, 0.000, math.radians(20)))  # tool tip at wobj (30, 40, 0)
    arm.set_tool((0, 0, 0, 1, 0, 0, 0))
    arm.set_workobject((0, 0, 0, 1, 0, 0, 0))
    flange = arm.pose()
    assert (flange.x, flange.y, flange.z) == pytest.approx((0.040, 0.040, 0.005), abs=1e-9)
    assert flange.alpha == pytest.approx(math.radians(20), abs=1e-5)


def test_buffered_path_speed_zone_info(arm):
    arm.buffer_clear()
    for x in (0.02, 0.03, 0.04):
        arm.buffer_add(Pose(x, 0.05, 0.01))
    assert arm.buffer_length() == 3
    arm.set_zone("z1")
    arm.set_speed(50)
    arm.buffer_execute()
    assert arm.pose().x == pytest.approx(0.04, abs=1e-9)
    arm.set_zone("fine")
    arm.buffer_clear()
    assert arm.buffer_length() == 0
    arm.move_linear(Pose(0.05, 0.05, 0.01), speed=0.2)
    assert arm.robot_info().serial == "SIM-0001"
    arm.ping()


def test_logger_streams_pose_and_joints(arm):
    arm.move_linear(Pose(0.070, 0.030, 0.012, math.radians(-30)))
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        cartesian, joints = arm.logged()
        if cartesian and joints and cartesian.values[0] == 70.0 and joints.values[0] == 70.0:
            break
        time.sleep(0.01)
    assert cartesian.values[:3] == (70.0, 30.0, 12.0)
    assert joints.values == pytest.approx((70.0, 30.0, 12.0, -30.0, 0.0, 0.0))


def test_server_survives_vanishing_and_garbage_clients(server):
    for junk in (b"", b"01 +1.0", b"hello there#", b"x" * 200):
        with socket.create_connection(("127.0.0.1", server.motion_port), timeout=2.0) as raw:
            raw.sendall(junk)
            if junk.endswith(b"#"):
                assert raw.recv(64) == _reply(server, "-1 0")
    with socket.create_connection(("127.0.0.1", server.motion_port), timeout=2.0) as raw:
        for request, reply in ((b"03 abc #", "3 0"), (b"03 1 #", "3 0"), (b"42 #", "42 0"),
                               (b"01 +1 +2 +3 +1 +0 +0 +0 #", "1 0"), (b"97 #", "97 1")):
            raw.sendall(request)
            assert raw.recv(64) == _reply(server, reply)
    arm = _abb(server)
    arm.connect()
    arm.pose()
    arm.close()
    assert server.clients_served >= 6


def test_before_connect_and_after_close(server):
    arm = _abb(server)
    with pytest.raises(NotConnected, match="connect"):
        arm.move_linear(Pose(0.05, 0.04, 0.01))
    with pytest.raises(NotConnected, match="connect"):
        arm.buffer_length()
    arm.connect()
    arm.close()
    with pytest.raises(NotConnected, match="connect"):
        arm.robot_info()


def test_connect_to_nothing_says_where():
    port, = free_ports()
    arm = AbbArm.create("abb", {"host": "127.0.0.1", "motion_port": port, "limits": LIMITS, "connect_timeout_s": 0.5})
    with pytest.raises(ConnectionLost, match=f"127.0.0.1:{port}"):
        arm.connect()
    arm.close()


def test_serve_blocks_until_stopped(microcell_sim):
    ports = free_ports(2)
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(microcell_sim, "127.0.0.1", ports[0], ports[1]),
                              kwargs={"stop": stop, "options": {"reply_delay_s": 0.0, "log_period_s": 0.02}})
    thread.start()
    try:
        arm = AbbArm.create("abb", {"host": "127.0.0.1", "motion_port": ports[0], "logger_port": ports[1], "limits": LIMITS})
        connect_when_up(arm, timeout_s=3.0)
        arm.move_linear(Pose(0.05, 0.04, 0.01))
        arm.close()
    finally:
        stop.set()
        thread.join(timeout=5.0)
    assert not thread.is_alive()
    with pytest.raises(ValueError, match="unknown ABB simulator option"):
        AbbFaults.from_options({"explode": True})


def test_pinned_exchange_with_a_controller_that_sends_no_terminator():
    """The stock reply format, replies split across segments where a count can still frame them."""
    controller = ScriptedController([
        (b"00 #", b"0 1 "),
        (b"06 +0.0000 +0.0000 +0.0000 +1.000000 +0.000000 +0.000000 +0.000000 #", b"6 1 "),
        (b"07 +0.0000 +0.0000 +0.0000 +1.000000 +0.000000 +0.000000 +0.000000 #", [b"7", b" 1 "]),
        (b"08 +100.0000 +50.0000 +50.0000 +50.0000 #", b"8 1 "),
        (b"09 1 +0.0000 +0.0000 +0.0000 #", b"9 1 "),
        (b"03 #", [b"3 1 50.00 40.00", b" 10.00 0.000 0.707 0.707 0.000"]),
        (b"04 #", b"4 1 10.00 -20.00 30.00 0.00 90.00 0.00"),
        (b"32 #", b"32 1 0"),
        (b"98 #", b"98 1 120-505050*6.10.1*IRB 120-3/0.6"),
        (b"03 #", b"3 0 "),
        (b"99 #", b"99 1 "),
    ])
    arm = controller.arm()
    arm.connect()
    pose = arm.pose()
    assert (pose.x, pose.y, pose.z) == pytest.approx((0.05, 0.04, 0.01), abs=1e-12)
    assert arm.joints().positions == pytest.approx([math.radians(v) for v in (10, -20, 30, 0, 90, 0)])
    assert arm.buffer_length() == 0
    assert arm.robot_info() == wire.RobotInfo("120-505050", "6.10.1", "IRB 120-3/0.6")  # ended by the quiet gap
    with pytest.raises(CommandRejected, match="bad message"):
        arm.pose()
    assert arm.state is DeviceState.READY  # a refusal framed at once, not a time-out
    arm.close()
    controller.finish()


def test_a_cellctl_reply_split_before_its_hash_keeps_the_link_in_step():
    controller = ScriptedController([(b"00 #", [b"0 1 ", b"#"]), *CONNECT_SCRIPT[1:],
                                     (b"03 #", [b"3 0 ", b"#"]), (b"00 #", b"0 1 #"), (b"99 #", b"99 1 #")])
    arm = controller.arm()
    arm.connect()  # "0 1 " is framed by its count; the '#' after it is dropped before the next reply
    with pytest.raises(CommandRejected):
        arm.pose()  # this link has sent '#': the reply is read up to its '#', not framed early
    arm.ping()
    arm.close()
    controller.finish()


# --- independent peers -------------------------------------------------------------------


class PublicStyleClient:
    """Talks as the public open_abb Python client does (written here from its behaviour): each request
    one send() of its text, each reply one recv(4096), then split() and float() on every token."""

    def __init__(self, host: str, port: int):
        self.sock = socket.create_connection((host, port), timeout=5.0)
        self.raw: list[bytes] = []

    def send(self, message: str) -> bytes:
        self.sock.send(message.encode("ascii"))
        data = self.sock.recv(4096)
        self.raw.append(data)
        return data

    def numbers(self, message: str) -> list[float]:
        return [float(token) for token in self.send(message).split()]

    @staticmethod
    def frame(xyz_mm, quaternion) -> str:
        """The client's number format: mm with one decimal, quaternions with five, signed, zero-padded."""
        return " ".join([format(v, "+08.1f") for v in xyz_mm] + [format(v, "+08.5f") for v in quaternion])

    def close(self) -> None:
        self.sock.send(b"99 #")  # the public client does not wait for this reply
        self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


def _readline(stream, timeout_s: float) -> str:
    """One line of a child's output, or '' after `timeout_s` (never blocks the test for good)."""
    ready, _, _ = select.select([stream], [], [], timeout_s)
    return stream.readline() if ready else ""


def _same_rotation(q, expected, tol: float) -> bool:
    return max(abs(a - b) for a, b in zip(q, expected)) < tol or max(abs(a + b) for a, b in zip(q, expected)) < tol


@contextmanager
def sim_abb_by_hand():
    """`cellctl sim abb` started as by hand, on a free port: yields that port; it must stop cleanly after."""
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "sim", "abb", "--config", str(MICROCELL),
                             "--port", "0"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        banner = _readline(proc.stdout, 30.0)
        found = re.search(r"serving on 127\.0\.0\.1:(\d+) \(logger \d+\), open_abb replies", banner)
        assert found, f"no banner from cellctl sim abb: {banner!r}"
        yield int(found[1])
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0


def test_a_public_style_open_abb_client_drives_cellctl_sim_abb():
    """`cellctl sim abb` as started by hand answers in the stock format: every token of every reply
    float()s, 98 splits on '*', nothing ends in '#'."""
    with sim_abb_by_hand() as port:
        client = PublicStyleClient("127.0.0.1", port)
        identity = client.frame((0, 0, 0), (1, 0, 0, 0))
        assert client.numbers("00 #") == [0, 1]
        assert client.numbers(f"06 {identity} #") == [6, 1]
        assert client.numbers(f"07 {identity} #") == [7, 1]
        assert client.numbers("08 +0100.0 +0050.0 +0050.0 +0050.0 #") == [8, 1]
        assert client.numbers("09 0 +01.0000 +01.0000 +00.1000 #") == [9, 1]  # z1
        q90 = quaternion_wxyz(tool_down(math.radians(90)))
        assert client.numbers(f"01 {client.frame((50, 40, 10), q90)} #") == [1, 1]
        r = client.numbers("03 #")
        assert r[:2] == [3, 1] and len(r) == 9
        assert r[2:5] == pytest.approx([50, 40, 10], abs=0.051)
        assert _same_rotation(r[5:9], q90, 1e-4)
        j = client.numbers("04 #")
        assert j[:2] == [4, 1] and j[2:8] == pytest.approx([50, 40, 10, 90, 0, 0], abs=0.051)
        assert client.numbers("31 #") == [31, 1]
        q0 = quaternion_wxyz(tool_down(0.0))
        for x in (45, 55):
            assert client.numbers(f"30 {client.frame((x, 35, 10), q0)} #") == [30, 1]
        assert int(float(client.send("32 #").split()[2])) == 2
        assert client.numbers("33 #") == [33, 1]
        assert client.numbers("03 #")[2:5] == pytest.approx([55, 35, 10], abs=0.051)
        info = client.send("98 #")[5:].split(b"*")
        assert info == [b"SIM-0001", b"6.99.0 cellctl-sim", b"cellctl 4-axis micro cell"]
        client.close()
        assert not any(b"#" in reply for reply in client.raw), client.raw
        again = PublicStyleClient("127.0.0.1", port)  # the server takes the next client
        assert again.numbers("00 #") == [0, 1]
        again.close()


class StockOpenAbbServer:
    """A stand-in for the public SERVER.mod and LOGGER.mod as they look on the wire (not their code):
    replies "<code> <ok> <data>" with no terminator, one send each, numbers with few decimals (2 for mm
    and degrees, 3 for quaternions here); logger lines "# 0 ..." with no newline. Knows no status 2 or 3."""

    def __init__(self):
        self.pose = [300.0, 0.0, 400.0, 0.0, 0.0, 1.0, 0.0]
        self.codes: list[int] = []
        self._stop = threading.Event()
        self._listeners = []
        for _ in range(2):
            sock = socket.socket()
            sock.bind(("127.0.0.1", 0))
            sock.listen(1)
            sock.settimeout(5.0)
            self._listeners.append(sock)
        self.motion_port, self.logger_port = (s.getsockname()[1] for s in self._listeners)
        self._threads = [threading.Thread(target=self._motion, name="stock-abb-motion"),
                         threading.Thread(target=self._logger, name="stock-abb-logger")]
        for thread in self._threads:
            thread.start()

    def _cartesian(self) -> str:
        return " ".join([f"{v:.2f}" for v in self.pose[:3]] + [f"{v:.3f}" for v in self.pose[3:]])

    def _motion(self):
        try:
            client, _ = self._listeners[0].accept()
        except OSError:
            return
        with client:
            buffer = b""
            while True:
                while b"#" not in buffer:
                    chunk = client.recv(1024)
                    if not chunk:
                        return
                    buffer += chunk
                message, _, buffer = buffer.partition(b"#")
                tokens = message.split()
                code, params = int(tokens[0]), [float(t) for t in tokens[1:]]
                self.codes.append(code)
                data = ""
                if code == 1 and len(params) == 7:
                    self.pose = params
                elif code == 3:
                    data = self._cartesian()
                elif code == 4:
                    data = "10.00 -20.00 30.00 0.00 90.00 0.00"
                elif code == 98:
                    data = "120-505050*6.10.1*IRB 120-3/0.6"
                client.sendall(f"{code} 1 {data}".encode())
                if code == 99:
                    return

    def _logger(self):
        try:
            client, _ = self._listeners[1].accept()
        except OSError:
            return
        with client:
            t = 0.0
            while not self._stop.wait(0.01):  # the logger's period
                t += 0.01
                try:
                    client.sendall(f"# 0 2026-11-22 10:00:00 {t:.2f} {self._cartesian()}".encode())
                except OSError:
                    return

    def close(self):
        self._stop.set()
        for sock in self._listeners:
            sock.close()
        for thread in self._threads:
            thread.join(timeout=5.0)


def test_abb_arm_drives_a_stock_open_abb_server():
    stock = StockOpenAbbServer()
    try:
        arm = AbbArm.create("abb", {"host": "127.0.0.1", "motion_port": stock.motion_port,
                                    "logger_port": stock.logger_port, "limits": LIMITS,
                                    "reply_timeout_s": 2.0, "move_timeout_s": 2.0})
        arm.connect()
        target = Pose(0.050, 0.040, 0.010, math.radians(90))
        arm.move_linear(target)
        pose = arm.pose()
        assert math.dist(pose.xyz, target.xyz) < 1e-5  # 2 decimals of a mm
        assert pose.alpha == pytest.approx(target.alpha, abs=2e-3)  # 3 decimals of a quaternion
        assert arm.joints().positions[4] == pytest.approx(math.radians(90))
        assert arm.robot_info().robot_type == "IRB 120-3/0.6"
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:  # the logger's lines have no newline: each ends at the next '#'
            cartesian, _ = arm.logged()
            if cartesian is not None and cartesian.values[:3] == (50.0, 40.0, 10.0):
                break
            time.sleep(0.01)
        assert cartesian is not None and cartesian.values[:3] == (50.0, 40.0, 10.0)
        arm.close()
    finally:
        stock.close()
    assert stock.codes == [0, 6, 7, 8, 9, 1, 3, 4, 98, 99]


# --- a protective stop part way along a move ------------------------------------------------


def test_protective_stop_mid_move_leaves_the_arm_short_of_its_target(server, arm):
    start, target = Pose(0.040, 0.030, 0.010), Pose(0.090, 0.030, 0.010)
    arm.move_linear(start)
    server.faults.protective_stop_mid_move = 0.4
    with pytest.raises(ProtectiveStop, match="protective stop"):
        arm.move_linear(target)
    stopped = arm.pose()
    assert stopped.x == pytest.approx(0.060, abs=1e-6) and stopped.x < target.x  # 40 % of the way, no further
    assert arm.state is DeviceState.READY
    with pytest.raises(ProtectiveStop):  # it stays stopped, as a controller does, until cleared
        arm.move_joints(JointState((0.050, 0.050, 0.010, 0.0, 0.0, 0.0)))
    assert arm.pose().xyz == pytest.approx(stopped.xyz, abs=1e-9)
    server.clear_protective_stop()
    arm.move_linear(target)
    assert arm.pose().x == pytest.approx(0.090, abs=1e-9)
    server.faults.protective_stop_mid_move = 0.5  # a joint move too
    with pytest.raises(ProtectiveStop):
        arm.move_joints(JointState((0.070, 0.030, 0.010, math.radians(40), 0.0, 0.0)))
    assert arm.pose().x == pytest.approx(0.080, abs=1e-6)
    assert arm.pose().alpha == pytest.approx(math.radians(20), abs=1e-5)
    server.clear_protective_stop()


def test_protective_stop_mid_move_option_is_checked():
    assert AbbFaults.from_options({"protective_stop_mid_move": 0.25}).protective_stop_mid_move == 0.25
    with pytest.raises(ValueError, match="0 < f < 1"):
        AbbFaults.from_options({"protective_stop_mid_move": 1.5})


def test_reply_dialect_choices(microcell_sim, capsys):
    from cellctl.cli import main

    assert main(["sim", "abb", "--config", str(MICROCELL), "--dialect", "cellctl",
                 "--option", "reply_dialect=open_abb"]) == 2
    assert "--dialect cellctl and --option reply_dialect=open_abb disagree" in capsys.readouterr().err
    with pytest.raises(ValueError, match="reply_dialect 'stock' unknown; allowed: open_abb, cellctl"):
        AbbServer(_sim_arm(microcell_sim), reply_dialect="stock")
