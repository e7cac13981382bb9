"""The open_abb request codes beyond the basic set, as the public SERVER.mod has them and our RAPID module,
the simulator and AbbArm now serve them: 5 (external axes), 34 (move the external axes), 35 + 36 (MoveC).

- the requests and replies in exact bytes (the protocol, pure; a scripted controller; the simulator in
  both reply dialects);
- what they mean on the 4-axis micro cell: no external axes (5 answers six 9E9, 34 moves nothing or is
  refused), arcs of the nozzle with the tool pointing down;
- the checks before anything moves: the whole arc against the workspace box (driver and simulator), three
  points that make no arc, a 36 without its 35.
"""

from __future__ import annotations

import math
import socket

import pytest
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz, tool_down

from drivers.arms.abb import protocol as wire
from drivers.arms.abb.arc import arc_length, arc_points
from drivers.interfaces import DeviceState, MotionRejected, MotionStopped, Pose, ProtectiveStop

from tests.support.abb import CONNECT_SCRIPT, ScriptedController, irb120_on_abb

Q0 = "+0.000000 +1.000000 +0.000000 +0.000000"  # the tool pointing down, alpha 0 (w first)
TILTED = quaternion_wxyz(tool_down(0.0) * Rotation.from_euler("x", 5, degrees=True))


def _sent(server, fields: str) -> bytes:
    """What the simulator sends for a reply of these fields: cellctl ends it with " #"; open_abb sends
    "<code> <ok> <data>" exactly as SERVER.mod builds it ("35 1 " with its space when there is no data)."""
    if server.reply_dialect == "cellctl":
        return (fields + " #").encode()
    return (fields if len(fields.split()) > 2 else fields + " ").encode()


def _frame(x: float, y: float, z: float, q: str = Q0) -> str:
    return f"{x:+.4f} {y:+.4f} {z:+.4f} {q}"


# --- the protocol, pure -------------------------------------------------------------------


def test_requests_are_pinned_bytes():
    assert wire.get_external_axes() == b"05 #"
    assert wire.move_external_axes([None] * 6) == b"34 9E9 9E9 9E9 9E9 9E9 9E9 #"
    assert wire.move_external_axes([1500.5, -90, None, None, None, None]) == b"34 +1500.5000 -90.0000 9E9 9E9 9E9 9E9 #"
    assert len(wire.move_external_axes([-99999.9999] * 6)) <= wire.MAX_REQUEST_CHARS
    with pytest.raises(ValueError, match="6 axes"):
        wire.move_external_axes([0.0] * 5)
    assert wire.circle_point((60, 40, 10), (0, 1, 0, 0)) == f"35 {_frame(60, 40, 10)} #".encode()
    assert wire.move_circular((50, 50, 10), (0, 1, 0, 0)) == f"36 {_frame(50, 50, 10)} #".encode()


def test_replies_are_framed_and_parsed_in_both_dialects():
    ours = wire.parse_reply(b"5 1 1500.0000 -90.0000 9E9 9E9 9E9 9E9 #", 5, 6)
    assert wire.parse_external_axes(ours) == (1500.0, -90.0, None, None, None, None)
    stock = b"5 1 1500.00 -90.00 90000000 90000000 90000000 90000000"  # SERVER.mod cuts each value to 8 characters
    frame, rest = wire.take_frame(stock, 5)  # no terminator: complete once its six fields are there
    assert (frame, rest) == (stock, b"")
    assert wire.parse_external_axes(wire.parse_reply(frame, 5, 6)) == (1500.0, -90.0, None, None, None, None)
    assert wire.take_frame(stock[:30], 5) == (None, stock[:30])
    for code in (34, 35, 36):
        assert wire.take_frame(f"{code} 1 ".encode(), code) == (f"{code} 1 ".encode(), b"")
        assert wire.take_frame(f"{code} 0 ".encode(), code)[0] is not None


