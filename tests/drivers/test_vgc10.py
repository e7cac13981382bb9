"""OnRobot VGC10 driver against its Modbus TCP simulator, against a scripted peer (exact bytes), and its registers."""

from __future__ import annotations

import socket
import time

import pytest
from pydantic import ValidationError

from drivers.grippers.modbus_link import ModbusReplyError, NoReply
from drivers.grippers.vgc10 import Vgc10Gripper
from drivers.grippers.vgc10_registers import (
    MODE_GRIP,
    decode_control,
    encode_control,
    encode_vacuum,
    vacuum_kpa,
    vacuum_percent,
)
from drivers.interfaces import ConnectionLost, DeviceState, NotConnected, VacuumLost
from drivers.sim.servers import connect_when_up
from drivers.sim.servers.vgc10 import Vgc10Server

from tests.support.contract import GripperContract, assert_faulted_until_connect
from tests.support.grippers import FAST, h, put_nozzle_on_a_sphere, wait_for_vacuum_lost
from tests.support.ports import free_ports
from tests.support.wire import WirePeer


@pytest.fixture
def server(sim_gripper):
    with Vgc10Server(sim_gripper) as server:
        yield server


def driver(server, **options) -> Vgc10Gripper:
    return Vgc10Gripper.create("vgc10", {"host": "127.0.0.1", "port": server.port, **FAST, **options})


@pytest.fixture
def make_device(server):
    """Drivers on the simulator, both channels: for the contract and conftest's connected `gripper`."""
    return lambda: driver(server)


class TestVgc10(GripperContract):
    """Both channels (the module's make_device)."""


class TestVgc10ChannelA(GripperContract):
    @pytest.fixture
    def make_device(self, server):
        return lambda: driver(server, channel="A")


@pytest.mark.parametrize("channel", ["both", "B"])
def test_grips_the_sphere_under_the_nozzle_then_reports_its_loss(world, server, channel):
    put_nozzle_on_a_sphere(world)
    gripper = driver(server, channel=channel, vacuum_percent=70, detect_vacuum_percent=30)
    gripper.connect()
    try:
        assert gripper.grip() is True
        assert world.held is not None
        status = gripper.status()
        assert status.object_detected and status.gripping
        assert status.vacuum_kpa >= 30 * 1.01325
        channels = gripper.read_channels()
        working = ["A", "B"] if channel == "both" else ["B"]
        for name in working:
            assert channels[name]["mode"] == "grip" and channels[name]["target_percent"] == 70
        for name in {"A", "B"} - set(working):
            assert channels[name]["mode"] == "release" and channels[name]["vacuum_percent"] == 0.0
        assert server.drop_object() is True
        wait_for_vacuum_lost(gripper)
        assert not gripper.status().object_detected
        gripper.release()
        assert not gripper.status().gripping
    finally:
        gripper.close()


def test_release_puts_the_sphere_down_and_idle_stops_the_pump(world, server, gripper):
    put_nozzle_on_a_sphere(world)
    assert gripper.grip() is True
    gripper.idle()
    assert world.held is not None  # valves closed: the part stays on
    assert {c["mode"] for c in gripper.read_channels().values()} == {"idle"}
    gripper.release()
    assert world.held is None
    assert gripper.status().vacuum_kpa <= 2.0 * 1.01325


def test_malformed_slow_and_dropped_replies(server):
    gripper = driver(server, timeout_s=0.1)
    gripper.connect()
    try:
        server.faults.malformed_replies = True
        with pytest.raises(ModbusReplyError, match="malformed reply .* not a valid Modbus TCP reply"):
            gripper.status()
        server.faults.malformed_replies = False
        assert gripper.state is DeviceState.READY
        gripper.status()

        server.faults.reply_delay_s = 0.4
        started = time.monotonic()
        with pytest.raises(NoReply, match="within 0.1 s"):
            gripper.status()
        assert time.monotonic() - started < 1.0
        assert gripper.state is DeviceState.FAULTED
        server.faults.reply_delay_s = 0.0
        gripper.connect()
        gripper.status()

        server.messages_on_connection = 0
        server.faults.drop_after_messages = 1
        with pytest.raises(ConnectionLost, match="dropped|closed"):
            gripper.status()  # two reads: the second finds the connection gone
        assert_faulted_until_connect(gripper, server.faults)
    finally:
        gripper.close()


