"""AbbArm's exact bytes: the protocol's framing and formats (pure), and pinned exchanges with a scripted
controller (what the driver sends, what it parses; the stock reply format without terminator; refusals before
anything is sent)."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from geometry.orientation import quaternion_wxyz, tool_down

from drivers.arms.abb import AbbArm, MalformedReply
from drivers.arms.abb import protocol as wire
from drivers.arms.abb.driver import CommandRejected
from drivers.interfaces import (
    ConnectionLost,
    DeviceState,
    JointState,
    MotionRejected,
    Pose,
)
from drivers.registry import backend_class

from tests.support.abb import (
    CONNECT_SCRIPT,
    LIMITS,
    ScriptedController,
)


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