def test_arc_geometry():
    points = arc_points((50, 30, 10), (60, 40, 10), (50, 50, 10), step_mm=0.5)
    assert points[0] == pytest.approx((50, 30, 10)) and points[-1] == pytest.approx((50, 50, 10))
    assert [math.dist(p, (50, 40, 10)) for p in points] == pytest.approx([10.0] * len(points))
    assert max(p[0] for p in points) == pytest.approx(60.0)  # through the circle point, the long way round
    assert arc_length(points) == pytest.approx(math.pi * 10, rel=1e-3)
    assert max(math.dist(a, b) for a, b in zip(points, points[1:])) <= 0.5 + 1e-9
    with pytest.raises(ValueError, match="on one line"):
        arc_points((0, 0, 0), (1, 1, 1), (2, 2, 2))
    with pytest.raises(ValueError, match="on one line"):
        arc_points((0, 0, 0), (1, 0, 0), (-1, 0, 0))  # start between the two: no circle either
    with pytest.raises(ValueError, match=r"0.0500 mm apart; MoveC needs at least 0.1 mm"):
        arc_points((0, 0, 0), (0, 0.05, 0), (10, 0, 0))


# --- the exact exchange with a scripted controller ---------------------------------------------

START = b"3 1 50.0000 30.0000 10.0000 0.000000 1.000000 0.000000 0.000000 #"


def test_pinned_exchange_of_the_codes_beyond_the_basic_set():
    controller = ScriptedController(CONNECT_SCRIPT + [
        (b"05 #", b"5 1 1500.0000 -90.0000 9E9 9E9 9E9 9E9 #"),
        (b"34 +1200.0000 +45.0000 9E9 9E9 9E9 9E9 #", b"34 1 #"),
        (b"34 +1200.0000 9E9 9E9 9E9 9E9 9E9 #", b"34 0 #"),
        (b"03 #", START),  # where the arc starts
        (f"35 {_frame(60, 40, 10)} #".encode(), b"35 1 #"),
        (f"36 {_frame(50, 50, 10)} #".encode(), b"36 1 #"),
        (b"03 #", START),
        (f"35 {_frame(60, 40, 10)} #".encode(), b"35 0 #"),  # refused: no 36 follows
        (b"03 #", START),
        (f"35 {_frame(60, 40, 10)} #".encode(), b"35 1 #"),
        (f"36 {_frame(50, 50, 10)} #".encode(), b"36 3 #"),  # stopped part way
        (b"03 #", b"3 1 150.0000 50.0000 10.0000 0.000000 1.000000 0.000000 0.000000 #"),  # nothing after this
        (b"99 #", b"99 1 #"),
    ])
    arm = controller.arm(external_linear_axes=[1])
    arm.connect()
    axes = arm.external_axes()
    assert axes[0] == pytest.approx(1.5) and axes[1] == pytest.approx(math.radians(-90)) and axes[2:] == (None,) * 4
    arm.move_external_axes([1.2, math.radians(45), None, None, None, None])
    with pytest.raises(MotionRejected, match="ok=0: a value for an external axis the robot does not have, or none "
                                             r"\(None\) for one it has"):
        arm.move_external_axes([1.2, None, None, None, None, None])
    arm.move_circular(Pose(0.060, 0.040, 0.010), Pose(0.050, 0.050, 0.010))
    with pytest.raises(MotionRejected, match=r"refused '35 \+60.0000 .*' \(ok=0: an arc the controller cannot run"):
        arm.move_circular(Pose(0.060, 0.040, 0.010), Pose(0.050, 0.050, 0.010))
    with pytest.raises(MotionStopped):
        arm.move_circular(Pose(0.060, 0.040, 0.010), Pose(0.050, 0.050, 0.010))
    with pytest.raises(MotionRejected, match=r"the arc leaves the workspace box at \(160\.\d+, .*\) mm: target "
                                             r"x_mm=160\.\d+ is outside the workspace box \[-10.0, 160.0\]; nothing moved"):
        arm.move_circular(Pose(0.1574246, 0.0530754, 0.010), Pose(0.150, 0.071, 0.010))  # circle of 10.5 mm about
        # (150, 60.5): both points inside the box, the arc between them through x = 160.5
    assert arm.state is DeviceState.READY
    arm.close()
    controller.finish()