def test_exception_response_is_a_clear_error(server, gripper):
    with pytest.raises(ModbusReplyError, match=r"exception 3 \(illegal data value\)"):
        gripper.link.write(0, [0x0300])  # mode 3 does not exist
    with pytest.raises(ModbusReplyError, match=r"exception 2 \(illegal data address\)"):
        gripper.link.write(258, [0])  # actual vacuum is read only
    with pytest.raises(ModbusReplyError, match=r"exception 2"):
        gripper.link.read(100, 1)


def test_wrong_unit_is_refused_clearly(server):
    gripper = driver(server, device_id=66)
    with pytest.raises(ModbusReplyError, match="device 66 answered"):
        gripper.connect()
    assert gripper.state is DeviceState.CREATED
    with pytest.raises(NotConnected):
        gripper.status()


def test_wire_exchanges_for_grip_and_status():
    # Modbus TCP: transaction id, protocol 0, length, unit 65 (0x41), then the PDU
    peer = WirePeer([
        (h("00 01 00 00 00 06 41 03 00 00 00 02"), h("00 01 00 00 00 07 41 03 04 00 00 00 00")),  # connect: modes
        (h("00 02 00 00 00 06 41 03 01 02 00 02"), h("00 02 00 00 00 07 41 03 04 00 00 00 00")),  # and vacuum
        (h("00 03 00 00 00 0B 41 10 00 00 00 02 04 01 3C 01 3C"), h("00 03 00 00 00 06 41 10 00 00 00 02")),  # grip 60 %
        (h("00 04 00 00 00 06 41 03 00 00 00 02"), h("00 04 00 00 00 07 41 03 04 01 3C 01 3C")),
        (h("00 05 00 00 00 06 41 03 01 02 00 02"), h("00 05 00 00 00 07 41 03 04 02 58 02 4E")),  # 60.0 %, 59.0 %
        (h("00 06 00 00 00 06 41 03 00 00 00 02"), h("00 06 00 00 00 07 41 03 04 01 3C 01 3C")),
        (h("00 07 00 00 00 06 41 03 01 02 00 02"), h("00 07 00 00 00 07 41 03 04 01 2C 02 58")),  # 30.0 %, 60.0 %
    ])
    gripper = Vgc10Gripper.create("vgc10", {"host": "127.0.0.1", "port": peer.port, **FAST})
    try:
        gripper.connect()
        assert gripper.grip() is True
        status = gripper.status()
        assert status.vacuum_kpa == pytest.approx(30.0 * 1.01325)  # the weaker channel
        assert status.object_detected and status.gripping
    finally:
        gripper.close()
        peer.close()
    assert peer.errors == []


def test_scripted_lost_vacuum_is_reported_once():
    held = (h("00 04 00 00 00 06 41 03 00 00 00 02"), h("00 04 00 00 00 07 41 03 04 01 3C 01 3C"))
    peer = WirePeer([
        (h("00 01 00 00 00 06 41 03 00 00 00 02"), h("00 01 00 00 00 07 41 03 04 00 00 00 00")),
        (h("00 02 00 00 00 06 41 03 01 02 00 02"), h("00 02 00 00 00 07 41 03 04 00 00 00 00")),
        (h("00 03 00 00 00 09 41 10 00 00 00 01 02 01 3C"), h("00 03 00 00 00 06 41 10 00 00 00 01")),  # channel A only
        held,
        (h("00 05 00 00 00 06 41 03 01 02 00 02"), h("00 05 00 00 00 07 41 03 04 02 58 00 00")),
        (h("00 06 00 00 00 06 41 03 00 00 00 02"), h("00 06 00 00 00 07 41 03 04 01 3C 00 00")),
        (h("00 07 00 00 00 06 41 03 01 02 00 02"), h("00 07 00 00 00 07 41 03 04 00 0F 00 00")),  # 1.5 %: lost
    ])
    gripper = Vgc10Gripper.create("vgc10", {"host": "127.0.0.1", "port": peer.port, "channel": "A", **FAST})
    try:
        gripper.connect()
        assert gripper.grip() is True
        with pytest.raises(VacuumLost, match=r"vacuum 1.5 %"):
            gripper.status()
    finally:
        gripper.close()
        peer.close()
    assert peer.errors == []


