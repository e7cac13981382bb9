"""UrArm (ur_rtde) against the UR simulator, each simulator in its own process.

ur_rtde's constructors hold the GIL, so the simulator can never be a thread of this
process: every test talks to a child process started by SimulatorProcess on its own
loopback address (the RTDE port 30004 is fixed). The remote-arm test shares this
process's World with the simulator through drivers.sim.remote.ArmHost.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest
import yaml

from drivers.interfaces import (
    ConnectionLost,
    DeviceState,
    JointState,
    MotionStopped,
    NotConnected,
    Pose,
    ProtectiveStop,
)
from drivers.registry import DriverContext, backend_class
from drivers.sim.servers.ur import SimulatorProcess
from drivers.sim.servers.ur.controller import matrix_of_rotvec
from drivers.sim.servers.ur.kinematics import UrKinematics

from tests.conftest import MICROCELL, microcell_data
from tests.support.contract import ArmContract
from tests.support.ur import LIMITS, ur_arm
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py

pytest.importorskip("rtde_control")

DATA = microcell_data()




def _realtime_cell(folder) -> str:
    """The micro cell whose moves take their real time (so a move can be interrupted)."""
    data = microcell_data()
    data["sim"]["motion"].update(realtime_factor=1.0, speed_mm_s=50.0, settle_s=0.02)
    path = folder / "realtime-cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.fixture(scope="module")
def world_host():
    """A World owned by this process (as the cameras' is) with its SimArm served to other processes."""
    from drivers.sim.micro.config import SimWorldConfig
    from drivers.sim.remote import ArmHost

    context = DriverContext(sim_config=SimWorldConfig(**DATA["sim"]))
    sim_arm = backend_class("arm", "sim").create("arm", {"limits": LIMITS}, context)
    sim_arm.connect()
    host = ArmHost(sim_arm)
    yield context.sim_world(), host
    host.close()


@pytest.fixture(scope="module")
def sims(tmp_path_factory, world_host):
    """Every simulator this module needs, started side by side (each takes most of a second to come up)."""
    realtime = _realtime_cell(tmp_path_factory.mktemp("ur"))
    processes = {
        "main": SimulatorProcess("127.0.0.2", MICROCELL, options={"unlock_delay_s": 0.0}),
        "remote": SimulatorProcess("127.0.0.3", world_host[1]),
        "pstop": SimulatorProcess("127.0.0.4", realtime, options={"unlock_delay_s": 0.0}),
        "drop": SimulatorProcess("127.0.0.5", MICROCELL, options={"faults": {"drop_after_commands": 2,
                                                                             "outage_s": 0.2}}),
        "knob": SimulatorProcess("127.0.0.6", realtime, options={"faults": {"protective_stop_after_moves": 2}}),
        "off": SimulatorProcess("127.0.0.10", MICROCELL, options={"powered": False}),
        # the slow-dashboard knob: every reply 0.3 s late; only unlock's 4 s late; every reply 4 s late
        "slow": SimulatorProcess("127.0.0.16", MICROCELL, options={"slow_reply_s": 0.3, "unlock_delay_s": 0.0}),
        "slow_unlock": SimulatorProcess("127.0.0.17", MICROCELL, options={
            "slow_reply_s": 4.0, "slow_requests": ["unlock protective stop"], "unlock_delay_s": 0.0}),
        "slow_all": SimulatorProcess("127.0.0.18", MICROCELL, options={"slow_reply_s": 4.0}),
    }
    errors = []

    def start(process):
        try:
            process.start()
        except Exception as exc:  # noqa: BLE001 - reported below, after every start has finished
            errors.append(exc)

    threads = [threading.Thread(target=start, args=(p,)) for p in processes.values()]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        if errors:
            raise errors[0]
        yield processes
    finally:
        for p in processes.values():
            p.terminate()
        codes = {name: p.stop() for name, p in processes.items()}
    assert all(code == 0 for code in codes.values()), codes  # SIGTERM: a clean exit


@pytest.fixture
def sim(sims):
    return sims["main"]


class TestUrArm(ArmContract):
    @pytest.fixture
    def make_device(self, sim):
        return lambda: ur_arm(sim.host)

    def test_joints_are_the_ur5e_angles_of_the_pose(self, make_device):
        """joints() of a UR on the micro cell: the six joint angles (rad) of the simulator's UR5e, whose forward
        kinematics is the pose; move_joints to angles of the same branch goes to their pose."""
        arm = make_device()
        arm.connect()
        try:
            k = UrKinematics()
            for target in (Pose(0.050, 0.040, 0.010, 0.0), Pose(0.120, 0.010, 0.030, math.radians(-120))):
                arm.move_linear(target)
                joints = arm.joints()
                assert joints.names == ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
                assert joints.positions == pytest.approx(k.joints(target), abs=1e-9)
                pose = arm.pose()
                T = k.forward(joints.positions)
                assert T[:3, 3] == pytest.approx(pose.xyz, abs=1e-9)
                assert math.atan2(T[1, 0], T[0, 0]) == pytest.approx(math.remainder(pose.alpha, math.tau), abs=1e-9)
            goal = Pose(0.080, 0.070, 0.005, math.radians(40))
            arm.move_joints(JointState(k.joints(goal)))
            assert math.dist(arm.pose().xyz, goal.xyz) < 1e-6
            assert arm.joints().positions == pytest.approx(k.joints(goal), abs=1e-6)
        finally:
            arm.close()

    def test_joint_targets_off_the_branch_stop_the_control_script(self, make_device, sim):
        arm = make_device()
        arm.connect()
        try:
            arm.move_linear(Pose(0.050, 0.040, 0.010, 0.0))
            q = list(arm.joints().positions)
            # the simulator ends the control script; ur_rtde reports that, or the refused move if its answer
            # comes first (both seen: which wins is timing), and the simulator's log says why
            with pytest.raises(MotionStopped, match="control script|did not accept the move"):
                arm.move_joints(JointState((q[0], q[1] + 0.2, *q[2:])))  # tilts the tool: a 4-axis arm cannot
            assert sim.said("tilt the tool")
            assert arm.state is DeviceState.FAULTED
            arm.connect()
            assert math.dist(arm.pose().xyz, (0.050, 0.040, 0.010)) < 1e-6  # nothing moved
        finally:
            arm.close()


def test_unmodified_ur_rtde_moves_and_the_receive_interface_reports_it(sim):
    import rtde_control
    import rtde_receive

    control = rtde_control.RTDEControlInterface(sim.host)
    try:
        target = [0.061, 0.042, 0.012, math.pi, 0.0, 0.0]
        assert control.moveL(target, 0.25, 1.2)
        receive = rtde_receive.RTDEReceiveInterface(sim.host)  # the default recipe: every variable it asks for
        try:
            got = receive.getActualTCPPose()
            assert math.dist(got[:3], target[:3]) < 1e-4
            flange = UrKinematics().forward(receive.getActualQ())  # a UR5e's joint angles (the arm stands still)
            assert flange[:3, 3] == pytest.approx(got[:3], abs=1e-12)
            assert np.abs(flange[:3, :3] - matrix_of_rotvec(got[3:])).max() < 1e-12
            assert receive.getRobotMode() == 7 and receive.getSafetyMode() == 1
            t0 = receive.getTimestamp()
            _until(lambda: receive.getTimestamp() > t0, "the RTDE stream's timestamp advances")  # the stream runs
        finally:
            receive.disconnect()
    finally:
        control.stopScript()
        control.disconnect()


def _until(condition, what: str, timeout_s: float = 3.0) -> None:
    """`condition()` until true; fail naming `what` after `timeout_s`."""
    eventually(condition, timeout=timeout_s, every=0.005, what=what)


def test_unmodified_ur_rtde_moves_the_world_the_simulated_camera_sees(sims, world_host):
    """moveL through the stock ur_rtde client, the new pose read back by RTDEReceiveInterface within 0.1 mm,
    and a simulated camera of the same world (this process's, served to the UR simulator by ArmHost)
    sees the nozzle move by what the move commanded."""
    import rtde_control
    import rtde_receive

    from drivers.sim.devices import SimCamera

    from calibration.vision.centroid import find_blob

    world, _ = world_host
    camera = SimCamera("cam2", world, SimCamera.Settings())  # top view of area2, 24 um per pixel at z = 0
    camera.connect()
    start, target = [0.105, 0.036, 0.0, math.pi, 0.0, 0.0], [0.114, 0.043, 0.0, math.pi, 0.0, 0.0]
    control = rtde_control.RTDEControlInterface(sims["remote"].host)
    try:
        receive = rtde_receive.RTDEReceiveInterface(sims["remote"].host)
        try:
            seen = []
            for pose in (start, target):
                assert control.moveL(pose, 0.25, 1.2)
                _until(lambda pose=pose: math.dist(receive.getActualTCPPose()[:3], pose[:3]) < 1e-4,
                       f"getActualTCPPose within 0.1 mm of {pose[:3]}")
                frame = camera.capture()
                blob = find_blob(frame.image)
                truth = world.frame_truth[("cam2", frame.frame_id)].features_px[0]  # the nozzle's true centre
                assert math.dist((blob.u, blob.v), truth) < 0.1  # the camera sees the nozzle where it is
                seen.append((blob.u, blob.v, truth))
        finally:
            receive.disconnect()
    finally:
        control.stopScript()
        control.disconnect()
    (u0, v0, truth0), (u1, v1, truth1) = seen
    moved_px = math.hypot(u1 - u0, v1 - v0)
    commanded_px = math.dist(start[:2], target[:2]) / 24e-6  # 11.4 mm at 24 um per pixel: ~475 px
    assert moved_px == pytest.approx(commanded_px, rel=0.02)  # perspective, tilt and distortion: under 2 %
    assert math.dist((u1 - u0, v1 - v0), (truth1[0] - truth0[0], truth1[1] - truth0[1])) < 0.2




def test_dashboard_answers_like_polyscope(sim):
    import dashboard_client

    dash = dashboard_client.DashboardClient(sim.host)
    dash.connect()
    try:
        assert dash.polyscopeVersion().startswith("5.")
        assert dash.getSerialNumber().isdigit()
        assert dash.robotmode() == "Robotmode: RUNNING"
        assert dash.safetymode() == "Safetymode: NORMAL"
        assert dash.isInRemoteControl()
        dash.unlockProtectiveStop()  # nothing to unlock: accepted
    finally:
        dash.disconnect()


def test_remote_arm_moves_the_world_owned_by_this_process(sims, world_host):
    """The test process owns the World (as the cameras do); the simulator process moves its SimArm."""
    world, _ = world_host
    arm = ur_arm(sims["remote"].host)
    arm.connect()
    try:
        target = Pose(0.0423, 0.0317, 0.0051, math.radians(-20))
        arm.move_linear(target)
        assert math.dist(world.arm.commanded.xyz, target.xyz) < 1e-9  # this process's world moved
        assert abs(world.arm.commanded.alpha - target.alpha) < 1e-9
        assert math.dist(world.reported_pose().xyz, arm.pose().xyz) < 1e-9
        # a rotation vector cannot tell 350 deg from -10 deg: the driver reports the turn it commanded
        for degrees in (350, -200):
            arm.move_linear(Pose(0.050, 0.040, 0.010, math.radians(degrees)))
            assert arm.pose().alpha == pytest.approx(math.radians(degrees), abs=1e-9)
    finally:
        arm.close()


def test_unmodified_synchronous_movel_releases_the_gil_for_the_remote_arm(sims, world_host):
    """ur_rtde's blocking moveL must let this process's ArmHost thread run (else: deadlock, the test hangs)."""
    import rtde_control

    world, _ = world_host
    control = rtde_control.RTDEControlInterface(sims["remote"].host)
    try:
        assert control.moveL([0.0611, 0.0222, 0.0033, math.pi, 0.0, 0.0], 0.25, 1.2)  # asynchronous=False
        assert math.dist(world.arm.commanded.xyz, (0.0611, 0.0222, 0.0033)) < 1e-9
    finally:
        control.stopScript()
        control.disconnect()


def test_remote_arm_errors_keep_their_types(world_host):
    from drivers.interfaces import DeviceError, MotionRejected
    from drivers.sim.remote import RemoteArm

    _, host = world_host
    remote = RemoteArm(host.address_text, host.authkey)
    try:
        with pytest.raises(MotionRejected, match="workspace box"):
            remote.move_linear(Pose(5.0, 0.0, 0.0))
        with pytest.raises(DeviceError, match="key"):
            RemoteArm(host.address_text, b"not the key").pose()
    finally:
        remote.close()


class _Watcher(threading.Thread):
    """Calls `action` once the arm's reported x passes `x` (the move is under way), or gives up after 10 s."""

    def __init__(self, arm, x: float, action):
        super().__init__(daemon=True)
        self.arm, self.x, self.action = arm, x, action
        self.fired, self.error = False, None

    def run(self):
        try:  # pose() from another thread: its own connection to ur_rtde's process
            eventually(lambda: self.arm.pose().x > self.x, timeout=10.0, every=0.002, what=f"the arm past x = {self.x}")
        except AssertionError as exc:
            self.error = str(exc)
            return
        self.action()
        self.fired = True


def _when_moving_past(arm, x: float, action) -> _Watcher:
    watcher = _Watcher(arm, x, action)
    watcher.start()
    return watcher


def _dashboard_answers(host: str) -> bool:
    """True when the dashboard greets a new connection: during a simulated outage it is closed at once."""
    try:
        with socket.create_connection((host, 29999), timeout=1.0) as sock:
            sock.settimeout(1.0)
            return sock.makefile("rb").readline().startswith(b"Connected: Universal Robots Dashboard Server")
    except OSError:
        return False


def test_protective_stop_aborts_the_move_and_is_surfaced(sims):
    arm = ur_arm(sims["pstop"].host)
    arm.connect()
    try:
        start = Pose(0.040, 0.030, 0.010, 0.0)
        arm.move_linear(start)
        far = Pose(0.090, 0.030, 0.010, 0.0)  # 50 mm at 50 mm/s: about a second
        watcher = _when_moving_past(arm, 0.045, arm.trigger_protective_stop)
        with pytest.raises(ProtectiveStop, match="protective stop"):
            arm.move_linear(far)
        watcher.join(15.0)
        assert watcher.fired, watcher.error
        stopped_at = arm.pose()
        assert 0.045 <= stopped_at.x < 0.089  # aborted part way, after it was seen moving
        assert arm.safety_mode() == "PROTECTIVE_STOP"
        with pytest.raises(ProtectiveStop):
            arm.move_linear(start)  # refused while stopped
        arm.unlock_protective_stop()
        arm.connect()  # the operator's way back: a new control script
        arm.move_linear(start)
        assert math.dist(arm.pose().xyz, start.xyz) < 1e-6
    finally:
        arm.close()


def test_protective_stop_fault_knob_and_stop_interrupts_a_move(sims):
    arm = ur_arm(sims["knob"].host)
    arm.connect()
    try:
        arm.move_linear(Pose(0.040, 0.030, 0.010, 0.0))
        watcher = _when_moving_past(arm, 0.045, arm.stop)
        with pytest.raises(MotionStopped, match="stop"):
            arm.move_linear(Pose(0.090, 0.030, 0.010, 0.0))
        watcher.join(15.0)
        assert watcher.fired, watcher.error
        assert 0.045 <= arm.pose().x < 0.089
        before = arm.pose()
        with pytest.raises(ProtectiveStop):
            arm.move_linear(Pose(0.050, 0.050, 0.010, 0.0))  # move 3: the knob stops it before it starts
        assert math.dist(arm.pose().xyz, before.xyz) < 1e-9
    finally:
        arm.close()


def test_dropped_connection_is_connection_lost_until_connect(sims):
    # The simulator drops every connection at the 3rd command: setTcp, moveL, then the drop.
    arm = ur_arm(sims["drop"].host)
    arm.connect()
    try:
        arm.move_linear(Pose(0.050, 0.040, 0.010, 0.0))
        with pytest.raises(ConnectionLost, match="connect"):
            arm.move_linear(Pose(0.060, 0.040, 0.010, 0.0))
        assert arm.state is DeviceState.FAULTED
        with pytest.raises(ConnectionLost):
            arm.pose()  # no silent reconnect
        arm.stop()  # still safe
        _until(lambda: _dashboard_answers(arm.settings.host), "the simulated outage (outage_s 0.2) ends",
               timeout_s=10.0)
        arm.connect()
        assert arm.state is DeviceState.READY
        assert math.dist(arm.pose().xyz, (0.050, 0.040, 0.010)) < 1e-6  # the lost command never moved it
    finally:
        arm.close()


def test_powered_off_robot_is_refused_or_powered_on_when_allowed(sims):
    from drivers.interfaces import DeviceError

    arm = ur_arm(sims["off"].host)
    with pytest.raises(DeviceError, match="POWER_OFF.*power_on: true"):
        arm.connect()
    assert arm.state is DeviceState.CREATED
    arm = ur_arm(sims["off"].host, power_on=True)
    arm.connect()
    try:
        assert arm.robot_mode() == "RUNNING"
        arm.move_linear(Pose(0.050, 0.040, 0.010, 0.0))
    finally:
        arm.close()


def test_unreachable_controller_fails_fast_with_a_clear_error():
    arm = ur_arm("127.0.0.9", connect_timeout_s=0.5)
    with pytest.raises(ConnectionLost, match="does not accept on port"):
        arm.connect()
    with pytest.raises(NotConnected, match="connect"):
        arm.pose()




def test_tcp_offset_and_upper_range_registers(sim):
    """setTcp moves the reported TCP off the flange; ur_rtde's register offset 24 reaches the script emulation."""
    arm = ur_arm(sim.host, upper_range_registers=True, tcp_offset_mm=(0.0, 0.0, 10.0))
    arm.connect()
    try:
        target = Pose(0.050, 0.040, 0.010, math.radians(15))
        arm.move_linear(target)
        assert math.dist(arm.pose().xyz, target.xyz) < 1e-9
        flange = UrKinematics().forward(arm.joints().positions)  # the UR5e's flange for the joints it reports
        assert flange[:3, 3] == pytest.approx((target.x, target.y, target.z + 0.010), abs=1e-9)  # above the TCP
    finally:
        arm.close()


# --- link faults seen by the driver (ur_rtde runs in UrArm's child process: its crash is ConnectionLost) ------

def _pose_until_error(arm, limit_s: float = 20.0) -> tuple[ConnectionLost, float]:
    """pose() every 5 ms until it raises ConnectionLost: (the error, seconds it took)."""
    start = time.monotonic()
    while time.monotonic() - start < limit_s:
        try:
            arm.pose()
        except ConnectionLost as exc:
            return exc, time.monotonic() - start
        time.sleep(0.005)
    pytest.fail(f"pose() never raised within {limit_s} s")


def test_silent_rtde_stream_makes_pose_raise_connection_lost_and_close_and_reconnect_work():
    """silent_after_packets: the controller stops sending data packages but keeps the sockets open. ur_rtde
    notices nothing (its getters keep returning the last values); the driver's timestamp watchdog makes pose()
    raise ConnectionLost naming the silence within link_timeout_s (+ slack) and leaves the arm FAULTED.
    Destroying ur_rtde's interfaces now (it reconnects in the background) used to segfault the caller: with
    ur_rtde in UrArm's child process, close() and a later connect() just work, in this process."""
    with SimulatorProcess("127.0.0.12", MICROCELL, options={"faults": {"silent_after_packets": 500}}) as silent:
        arm = ur_arm(silent.host, link_timeout_s=0.5)
        arm.connect()
        started = time.monotonic()
        error, elapsed = _pose_until_error(arm)
        assert silent.said("stops, socket kept open")  # the knob fired
        assert "no RTDE data for" in str(error) and "call connect()" in str(error)
        assert arm.state is DeviceState.FAULTED
        assert elapsed < 500 / 500 + 0.5 + 1.5  # ~1 s of stream, then the link time-out (ur_rtde has none)
        with pytest.raises(ConnectionLost, match="connect"):
            arm.pose()
        arm.close()  # no crash
        assert arm.state is DeviceState.CLOSED
        arm.connect()  # a new ur_rtde process, a new link (the knob counts packets per connection)
        try:
            assert arm.state is DeviceState.READY
            assert math.isfinite(arm.pose().x)
            _pose_until_error(arm)  # the knob fires again: still a typed error
            arm.connect()  # straight from FAULTED, without close(): no crash either
            assert arm.state is DeviceState.READY and math.isfinite(arm.pose().x)
        finally:
            arm.close()
    assert time.monotonic() - started < 30


def test_malformed_rtde_frame_is_connection_lost_naming_ur_rtde_s_abort():
    """A data package whose size field (2) is below the 3-byte header makes ur_rtde 1.6.5's receive thread
    throw std::length_error, which nothing catches: std::terminate aborts ur_rtde's process. That process is
    UrArm's child, so this process lives on and pose() raises ConnectionLost naming the abort (SIGABRT) and
    "call connect()" within moments of the bad frame; the arm is FAULTED, close() and connect() work."""
    import os

    with SimulatorProcess("127.0.0.11", MICROCELL, options={"faults": {"malformed_after_packets": 500}}) as bad:
        arm = ur_arm(bad.host, link_timeout_s=0.5)
        arm.connect()
        try:
            error, elapsed = _pose_until_error(arm)
            assert bad.said("malformed RTDE frame")
            message = str(error)
            assert "ur_rtde's process" in message and "died with signal SIGABRT" in message, message
            assert "std::length_error" in message and "call connect() to reconnect" in message, message
            assert elapsed < 10  # bounded: the abort follows the bad frame (package 501, about 1 s of stream)
            assert arm.state is DeviceState.FAULTED
            with pytest.raises(ConnectionLost, match="call connect"):
                arm.joints()
            arm.stop()  # never raises
            arm.connect()  # a new child; the knob fires again on the new link
            assert arm.state is DeviceState.READY and math.isfinite(arm.pose().x)
        finally:
            arm.close()
        assert arm.state is DeviceState.CLOSED
        assert arm._child.poll() is not None  # close() ended ur_rtde's process
    assert os.getpid()  # still this process


# --- the child process: a hung request, a slow dashboard ---------------------------------------------------------

def wait_stopped(pid: int, timeout_s: float = 5.0) -> None:
    """Until every thread of `pid` is stopped ("T" in /proc/PID/task/*/stat)."""
    from pathlib import Path

    def states() -> list[str]:
        return [(t / "stat").read_text().rsplit(")", 1)[1].split()[0] for t in Path(f"/proc/{pid}/task").iterdir()]

    eventually(lambda: all(state in "tT" for state in states()), timeout=timeout_s, every=0.01,
               what=lambda: f"process {pid} stopped (thread states {states()})")


FAST_TIMEOUTS = {"command_timeout_s": 1.0, "settle_timeout_s": 0.2, "link_timeout_s": 0.5}


def test_a_request_that_hangs_in_the_child_is_connection_lost_within_its_time_out(sim):
    """ur_rtde's process stops answering (frozen here with SIGSTOP, as a deadlock in ur_rtde holding its GIL
    would): pose() gives up after its time-out (command + settle + link time-outs + 5 s) with ConnectionLost
    saying so and what to do; the frozen child is ended (SIGTERM cannot end a stopped process: SIGKILL does);
    the arm is FAULTED, stop() stays safe, and connect() starts a new child."""
    import os
    import signal

    arm = ur_arm(sim.host, **FAST_TIMEOUTS)
    arm.connect()
    try:
        arm.move_linear(Pose(0.050, 0.040, 0.010, 0.0))
        child = arm._child
        os.kill(child.pid, signal.SIGSTOP)
        wait_stopped(child.pid)  # SIGSTOP stops every thread of the child, not necessarily before kill() returns
        start = time.monotonic()
        with pytest.raises(ConnectionLost) as caught:
            arm.pose()
        elapsed = time.monotonic() - start
        message = str(caught.value)
        assert "ur_rtde's process did not answer pose in time" in message, message
        assert "ended it" in message and "call connect() to reconnect" in message, message
        assert arm._timeout_s == pytest.approx(6.7)
        assert arm._timeout_s <= elapsed < arm._timeout_s + 5.0  # the time-out, then ending the child (< 3 s)
        assert child.poll() == -signal.SIGKILL
        assert arm.state is DeviceState.FAULTED
        with pytest.raises(ConnectionLost, match="connect"):
            arm.joints()
        arm.stop()  # never raises
        arm.connect()
        assert arm.state is DeviceState.READY and arm._child.pid != child.pid
        assert math.dist(arm.pose().xyz, (0.050, 0.040, 0.010)) < 1e-6
    finally:
        arm.close()


def test_a_slow_dashboard_only_slows_connect_and_unlock(sims):
    """slow_reply_s = 0.3: every dashboard reply 0.3 s late, within ur_rtde's ~2.5 s. connect() asks the dashboard
    (robot mode, safety mode; ur_rtde's control interface its PolyScope version) and takes that much longer;
    a protective stop is unlocked as usual (FAULTED until connect() uploads the control script again)."""
    arm = ur_arm(sims["slow"].host, **FAST_TIMEOUTS)
    start = time.monotonic()
    arm.connect()
    assert time.monotonic() - start >= 3 * 0.3  # the knob is on: three dashboard replies at least
    try:
        arm.move_linear(Pose(0.050, 0.040, 0.010, 0.0))
        arm.trigger_protective_stop()
        assert arm.safety_mode() == "PROTECTIVE_STOP"
        arm.unlock_protective_stop()
        assert arm.state is DeviceState.FAULTED
        arm.connect()
        assert arm.safety_mode() == "NORMAL"
        arm.move_linear(Pose(0.060, 0.040, 0.010, 0.0))
        assert math.dist(arm.pose().xyz, (0.060, 0.040, 0.010)) < 1e-6
    finally:
        arm.close()


def _dashboard_says(host: str, request: bytes) -> str:
    with socket.create_connection((host, 29999), timeout=2.0) as sock:
        reader = sock.makefile("rb")
        reader.readline()
        sock.sendall(request + b"\n")
        return reader.readline().decode().strip()


def test_a_dashboard_reply_later_than_ur_rtde_waits_is_connection_lost(sims):
    """'unlock protective stop' answered 4 s late: ur_rtde's dashboard client gives up after ~2.5 s ('Operation
    canceled'), before the call's own time-out; unlock_protective_stop() raises ConnectionLost naming the request
    and the time-out (not a refusal), the arm is FAULTED (a late reply would pass for the next request's).
    The controller still unlocks when it gets round to it; connect() then goes on."""
    host = sims["slow_unlock"].host
    arm = ur_arm(host, **FAST_TIMEOUTS)
    arm.connect()
    try:
        arm.trigger_protective_stop()
        start = time.monotonic()
        with pytest.raises(ConnectionLost, match="did not answer 'unlock protective stop' in time.*call connect"):
            arm.unlock_protective_stop()
        assert time.monotonic() - start < arm._timeout_s  # ur_rtde's time-out, not the child's
        assert arm.state is DeviceState.FAULTED
        _until(lambda: _dashboard_says(host, b"safetymode") == "Safetymode: NORMAL",
               "the late unlock takes effect", timeout_s=10.0)
        arm.connect()
        arm.move_linear(Pose(0.050, 0.040, 0.010, 0.0))
    finally:
        arm.close()


def test_a_dashboard_slower_than_ur_rtde_waits_fails_connect_clearly(sims):
    arm = ur_arm(sims["slow_all"].host, **FAST_TIMEOUTS)
    start = time.monotonic()
    with pytest.raises(ConnectionLost, match=r"cannot connect to the UR controller at 127\.0\.0\.18, at the "
                                             r"dashboard \(port 29999\): .*about 2\.5 s"):
        arm.connect()
    assert time.monotonic() - start < 20  # bounded: ur_rtde's dashboard time-out, not a hang
    assert arm.state is DeviceState.CREATED
