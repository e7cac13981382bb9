"""Robotiq EPick driver against its protocol simulator (RTU on a socat pty pair and RTU over TCP): the Gripper
contract over both transports, gripping a sphere in the world, and link faults."""

from __future__ import annotations

import time

import pytest

from drivers.grippers.epick_registers import (
    OBJ_NONE,
    VAS_GRIPPING,
    decode_status,
)
from drivers.grippers.modbus_link import ModbusReplyError, NoReply
from drivers.interfaces import (
    ConnectionLost,
    DeviceError,
    DeviceState,
    NotConnected,
    VacuumLost,
)
from drivers.sim.servers.epick import EPickServer

from tests.support.contract import GripperContract, assert_faulted_until_connect
from tests.support.grippers import (
    put_nozzle_on_a_sphere,
    serial_driver,
    served_driver,
    tcp_driver,
    wait_for_vacuum_lost,
)
from tests.support.wait import eventually

# -- the contract, over both transports -------------------------------------------


class TestEPickOverTcp(GripperContract):
    """On the TCP simulator (the module's make_device)."""


class TestEPickOverPty(GripperContract):
    @pytest.fixture
    def make_device(self, serial_server, pty_pair):
        return lambda: serial_driver(pty_pair[0])


# -- gripping a sphere in the world -----------------------------------------------






@pytest.mark.parametrize("transport", ["tcp", "serial"])
def test_grips_the_sphere_under_the_nozzle_then_reports_its_loss(world, sim_gripper, pty_pair, transport):
    put_nozzle_on_a_sphere(world)
    server, gripper = served_driver(transport, sim_gripper, pty_pair)
    try:
        gripper.connect()
        assert gripper.grip() is True
        assert world.held is not None
        status = gripper.status()
        assert status.object_detected and status.gripping
        assert status.vacuum_kpa >= gripper.settings.detect_vacuum_kpa
        assert server.drop_object() is True  # the held sphere falls
        assert world.held is None
        wait_for_vacuum_lost(gripper)
        assert not gripper.status().object_detected  # reported once, then plain status
        gripper.release()
    finally:
        gripper.close()
        server.close()


def test_release_puts_the_sphere_down_and_reports_an_earlier_loss(world, sim_gripper, tcp_server, gripper):
    put_nozzle_on_a_sphere(world)
    assert gripper.grip() is True
    gripper.release()
    assert world.held is None
    assert gripper.status().vacuum_kpa <= gripper.settings.release_vacuum_kpa
    assert gripper.grip() is True  # the sphere lies where it was put down, still under the nozzle
    tcp_server.drop_object()
    # the simulated vacuum collapses (seen on the server side, not by the driver)
    eventually(lambda: decode_status(tcp_server.model.status_registers(time.monotonic())).object == OBJ_NONE,
               timeout=2.0, every=0.01, what="the simulated vacuum collapsed")
    with pytest.raises(VacuumLost):
        gripper.release()  # the release is done, then the loss is reported
    assert gripper.read_status().actuator != VAS_GRIPPING


def test_active_release_blows_off(world, sim_gripper, tcp_server):
    put_nozzle_on_a_sphere(world)
    gripper = tcp_driver(tcp_server, release="active", active_release_kpa=15)
    gripper.connect()
    try:
        assert gripper.grip() is True
        gripper.release()
        status = gripper.read_status()
        assert status.pressure_request_kpa == 115
        assert world.held is None
    finally:
        gripper.close()


def test_gripper_fault_is_a_clear_error(tcp_server, gripper):
    tcp_server.inject_fault(0x8)
    with pytest.raises(DeviceError, match="temperature"):
        gripper.grip()
    tcp_server.inject_fault(0)
    assert gripper.grip() is False


def test_status_block_answers_fc03_and_fc04_alike(tcp_server, gripper):
    by_input = gripper.link.read(0x07D0, 3, function=4)
    by_holding = gripper.link.read(0x07D0, 3, function=3)
    assert by_input == by_holding
    assert decode_status(by_holding).operational


# -- link faults, against the simulator -------------------------------------------


def test_exception_response_is_a_clear_error(tcp_server, gripper):
    with pytest.raises(ModbusReplyError, match=r"exception 3 \(illegal data value\)"):
        gripper.link.write(0x03E8, [0x0500, 0x0064, 0x0A50])  # rMOD 2 is reserved
    with pytest.raises(ModbusReplyError, match=r"exception 2 \(illegal data address\)"):
        gripper.link.write(0x07D0, [0, 0, 0])  # the status block is read only
    assert gripper.state is DeviceState.READY
    gripper.status()


@pytest.mark.parametrize("transport", ["tcp", "serial"])
def test_malformed_reply_is_a_clear_error(sim_gripper, pty_pair, transport):
    server, gripper = served_driver(transport, sim_gripper, pty_pair, timeout_s=0.1)
    try:
        gripper.connect()
        server.faults.malformed_replies = True
        started = time.monotonic()
        with pytest.raises(ModbusReplyError, match=r"malformed reply to the FC04 read .* got 09 04 06 "):
            gripper.status()
        assert time.monotonic() - started < 2.0
        assert gripper.state is DeviceState.READY  # the link itself still works
        server.faults.malformed_replies = False
        assert gripper.status().vacuum_kpa == 0.0
    finally:
        gripper.close()
        server.close()


def test_slow_reply_times_out_faults_and_reconnects_cleanly(tcp_server):
    gripper = tcp_driver(tcp_server, timeout_s=0.1, retries=1)
    gripper.connect()
    tcp_server.faults.reply_delay_s = 0.5
    started = time.monotonic()
    with pytest.raises(NoReply, match=r"no reply .* within 0.1 s \(2 attempts\)"):
        gripper.status()
    assert time.monotonic() - started < 1.0
    assert gripper.state is DeviceState.FAULTED
    with pytest.raises(ConnectionLost, match="connect"):
        gripper.status()
    tcp_server.faults.reply_delay_s = 0.0
    gripper.connect()  # an operator action; never done by the driver itself
    assert gripper.state is DeviceState.READY
    assert gripper.status().vacuum_kpa == 0.0
    gripper.close()


@pytest.mark.parametrize("transport", ["tcp", "serial"])
def test_dropped_link_faults_until_connect(sim_gripper, pty_pair, transport):
    server, gripper = served_driver(transport, sim_gripper, pty_pair)
    try:
        gripper.connect()
        server.messages_on_connection = 0
        server.faults.drop_after_messages = 2
        gripper.status()
        gripper.status()
        with pytest.raises(ConnectionLost):
            gripper.status()
        assert_faulted_until_connect(gripper, server.faults)
    finally:
        gripper.close()
        server.close()


def test_simulator_on_a_missing_serial_device_is_an_os_error_naming_it(sim_gripper, tmp_path):
    missing = str(tmp_path / "no-such-tty")
    with pytest.raises(OSError, match=rf"Modbus simulator \(serial\) could not start on {missing}"):
        EPickServer(sim_gripper, kind="serial", serial_port=missing).start()
    with pytest.raises(ValueError, match=r"device_id 0: a Modbus RTU device has an id 1..247 \(0 is the broadcast\)"):
        EPickServer(sim_gripper, device_id=0)


def test_cannot_open_a_missing_port(tmp_path):
    gripper = serial_driver(str(tmp_path / "no-such-tty"))
    with pytest.raises(ConnectionLost, match="no-such-tty"):
        gripper.connect()
    assert gripper.state is DeviceState.CREATED
    with pytest.raises(NotConnected, match="connect"):
        gripper.status()