# -- what the device documents, in exact bytes (Modbus TCP: transaction, protocol 0, length, unit 65) --------


def _exchange(sock, request: str) -> str:
    sock.sendall(h(request))
    return sock.recv(256).hex(" ").upper()


def test_simulator_refuses_undocumented_function_codes_with_exception_1(server):
    """The VG10 / VGC10 documents FC 3, 6, 16 and 23; anything else is an illegal function (exception 1),
    whatever the address: FC 4 (read input registers) finds no input registers to read."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=2.0) as sock:
        assert _exchange(sock, "00 01 00 00 00 06 41 04 01 02 00 02") == "00 01 00 00 00 03 41 84 01"  # FC4 at 258
        assert _exchange(sock, "00 02 00 00 00 06 41 04 27 10 00 01") == "00 02 00 00 00 03 41 84 01"  # FC4, no register
        assert _exchange(sock, "00 03 00 00 00 06 41 01 00 00 00 01") == "00 03 00 00 00 03 41 81 01"  # FC1 coils
        assert _exchange(sock, "00 04 00 00 00 06 41 05 00 00 FF 00") == "00 04 00 00 00 03 41 85 01"  # FC5 coil
        assert _exchange(sock, "00 05 00 00 00 06 41 03 01 02 00 02") == "00 05 00 00 00 07 41 03 04 00 00 00 00"  # FC3
        assert _exchange(sock, "00 06 00 00 00 0D 41 17 01 02 00 02 00 00 00 01 02 00 00") == \
            "00 06 00 00 00 07 41 17 04 00 00 00 00"  # FC23: write A = release, read the vacuum


def test_simulator_regulates_a_target_above_80_percent_at_80(world, server):
    """OnRobot: the target vacuum "should never exceed 80"; the gripper takes a larger one without an exception
    (public drivers command 255) and regulates at most 80 %: the write is echoed, the register reads back what
    was written, the vacuum settles at 800 per mille, not 1000."""
    put_nozzle_on_a_sphere(world)
    server.model.tau_s = 0.02
    with socket.create_connection(("127.0.0.1", server.port), timeout=2.0) as sock:
        assert _exchange(sock, "00 01 00 00 00 06 41 06 00 00 01 64") == "00 01 00 00 00 06 41 06 00 00 01 64"  # grip 100 %
        assert world.held is not None
        time.sleep(0.3)  # 15 time constants
        assert _exchange(sock, "00 02 00 00 00 06 41 03 00 00 00 01") == "00 02 00 00 00 05 41 03 02 01 64"
        assert _exchange(sock, "00 03 00 00 00 06 41 03 01 02 00 02") == "00 03 00 00 00 07 41 03 04 03 20 00 00"
        assert _exchange(sock, "00 04 00 00 00 06 41 06 00 00 01 FF") == "00 04 00 00 00 06 41 06 00 00 01 FF"  # 255 %
        time.sleep(0.3)
        assert _exchange(sock, "00 05 00 00 00 06 41 03 01 02 00 02") == "00 05 00 00 00 07 41 03 04 03 20 00 00"
        assert _exchange(sock, "00 06 00 00 00 06 41 06 00 00 00 00") == "00 06 00 00 00 06 41 06 00 00 00 00"  # release


def test_driver_never_sends_a_target_above_80_percent():
    peer = WirePeer([
        (h("00 01 00 00 00 06 41 03 00 00 00 02"), h("00 01 00 00 00 07 41 03 04 00 00 00 00")),
        (h("00 02 00 00 00 06 41 03 01 02 00 02"), h("00 02 00 00 00 07 41 03 04 00 00 00 00")),
        (h("00 03 00 00 00 0B 41 10 00 00 00 02 04 01 50 01 50"), h("00 03 00 00 00 06 41 10 00 00 00 02")),  # 80 %
        (h("00 04 00 00 00 06 41 03 00 00 00 02"), h("00 04 00 00 00 07 41 03 04 01 50 01 50")),
        (h("00 05 00 00 00 06 41 03 01 02 00 02"), h("00 05 00 00 00 07 41 03 04 03 20 03 20")),
    ])
    gripper = Vgc10Gripper.create("vgc10", {"host": "127.0.0.1", "port": peer.port, **FAST, "vacuum_percent": 80,
                                            "detect_vacuum_percent": 80})
    try:
        gripper.connect()
        assert gripper.grip() is True
    finally:
        gripper.close()
        peer.close()
    assert peer.errors == []


def test_bad_settings_name_the_field_and_allowed_values():
    with pytest.raises(ValidationError, match=r"channel\n.*'A', 'B' or 'both'"):
        Vgc10Gripper.create("vgc10", {"channel": "C"})
    with pytest.raises(ValidationError, match=r"vacuum_percent: 95 is above 80 %, the most vacuum the VGC10 regulates "
                                              r"to .* allowed: 1..80. Nothing was sent"):
        Vgc10Gripper.create("vgc10", {"vacuum_percent": 95})
    with pytest.raises(ValidationError, match=r"detect_vacuum_percent: 85.0 is above 80 %"):
        Vgc10Gripper.create("vgc10", {"detect_vacuum_percent": 85.0})
    with pytest.raises(ValidationError, match="detect_vacuum_percent .* must not exceed vacuum_percent"):
        Vgc10Gripper.create("vgc10", {"vacuum_percent": 30, "detect_vacuum_percent": 40})


def test_registers():
    assert encode_control(MODE_GRIP, 60) == 0x013C
    assert decode_control(0x023C) == (2, 60)
    assert encode_control(0) == 0
    with pytest.raises(ValueError, match="mode must be one of"):
        encode_control(3, 10)
    with pytest.raises(ValueError, match=r"0..80 % \(the gripper regulates at most 80 %\), got 255; nothing was sent"):
        encode_control(MODE_GRIP, 255)
    assert vacuum_percent(600) == 60.0
    assert vacuum_kpa(800) == pytest.approx(81.06)
    assert encode_vacuum(59.96) == 600 and encode_vacuum(150) == 1000 and encode_vacuum(-1) == 0


def test_serve_runs_until_stopped_and_rejects_unknown_options(microcell_sim):
    import threading

    from drivers.sim.servers import vgc10 as vgc10_server

    with pytest.raises(ValueError, match=r"unknown Modbus simulator option\(s\) \['bogus'\]; allowed: .*drop_after_messages"):
        vgc10_server.serve(microcell_sim, port=0, options={"bogus": 1})
    port, = free_ports()
    stop = threading.Event()
    thread = threading.Thread(target=vgc10_server.serve, args=(microcell_sim,),
                              kwargs={"port": port, "stop": stop, "options": {"tau_s": 0.05}}, daemon=True)
    thread.start()
    gripper = Vgc10Gripper.create("vgc10", {"host": "127.0.0.1", "port": port, **FAST})
    connect_when_up(gripper, timeout_s=5.0)
    try:
        assert gripper.grip() is False  # nothing under the nozzle at home
    finally:
        gripper.close()
        stop.set()
        thread.join(5.0)
    assert not thread.is_alive()
