"""`cellctl sim`: a protocol simulator on its own, for commissioning a driver by hand."""

from __future__ import annotations

import math
import os
import re
import signal
import socket
import subprocess
import sys

import pytest

from drivers.arms.abb import AbbArm
from drivers.grippers.epick import EPickGripper
from drivers.interfaces import Pose

from cellctl.cli import main

from tests.conftest import MICROCELL, ROOT
from tests.support.ports import free_ports

LIMITS = {"x_mm": [-10, 160], "y_mm": [-10, 110], "z_mm": [-5, 40], "alpha_deg": [-360, 360]}


def test_abb_simulator_serves_a_driver_and_stops_cleanly_on_sigterm():
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "sim", "abb", "--config", str(MICROCELL),
                             "--port", "0"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        banner = proc.stdout.readline()
        found = re.search(r"serving on 127\.0\.0\.1:(\d+) \(logger (\d+)\)", banner)
        assert found, banner
        arm = AbbArm.create("arm", {"host": "127.0.0.1", "motion_port": int(found[1]),
                                    "logger_port": int(found[2]), "limits": LIMITS})
        arm.connect()
        try:
            arm.move_linear(Pose(0.050, 0.040, 0.010, 0.3))
            pose = arm.pose()
            assert (pose.x, pose.y, pose.z) == pytest.approx((0.050, 0.040, 0.010), abs=1e-6)
            assert pose.alpha == pytest.approx(0.3, abs=1e-4)
        finally:
            arm.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert "stopped" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_epick_simulator_on_a_serial_port(pty_pair):
    driver_end, sim_end = pty_pair
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "sim", "epick", "--config", str(MICROCELL),
                             "--serial", sim_end], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert f"serving on {sim_end}" in proc.stdout.readline()
        gripper = EPickGripper.create("gripper", {"transport": "serial", "serial_port": driver_end})
        gripper.connect()  # activates the gripper over RTU: the simulator answered
        try:
            assert gripper.grip() is False  # nothing under the nozzle: no object detected
            assert gripper.status().object_detected is False
        finally:
            gripper.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_bad_simulator_input_exits_2_naming_what_is_allowed(tmp_path, capsys):
    assert main(["sim", "vgc10", "--config", str(MICROCELL), "--port", "0", "--option", "bogus=1"]) == 2
    err = capsys.readouterr().err
    assert "unknown Modbus simulator option(s) ['bogus']" in err and "reply_delay_s" in err
    assert main(["sim", "abb", "--config", str(MICROCELL), "--port", "70000"]) == 2
    assert "--port 70000: expected 1..65535" in capsys.readouterr().err
    real = tmp_path / "real.yaml"
    real.write_text("cell: {name: real}\narm: {backend: abb, host: 10.0.0.5, limits: %s}\n"
                    "operator: {backend: console}\ncameras: {top: {backend: uvc, source: 0}}\nareas: {}\n" % LIMITS)
    assert main(["sim", "abb", "--config", str(real)]) == 2
    assert "no 'sim:' section" in capsys.readouterr().err
    assert main(["sim", "camera-files", "--config", str(MICROCELL), "--out", str(tmp_path), "--camera", "cam9"]) == 2
    assert "--camera 'cam9': not a camera of the sim section; allowed: cam1, cam2, cam3" in capsys.readouterr().err


def test_camera_files_writes_the_frames(tmp_path, capsys):
    assert main(["sim", "camera-files", "--config", str(MICROCELL), "--out", str(tmp_path / "frames"),
                 "--camera", "cam2", "--frames", "2"]) == 0
    assert "2 frames of cam2" in capsys.readouterr().out
    assert len(list((tmp_path / "frames").rglob("*.png"))) == 2


def _released(host: str, port: int) -> bool:
    """A new server can listen there (as the simulator did: SO_REUSEADDR, so TIME_WAIT does not count)."""
    try:
        socket.create_server((host, port)).close()
        return True
    except OSError:
        return False