def test_refusals_before_any_byte_is_sent():
    controller = ScriptedController(CONNECT_SCRIPT + [(b"03 #", START), (b"99 #", b"99 1 #")])
    arm = controller.arm()
    arm.connect()
    with pytest.raises(MotionRejected, match="an extjoint has 6 axes .* nothing moved"):
        arm.move_external_axes([0.0] * 5)
    with pytest.raises(MotionRejected, match="not all finite"):
        arm.move_external_axes([math.nan] + [None] * 5)
    with pytest.raises(MotionRejected, match="at most 80"):
        arm.move_external_axes([1e9] * 6)  # would not fit a RAPID string
    with pytest.raises(MotionRejected, match="outside the workspace box"):
        arm.move_circular(Pose(0.5, 0.04, 0.01), Pose(0.05, 0.05, 0.01))  # the circle point itself
    with pytest.raises(MotionRejected, match="on one line"):
        arm.move_circular(Pose(0.060, 0.040, 0.010), Pose(0.070, 0.050, 0.010))  # from (50, 30, 10): a line
    arm.close()
    controller.finish()
    assert controller.received == CONNECT_SCRIPT_REQUESTS + [b"03 #", b"99 #"]


CONNECT_SCRIPT_REQUESTS = [request for request, _ in CONNECT_SCRIPT]


# --- the simulator: exact replies, in each dialect ------------------------------------------------


def test_simulator_replies_in_exact_bytes(server):
    """The micro cell behind the protocol: no external axes; arcs of the nozzle, tool down."""
    tilted = " ".join(f"{v:+.6f}" for v in TILTED)
    with socket.create_connection(("127.0.0.1", server.motion_port), timeout=5.0) as raw:
        for request, fields in (
            (b"05 #", "5 1 9E9 9E9 9E9 9E9 9E9 9E9"),
            (b"05 1 #", "5 0"),
            (b"34 9E9 9E9 9E9 9E9 9E9 9E9 #", "34 1"),  # nothing to move: a MoveAbsJ that moves nothing
            (b"34 +1.0000 9E9 9E9 9E9 9E9 9E9 #", "34 0"),  # eax_a is not there
            (b"34 9E9 #", "34 0"),
            (f"36 {_frame(50, 50, 10)} #".encode(), "36 0"),  # no circle point yet
            (f"01 {_frame(50, 30, 10)} #".encode(), "1 1"),
            (f"35 {_frame(60, 40, 10)} #".encode(), "35 1"),
            (f"36 {_frame(50, 50, 10)} #".encode(), "36 1"),
            (b"03 #", "3 1 50.0000 50.0000 10.0000 0.000000 1.000000 0.000000 0.000000"),
            (f"36 {_frame(50, 30, 10)} #".encode(), "36 0"),  # the circle point was used up
            (f"35 {_frame(60, 40, 10, '+0.000000 +2.000000 +0.000000 +0.000000')} #".encode(), "35 0"),
            (f"35 {_frame(60, 40, 10, tilted)} #".encode(), "35 0"),  # a 4-axis arm cannot tilt its tool
            (f"35 {_frame(60, 50, 10)} #".encode(), "35 1"),
            (f"36 {_frame(70, 50, 10)} #".encode(), "36 0"),  # start, circle point and end on one line
            (f"01 {_frame(89.5, 0, 10)} #".encode(), "1 1"),
            (f"35 {_frame(92.5754, -7.4246, 10)} #".encode(), "35 1"),
            (f"36 {_frame(110.5, 0, 10)} #".encode(), "36 0"),  # the arc dips to y = -10.5, below the box
            (b"03 #", "3 1 89.5000 0.0000 10.0000 0.000000 1.000000 0.000000 0.000000"),  # nothing moved
        ):
            raw.sendall(request)
            assert raw.recv(256) == _sent(server, fields), request


