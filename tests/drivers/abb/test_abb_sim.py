"""AbbArm against the ABB protocol simulator (drivers/sim/servers/abb.py in a thread), in both reply dialects
(open_abb: no terminator; cellctl: ended by '#'): the Arm contract over real sockets, and the faults (dropped link,
protective stop before and part way along a move, slow and malformed replies, stop)."""

from __future__ import annotations

import math
import socket
import threading
import time

import pytest
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz, tool_down

from drivers.arms.abb import AbbArm, MalformedReply, ReplyTimeout
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
from drivers.sim.servers import connect_when_up
from drivers.sim.servers.abb import AbbFaults, AbbServer, serve

from tests.conftest import MICROCELL
from tests.support.abb import (
    LIMITS,
    abb_on,
    server_reply,
    sim_arm,
)
from tests.support.contract import ArmContract
from tests.support.ports import free_ports
from tests.support.wait import eventually


class TestAbbOverSimServer(ArmContract):
    @pytest.fixture
    def make_device(self, server):
        return lambda: abb_on(server)


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
    with AbbServer(sim_arm(config)) as srv:
        arm = abb_on(srv)
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
    with AbbServer(sim_arm(microcell_sim.model_copy(update={"faults": faults}))) as srv:
        arm = abb_on(srv)
        arm.connect()
        arm.move_linear(Pose(0.05, 0.04, 0.01))
        with pytest.raises(ProtectiveStop):
            arm.move_linear(Pose(0.06, 0.04, 0.01))
        arm.close()


def test_slow_reply_is_an_error_not_a_hang(server):
    arm = abb_on(server, reply_timeout_s=0.2)
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


@pytest.mark.parametrize("verb", ["move_linear", "move_through"])
def test_stop_ends_a_move_in_progress(microcell_sim, verb):
    """A stop ends a move under way, a settled one and a fly-by to a via point alike (the via point's zone is put
    back to fine by the next ordinary move)."""
    config = microcell_sim.model_copy(update={"motion": microcell_sim.motion.model_copy(update={"realtime_factor": 1.0})})
    with AbbServer(sim_arm(config)) as srv:
        arm = abb_on(srv)
        arm.connect()
        outcome = {}

        def move():
            try:
                getattr(arm, verb)(Pose(0.150, 0.100, 0.020))  # about 1.8 s of real time
            except Exception as exc:  # noqa: BLE001 - handed to the test thread
                outcome["error"] = exc

        mover = threading.Thread(target=move)
        mover.start()
        assert srv.moving.wait(timeout=5.0)
        arm.stop()
        mover.join(timeout=10.0)
        assert not mover.is_alive()
        assert isinstance(outcome.get("error"), MotionStopped)
        stopped = arm.pose()
        assert stopped.x < 0.150 - 0.01  # short of the target: the stop, not the move's end, ended it
        arm.move_linear(Pose(0.050, 0.040, 0.010))
        assert srv.zone == (True, 0.0, 0.0, 0.0)  # fine
        # idle: harmless (with no move after it: a stop request that reaches the controller after the next move has
        # begun ends that move, on the RAPID server as here; cellctl sends none between a halt and a resume)
        arm.stop()
        arm.close()


def test_stop_without_a_logger_link_is_safe(server):
    """Without a logger link stop() can send nothing: it raises nothing, faults nothing, and the motion link stays
    in step (the next request is answered, the arm still where it was)."""
    arm = abb_on(server, logger_port=None)
    arm.stop()  # before connect: nothing to stop
    assert arm.state is DeviceState.CREATED
    arm.connect()
    before = arm.pose()
    arm.stop()
    assert arm.state is DeviceState.READY
    after = arm.pose()
    assert (after.x, after.y, after.z) == pytest.approx((before.x, before.y, before.z), abs=1e-6)
    target = Pose(before.x + 0.001, before.y, before.z)
    arm.move_linear(target)  # and it still moves when asked
    assert arm.pose().x == pytest.approx(target.x, abs=1e-4)
    arm.close()
    assert arm.state is DeviceState.CLOSED


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
    cartesian, joints = eventually(lambda: (logged := arm.logged())[0] and logged[1] and logged[0].values[0] == 70.0
                                   and logged[1].values[0] == 70.0 and logged, timeout=3.0, every=0.01,
                                   what="the logger's pose and joints at the target")
    assert cartesian.values[:3] == (70.0, 30.0, 12.0)
    assert joints.values == pytest.approx((70.0, 30.0, 12.0, -30.0, 0.0, 0.0))


def test_server_survives_vanishing_and_garbage_clients(server):
    for junk in (b"", b"01 +1.0", b"hello there#", b"x" * 200):
        with socket.create_connection(("127.0.0.1", server.motion_port), timeout=2.0) as raw:
            raw.sendall(junk)
            if junk.endswith(b"#"):
                assert raw.recv(64) == server_reply(server, "-1 0")
    with socket.create_connection(("127.0.0.1", server.motion_port), timeout=2.0) as raw:
        for request, reply in ((b"03 abc #", "3 0"), (b"03 1 #", "3 0"), (b"42 #", "42 0"),
                               (b"01 +1 +2 +3 +1 +0 +0 +0 #", "1 0"), (b"97 #", "97 1")):
            raw.sendall(request)
            assert raw.recv(64) == server_reply(server, reply)
    arm = abb_on(server)
    arm.connect()
    arm.pose()
    arm.close()
    assert server.clients_served >= 6


def test_before_connect_and_after_close(server):
    arm = abb_on(server)
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
        AbbServer(sim_arm(microcell_sim), reply_dialect="stock")