def test_ur_simulator_serves_unmodified_ur_rtde_and_stops_cleanly_on_sigterm():
    """`cellctl sim ur --host 127.0.0.13` (ports fixed as on a UR; other tests use .2-.12): the stock
    RTDEReceiveInterface reads the simulated arm's pose; SIGTERM ends it with status 0, every port free."""
    rtde_receive = pytest.importorskip("rtde_receive")
    host = "127.0.0.13"
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "sim", "ur", "--config", str(MICROCELL),
                             "--host", host], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        banner = proc.stdout.readline()
        assert f"serving on {host} (dashboard 29999, primary 30001, secondary 30002, script 30003, RTDE 30004)" \
            in banner, banner
        for port in (30001, 30002):  # the primary and secondary interfaces greet with the version message
            with socket.create_connection((host, port), timeout=2.0) as sock:
                assert sock.recv(10, socket.MSG_WAITALL) == bytes.fromhex("00000037140000000000")
        receive = rtde_receive.RTDEReceiveInterface(host)
        try:
            pose = receive.getActualTCPPose()
            assert len(pose) == 6 and all(math.isfinite(v) for v in pose)
            assert math.hypot(*pose[3:]) == pytest.approx(math.pi, abs=1e-6)  # tool down: a half turn
            assert receive.getRobotMode() == 7  # RUNNING
        finally:
            receive.disconnect()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
        assert "stopped" in proc.stdout.read()
        for port in (29999, 30001, 30002, 30003, 30004):
            assert _released(host, port), port
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_vgc10_simulator_answers_a_plain_modbus_client_and_stops_cleanly_on_sigterm():
    """`cellctl sim vgc10 --port P`: pymodbus' ModbusTcpClient, unit 65, reads the control registers (both
    channels released, current limit 500 mA) and channel A's vacuum; SIGTERM: status 0 and P free again."""
    from pymodbus.client import ModbusTcpClient

    port = free_ports()[0]
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "sim", "vgc10", "--config", str(MICROCELL),
                             "--port", str(port)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        banner = proc.stdout.readline()
        assert f"serving on 127.0.0.1:{port}" in banner, banner
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        assert client.connect()
        try:
            control = client.read_holding_registers(0, count=3, device_id=65)
            assert not control.isError(), control
            assert control.registers == [0, 0, 500]
            vacuum = client.read_holding_registers(258, count=1, device_id=65)
            assert not vacuum.isError() and vacuum.registers[0] < 100  # released: under 10 % vacuum
        finally:
            client.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert "stopped" in proc.stdout.read()
        assert _released("127.0.0.1", port)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_abb_simulator_logger_port_can_be_chosen():
    """--logger-port Q: the banner names Q, the ABB driver reads its pose stream there; bad values exit 2."""
    logger = free_ports()[0]
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "sim", "abb", "--config", str(MICROCELL),
                             "--port", "0", "--logger-port", str(logger)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        banner = proc.stdout.readline()
        found = re.search(r"serving on 127\.0\.0\.1:(\d+) \(logger (\d+)\)", banner)
        assert found and int(found[2]) == logger, banner
        arm = AbbArm.create("arm", {"host": "127.0.0.1", "motion_port": int(found[1]), "logger_port": logger,
                                    "limits": LIMITS})
        arm.connect()
        try:
            arm.move_linear(Pose(0.050, 0.040, 0.010, 0.0))
            assert (arm.pose().x, arm.pose().y) == pytest.approx((0.050, 0.040), abs=1e-6)
        finally:
            arm.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert _released("127.0.0.1", logger)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_abb_logger_port_errors_exit_2(capsys):
    assert main(["sim", "abb", "--config", str(MICROCELL), "--port", "5000", "--logger-port", "70000"]) == 2
    assert "--logger-port 70000: expected 1..65535" in capsys.readouterr().err
    assert main(["sim", "abb", "--config", str(MICROCELL), "--port", "5000", "--logger-port", "5000"]) == 2
    assert "the same as --port" in capsys.readouterr().err