def test_a_circle_point_is_not_carried_over_to_the_next_client(server):
    with socket.create_connection(("127.0.0.1", server.motion_port), timeout=5.0) as raw:
        for request, fields in ((f"01 {_frame(50, 30, 10)} #".encode(), "1 1"),
                                (f"35 {_frame(60, 40, 10)} #".encode(), "35 1")):
            raw.sendall(request)
            assert raw.recv(256) == _sent(server, fields)
    with socket.create_connection(("127.0.0.1", server.motion_port), timeout=5.0) as raw:
        raw.sendall(f"36 {_frame(50, 50, 10)} #".encode())
        assert raw.recv(256) == _sent(server, "36 0")


# --- the driver on the simulator -------------------------------------------------------------------


def test_external_axes_of_the_micro_cell(server, arm):
    assert arm.external_axes() == (None,) * 6  # x, y, z, alpha are robot axes (code 4), not external ones
    home = arm.pose()
    arm.move_external_axes([None] * 6)
    with pytest.raises(MotionRejected, match="does not have"):
        arm.move_external_axes([0.5, None, None, None, None, None])
    assert arm.pose() == home
    server.faults.protective_stop = True
    with pytest.raises(ProtectiveStop):
        arm.move_external_axes([None] * 6)
    server.clear_protective_stop()


def test_circular_moves_of_the_micro_cell(server, arm):
    arm.move_linear(Pose(0.050, 0.030, 0.010))
    arm.move_circular(Pose(0.060, 0.040, 0.010), Pose(0.050, 0.050, 0.012, math.radians(30)))
    pose = arm.pose()
    assert pose.xyz == pytest.approx((0.050, 0.050, 0.012), abs=1e-9)
    assert pose.alpha == pytest.approx(math.radians(30), abs=1e-5)
    with pytest.raises(MotionRejected, match=r"refused '35 .*' \(ok=0"):
        arm.move_circular(Pose(0.060, 0.040, 0.010, orientation=TILTED), Pose(0.050, 0.030, 0.010))
    arm.move_linear(Pose(0.0895, 0.0, 0.010))
    with pytest.raises(MotionRejected, match="the arc leaves the workspace box"):  # the driver's own check
        arm.move_circular(Pose(0.0925754, -0.0074246, 0.010), Pose(0.1105, 0.0, 0.010))
    assert arm.pose().xyz == pytest.approx((0.0895, 0.0, 0.010), abs=1e-9)
    arm.set_workobject((10, 0, 0, 1, 0, 0, 0))  # the arc is in the work object, from where the TCP stands in it
    arm.move_circular(Pose(0.0895, 0.010, 0.010), Pose(0.0795, 0.020, 0.010))
    assert arm.pose().xyz == pytest.approx((0.0795, 0.020, 0.010), abs=1e-9)
    arm.set_workobject((0, 0, 0, 1, 0, 0, 0))
    assert arm.pose().xyz == pytest.approx((0.0895, 0.020, 0.010), abs=1e-9)


def test_the_irb120_cell_has_no_external_axes_and_runs_arcs_in_any_orientation():
    """The six-axis world behind the same protocol: 5 answers six 9E9 (the IRB 120 cell has no track or
    positioner); an arc of the flange at its tilted home orientation is run through its nominal kinematics."""
    with irb120_on_abb() as (_, arm):
        assert arm.external_axes() == (None,) * 6
        home = arm.pose()
        q, (x, y, z) = home.orientation, home.xyz
        arm.move_circular(Pose(x + 0.010, y + 0.010, z, orientation=q), Pose(x, y + 0.020, z, orientation=q))
        end = arm.pose()
        assert end.xyz == pytest.approx((x, y + 0.020, z), abs=1e-6)
        assert abs(sum(a * b for a, b in zip(end.orientation, q))) == pytest.approx(1.0, abs=1e-9)  # same rotation
        with pytest.raises(MotionRejected, match="does not have"):
            arm.move_external_axes([math.radians(10), None, None, None, None, None])
