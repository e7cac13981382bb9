"""Via points through the ABB driver (AbbArm.move_through, issue 31) against the protocol simulator, in both reply
dialects: a MoveL with the fly-by zone `via_zone`, which the simulator passes without settling (a fine point
settles); the cell file's zone set back for the next ordinary move, SET_ZONE sent only when the zone changes;
limits, refusals, protective stops, stops and a lost link as for move_linear."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz, tool_down

from drivers.arms.abb import AbbArm
from drivers.arms.abb import protocol as wire
from drivers.interfaces import (
    ConnectionLost,
    DeviceState,
    MotionRejected,
    MovesThrough,
    Pose,
    ProtectiveStop,
    move_via,
)
from drivers.sim.servers.abb import AbbServer

from tests.support.abb import LIMITS, abb_on, irb120_on_abb

START = Pose(0.040, 0.030, 0.010)
ABOVE = Pose(0.060, 0.045, 0.013)  # 3 mm over the part at (60, 45, 10) mm
DOWN = Pose(0.060, 0.045, 0.010)
FINE = (True, 0.0, 0.0, 0.0)


def _zone(name: str) -> tuple:
    return FINE if name == "fine" else (False, *wire.ZONES[name])


def _sent_during(server: AbbServer, call) -> int:
    """How many requests `call` sent on the motion link (each is answered)."""
    before = server.messages_on_connection
    call()
    return server.messages_on_connection - before


def test_the_driver_offers_via_points_and_checks_its_via_zone():
    arm = AbbArm.create("abb", {"host": "127.0.0.1", "limits": LIMITS})
    assert isinstance(arm, MovesThrough)
    assert arm.settings.via_zone == "z1"
    with pytest.raises(ValidationError, match=r"via_zone 'z7' unknown; allowed: fine, z0, z1"):
        AbbArm.create("abb", {"host": "127.0.0.1", "limits": LIMITS, "via_zone": "z7"})
    with pytest.raises(ValueError, match=r"zone 'z3' unknown; allowed: fine, z0"):
        arm.set_zone("z3")  # before anything is sent: nothing to connect for


def test_a_via_point_counts_the_motion_and_skips_the_settling(server, arm):
    world = server.arm.world
    settle = world.config.motion.settle_s
    arm.move_linear(START)
    t0 = world.clock.now()
    arm.move_through(ABOVE)
    via_s = world.clock.now() - t0
    assert server.zone == _zone("z1")
    arm.move_linear(START)
    t0 = world.clock.now()
    arm.move_linear(ABOVE)
    fine_s = world.clock.now() - t0
    assert server.zone == FINE  # the cell file's zone for the ordinary move
    motion = world.motion_time(START, ABOVE, arm.settings.speed_mm_s * 1e-3)
    assert via_s == pytest.approx(motion)
    assert fine_s == pytest.approx(motion + settle)
    assert via_s < fine_s


def test_the_arm_ends_where_asked_within_its_repeatability(server, arm):
    world = server.arm.world
    robot = world.config.robot
    arm.move_linear(START)
    for target in (ABOVE, Pose(0.070, 0.035, 0.012, math.radians(30))):
        arm.move_through(target)
        reported = arm.pose()  # the controller's report: the commanded pose to encoder resolution
        assert (reported.x, reported.y, reported.z) == pytest.approx((target.x, target.y, target.z), abs=1e-6)
        assert reported.alpha == pytest.approx(target.alpha, abs=1e-5)
        reached = world.arm.axis  # the true axis: within a few sigma of where this cell's geometry puts the target
        ideal = world._actual_axis(target, noise=False)
        assert np.all(np.abs(reached[:2] - ideal[:2]) < 6 * robot.repeatability_xy_um * 1e-6)
        assert abs(reached[2] - ideal[2]) < 6 * robot.repeatability_z_um * 1e-6


def test_set_zone_is_sent_only_when_it_changes(server, arm):
    arm.move_linear(START)
    assert _sent_during(server, lambda: arm.move_linear(DOWN)) == 1  # zone and speed unchanged: the move alone
    assert _sent_during(server, lambda: arm.move_through(ABOVE)) == 2  # the via zone, then the move
    assert _sent_during(server, lambda: arm.move_through(START)) == 1  # still the via zone
    assert server.zone == _zone("z1")
    assert _sent_during(server, lambda: arm.move_linear(DOWN)) == 2  # fine again, then the move
    assert server.zone == FINE
    joints = arm.joints()
    assert _sent_during(server, lambda: arm.move_joints(joints)) == 1
    # through move_via (what routines call) and at a speed of its own: speed, zone, move
    assert _sent_during(server, lambda: move_via(arm, ABOVE, 0.05)) == 3
    assert server.speed[0] == pytest.approx(50.0)
    assert _sent_during(server, lambda: arm.move_circular(Pose(0.065, 0.050, 0.013), Pose(0.060, 0.055, 0.013))) \
        == 5  # where it stands (the arc is checked from there), default speed, fine, circle point, arc
    assert server.zone == FINE


def test_the_zone_goes_back_to_the_cell_files_and_to_set_zones(server):
    arm = abb_on(server, zone="z0", via_zone="z5")
    arm.connect()
    try:
        assert server.zone == _zone("z0")
        arm.move_through(ABOVE)
        assert server.zone == _zone("z5")
        arm.move_linear(DOWN)
        assert server.zone == _zone("z0")  # the cell file's, not fine
        arm.set_zone("fine")
        arm.move_through(ABOVE)
        arm.buffer_clear()
        arm.buffer_add(START)
        arm.buffer_execute()  # buffered moves run in the ordinary zone
        assert server.zone == FINE
        arm.connect()  # a new link: the cell file's zone again
        assert server.zone == _zone("z0")
    finally:
        arm.close()


def test_via_zone_fine_makes_via_points_settle(server):
    arm = abb_on(server, via_zone="fine")
    arm.connect()
    try:
        world = server.arm.world
        arm.move_linear(START)
        t0 = world.clock.now()
        assert _sent_during(server, lambda: arm.move_through(ABOVE)) == 1  # no zone to change
        motion = world.motion_time(START, ABOVE, arm.settings.speed_mm_s * 1e-3)
        assert world.clock.now() - t0 == pytest.approx(motion + world.config.motion.settle_s)
    finally:
        arm.close()


def _refusal(call) -> tuple[type, str]:
    with pytest.raises(MotionRejected) as info:
        call()
    return type(info.value), str(info.value)


def test_a_refused_target_is_refused_as_by_move_linear(server, arm):
    arm.move_linear(START)
    outside = Pose(0.500, 0.030, 0.010)
    for target in (outside, Pose(0.050, 0.030, 0.010, orientation=(0.5, 0.5, 0.5, 0.6))):  # not a unit quaternion
        n = server.messages_on_connection
        assert _refusal(lambda t=target: arm.move_through(t)) == _refusal(lambda t=target: arm.move_linear(t))
        assert server.messages_on_connection == n  # refused before any byte was sent
    n = server.messages_on_connection
    assert _refusal(lambda: arm.move_through(ABOVE, speed=10.0)) == _refusal(lambda: arm.move_linear(ABOVE, speed=10.0))
    assert server.messages_on_connection == n
    # the controller refuses a tilted tool on the 4-axis cell (ok=0): the same error, nothing moved
    tilted = Pose(0.050, 0.030, 0.010, orientation=quaternion_wxyz(tool_down(0.0) * Rotation.from_euler("x", 5, degrees=True)))
    through = _refusal(lambda: arm.move_through(tilted))
    assert server.zone == _zone("z1")
    assert through == _refusal(lambda: arm.move_linear(tilted))
    assert server.zone == FINE
    assert "ok=0" in through[1] and "nothing moved" in through[1]
    assert arm.pose().xyz == pytest.approx(START.xyz, abs=1e-9)
    assert arm.state is DeviceState.READY


def test_a_protective_stop_at_a_via_point_is_reported_as_by_move_linear(server, arm):
    arm.move_linear(START)
    server.faults.protective_stop_mid_move = 0.5
    with pytest.raises(ProtectiveStop, match="protective stop"):
        arm.move_through(ABOVE)
    short = arm.pose()
    assert short.x == pytest.approx(0.050, abs=1e-6)  # half way: it came to a stand there
    with pytest.raises(ProtectiveStop):  # stays stopped until cleared, via point or not
        arm.move_through(ABOVE)
    with pytest.raises(ProtectiveStop):
        arm.move_linear(ABOVE)
    server.clear_protective_stop()
    arm.move_linear(DOWN)
    assert server.zone == FINE
    assert arm.pose().xyz == pytest.approx(DOWN.xyz, abs=1e-9)


def test_a_lost_link_during_a_via_point_faults_until_connect(server, arm):
    arm.move_linear(START)
    server.faults.drop_after_messages = server.messages_on_connection + 1  # the zone is answered, the move is not
    with pytest.raises(ConnectionLost, match="connect"):
        arm.move_through(ABOVE)
    assert arm.state is DeviceState.FAULTED
    server.faults.drop_after_messages = None
    with pytest.raises(ConnectionLost):
        arm.move_through(ABOVE)
    arm.connect()
    assert server.zone == FINE
    assert _sent_during(server, lambda: arm.move_through(ABOVE)) == 2  # the via zone is sent again
    assert arm.pose().xyz == pytest.approx(ABOVE.xyz, abs=1e-9)


def test_the_irb120_passes_via_points_without_settling():
    """The six-axis world behind the same protocol: a fly-by MoveL counts its motion, a fine one settles too."""
    with irb120_on_abb() as (world, arm):
        home = arm.pose()
        x, y, z = home.xyz
        there = Pose(x, y + 0.020, z, orientation=home.orientation)
        times = []
        for move in (arm.move_through, arm.move_linear):
            arm.move_linear(home)
            t0 = world.clock.now()
            move(there)
            times.append(world.clock.now() - t0)
            assert arm.pose().xyz == pytest.approx(there.xyz, abs=1e-6)
        assert times[1] - times[0] == pytest.approx(world.config.robot.settle_s)