@pytest.mark.parametrize(("protocol", "port", "says"), [
    ("abb", ["--port", "0"], "unknown ABB simulator option(s) ['nonsense']; allowed: ['drop_after_messages'"),
    ("ur", [], "unknown UR simulator option 'nonsense'; allowed: version, serial_number, robot_model"),
    ("epick", ["--port", "0"], "unknown Modbus simulator option(s) ['nonsense']; allowed: ['activation_s'"),
    ("vgc10", ["--port", "0"], "unknown Modbus simulator option(s) ['nonsense']; allowed: "),
])
def test_every_simulator_refuses_an_unknown_option_listing_the_allowed_ones(protocol, port, says, capsys):
    """`cellctl sim P --option nonsense=1`: exit 2, no traceback, the allowed options named (the help says so)."""
    host = ["--host", "127.0.0.19"] if protocol == "ur" else []
    before = signal.getsignal(signal.SIGINT)  # Python's, or one a library imported earlier in this process set
    assert main(["sim", protocol, "--config", str(MICROCELL), *port, *host, "--option", "nonsense=1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cellctl: error: {protocol} simulator: ") and says in err, err
    assert "Traceback" not in err
    assert signal.getsignal(signal.SIGINT) is before  # the command's handlers are gone again


@pytest.mark.parametrize(("protocol", "option", "says"), [
    ("abb", "reply_delay_s=abc", "reply_delay_s='abc': seconds, 0 to 60"),
    ("abb", "drop_after_messages=0", "drop_after_messages=0: a whole number of messages >= 1, or none"),
    ("abb", "protective_stop_mid_move=x", "protective_stop_mid_move='x': the fraction of the move's way"),
    ("epick", "reply_delay_s=-1", "reply_delay_s=-1: seconds, 0 to 60"),
    ("vgc10", "malformed_replies=3", "malformed_replies=3: true or false"),
    ("vgc10", "drop_after_messages=[1, 2]", "drop_after_messages=[1, 2]: a whole number of messages >= 1"),
])
def test_every_simulator_refuses_a_knob_value_that_cannot_work(protocol, option, says, capsys):
    assert main(["sim", protocol, "--config", str(MICROCELL), "--port", "0", "--option", option]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cellctl: error: {protocol} simulator: ") and says in err, err
    assert "Traceback" not in err


def test_ur_simulator_option_errors_name_the_option_and_the_fault_knobs(capsys):
    assert main(["sim", "ur", "--config", str(MICROCELL), "--host", "127.0.0.19", "--option", "slow_reply_s=abc",
                 "--option", "version=[5, 15]"]) == 2
    err = capsys.readouterr().err
    assert "UR simulator option faults.slow_reply_s='abc': Input should be a valid number" in err, err
    assert "UR simulator option version=[5, 15]" in err, err
    assert "fault knobs: drop_after_commands, outage_s, protective_stop_after_moves, slow_reply_s" in err, err


def test_ur_simulator_on_a_taken_address_exits_2_saying_so(capsys):
    """Another controller (here an in-process simulator) holds 127.0.0.19's UR ports: the child simulator cannot
    listen, and `cellctl sim ur` says which port and what to do, exit 2."""
    from drivers.sim.servers.ur import UrSimulator

    class StandingArm:
        def move_linear(self, target, speed=None):
            pass

        def pose(self):
            return Pose(0.05, 0.04, 0.01, 0.0)

        def stop(self):
            pass

    with UrSimulator(StandingArm(), "127.0.0.19"):
        assert main(["sim", "ur", "--config", str(MICROCELL), "--host", "127.0.0.19"]) == 2
    err = capsys.readouterr().err
    assert f"ur simulator: port 29999 on 127.0.0.19 is in use by pid {os.getpid()} (" in err, err
    assert "pick another --host (its ports are fixed)" in err, err
