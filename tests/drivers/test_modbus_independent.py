"""The gripper simulators driven by a plain pymodbus client, from /work/shared/PROTOCOLS.md's register maps.

Nothing of drivers/grippers is used: the registers are packed and unpacked here by hand, so the
simulators are checked against a second reading of the maps by a client that is not ours
(pymodbus 3.16: `ModbusTcpClient`, `framer=FramerType.RTU` for RTU over TCP, `ModbusSerialClient`
on a socat pty, `device_id=`). The EPick is activated, grips the sphere under the nozzle and
releases it; it answers only its own device id and executes a broadcast (id 0) write without
answering it. The VGC10 grips on channel A, and its actual vacuum is read at 258/259 and at 18/19;
it answers only the function codes it documents (3, 6, 16, 23), and regulates a target above
80 % at 80 %.
"""

from __future__ import annotations

import time

import pytest
from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusIOException

from drivers.sim.servers.epick import EPickServer
from drivers.sim.servers.vgc10 import Vgc10Server

from tests.support.grippers import put_nozzle_on_a_sphere
from tests.support.wait import eventually

EPICK_ID, EPICK_COMMAND, EPICK_STATUS = 9, 0x03E8, 0x07D0
VGC10_UNIT = 65


def _until(read, done, what: str, timeout_s: float = 5.0):
    """`read()` until `done(value)` (the EPick takes at most one request per 5 ms: one every 10 ms)."""
    return eventually(lambda: (value,) if done(value := read()) else None, timeout=timeout_s, every=0.01, what=what)[0]


def _ok(response):
    assert not response.isError(), f"Modbus error response: {response}"
    return response


# --- Robotiq EPick: Modbus RTU, device 9 ----------------------------------------------------------


def _epick_status(client, function_code: int = 4) -> dict:
    """The status block at 0x07D0, field by field (FC04 or FC03: the gripper answers both)."""
    read = client.read_input_registers if function_code == 4 else client.read_holding_registers
    r = _ok(read(EPICK_STATUS, count=3, device_id=EPICK_ID)).registers
    high = r[0] >> 8
    return {"gACT": high & 1, "gMOD": high >> 1 & 3, "gGTO": high >> 3 & 1, "gSTA": high >> 4 & 3,
            "gOBJ": high >> 6 & 3, "gVAS": r[0] & 3, "gFLT": r[1] >> 8 & 0x0F, "gPR": r[1] & 0xFF, "gPO": r[2] >> 8}


def _epick_command(activate: bool, regulate: bool = False, pressure_kpa: int = 100, timeout_ticks: int = 0,
                   min_kpa: int = 100, advanced: bool = True) -> list[int]:
    action = int(activate) | int(advanced) << 1 | int(regulate) << 3
    return [action << 8, pressure_kpa, timeout_ticks << 8 | min_kpa]


@pytest.fixture(params=["rtu-over-tcp", "pty"])
def epick(request, world, sim_gripper):
    """(plain pymodbus client, raw frames it received, the simulator) over each RTU transport."""
    received: list[bytes] = []

    def trace(sending: bool, data: bytes) -> bytes:
        if not sending:
            received.append(bytes(data))
        return data

    if request.param == "pty":
        driver_end, sim_end = request.getfixturevalue("pty_pair")  # skips without socat
        server = EPickServer(sim_gripper, kind="serial", serial_port=sim_end)
        client = ModbusSerialClient(driver_end, framer=FramerType.RTU, baudrate=115200, bytesize=8, parity="N",
                                    stopbits=1, timeout=0.5, retries=1, trace_packet=trace)
    else:
        server = EPickServer(sim_gripper, kind="rtu-over-tcp")
        client = None
    with server:
        if client is None:
            client = ModbusTcpClient("127.0.0.1", port=server.port, framer=FramerType.RTU, timeout=0.5, retries=1,
                                     trace_packet=trace)
        assert client.connect(), f"pymodbus could not connect to the EPick simulator at {server.where}"
        try:
            yield client, received, server
        finally:
            client.close()


def test_epick_activates_grips_and_releases_for_a_plain_pymodbus_client(epick, world):
    client, received, _ = epick
    put_nozzle_on_a_sphere(world)
    _ok(client.write_registers(EPICK_COMMAND, _epick_command(activate=False), device_id=EPICK_ID))  # reset
    received.clear()
    reply = _ok(client.write_registers(EPICK_COMMAND, _epick_command(activate=True), device_id=EPICK_ID))
    assert (reply.address, reply.count) == (EPICK_COMMAND, 3)
    assert b"".join(received) == bytes.fromhex("09 10 03 E8 00 03 01 30")  # the manual's activation reply
    status = _until(lambda: _epick_status(client), lambda s: s["gSTA"] == 3, "activation (gSTA 3)")
    assert (status["gACT"], status["gGTO"], status["gFLT"]) == (1, 0, 0)

    grip = _epick_command(activate=True, regulate=True, pressure_kpa=30, timeout_ticks=10, min_kpa=70)
    _ok(client.write_registers(EPICK_COMMAND, grip, device_id=EPICK_ID))
    assert world.held is not None  # the sphere under the nozzle is on it
    status = _until(lambda: _epick_status(client), lambda s: s["gOBJ"] in (1, 2), "object detected (gOBJ 1 or 2)")
    assert (status["gGTO"], status["gVAS"], status["gPR"], status["gFLT"]) == (1, 1, 30, 0)
    assert status["gPO"] <= 70  # at least the minimum vacuum (absolute kPa: lower is more vacuum)
    by_fc03 = _epick_status(client, function_code=3)
    assert by_fc03["gOBJ"] in (1, 2) and by_fc03["gPR"] == 30

    release = _epick_command(activate=True, regulate=True, pressure_kpa=100, timeout_ticks=10, min_kpa=70)
    _ok(client.write_registers(EPICK_COMMAND, release, device_id=EPICK_ID))
    assert world.held is None  # put down
    status = _until(lambda: _epick_status(client), lambda s: s["gPO"] >= 95 and s["gOBJ"] == 3,
                    "vented, no object (gOBJ 3)")
    assert status["gPR"] == 100


def test_epick_refuses_a_reserved_mode_with_exception_3(epick):
    client, _, _ = epick
    reply = client.write_registers(EPICK_COMMAND, [(1 | 2 << 1) << 8, 100, 100], device_id=EPICK_ID)  # rMOD 2
    assert reply.isError() and reply.exception_code == 3


def test_epick_answers_only_its_own_device_id_and_obeys_a_broadcast(epick):
    """Modbus over serial line: only the addressed device answers; a write to id 0 is executed by every
    device and answered by none. pymodbus's client, asked for device 8, hears nothing and gives up."""
    client, received, server = epick
    received.clear()
    with pytest.raises(ModbusIOException, match="No response"):
        client.read_input_registers(EPICK_STATUS, count=3, device_id=8)
    with pytest.raises(ModbusIOException, match="No response"):
        client.write_registers(EPICK_COMMAND, _epick_command(activate=True), device_id=8)
    assert b"".join(received) == b""  # not one byte came back, not even an exception
    assert _epick_status(client)["gACT"] == 0  # device 8's activation was not executed here
    assert client.write_registers(EPICK_COMMAND, _epick_command(activate=True), device_id=0,
                                  no_response_expected=True) is None  # broadcast: nothing to wait for
    status = _until(lambda: _epick_status(client), lambda s: s["gSTA"] == 3, "activation by broadcast")
    assert status["gACT"] == 1 and server.broadcasts == 1


# --- OnRobot VGC10: Modbus TCP, unit 65 -----------------------------------------------------------


@pytest.fixture
def vgc10(sim_gripper):
    with Vgc10Server(sim_gripper, tau_s=0.05) as server:
        client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=1.0, retries=1)
        assert client.connect(), f"pymodbus could not connect to the VGC10 simulator at {server.where}"
        try:
            yield client
        finally:
            client.close()


def _vacuum(client, address: int) -> list[int]:
    return _ok(client.read_holding_registers(address, count=2, device_id=VGC10_UNIT)).registers


def test_vgc10_grips_on_channel_a_and_reports_its_vacuum_at_258_and_at_18(vgc10, world):
    client = vgc10
    put_nozzle_on_a_sphere(world)
    assert _ok(client.read_holding_registers(0, count=3, device_id=VGC10_UNIT)).registers == [0, 0, 500]
    _ok(client.write_register(0, 1 << 8 | 60, device_id=VGC10_UNIT))  # channel A: grip, 60 %
    assert world.held is not None
    assert _until(lambda: _vacuum(client, 258), lambda v: v == [600, 0], "60 % on A (600 per mille)") == [600, 0]
    assert _vacuum(client, 18) == [600, 0]  # the other public reading of the map sees the same vacuum
    _ok(client.write_register(0, 0, device_id=VGC10_UNIT))  # release
    assert world.held is None
    _until(lambda: _vacuum(client, 258) + _vacuum(client, 18), lambda v: v == [0, 0, 0, 0], "vented")


def test_vgc10_refusals_a_plain_client_sees(vgc10):
    client = vgc10
    reply = client.write_register(0, 3 << 8, device_id=VGC10_UNIT)  # mode 3 does not exist
    assert reply.isError() and reply.exception_code == 3
    for address in (258, 18):  # actual vacuum is read only
        reply = client.write_register(address, 5, device_id=VGC10_UNIT)
        assert reply.isError() and reply.exception_code == 2
    for read in (client.read_input_registers, client.read_coils, client.read_discrete_inputs):
        reply = read(0, count=2, device_id=VGC10_UNIT)  # FC 4, 1, 2: not among the documented 3, 6, 16, 23
        assert reply.isError() and reply.exception_code == 1, read.__name__
    both = _ok(client.readwrite_registers(read_address=0, read_count=2, write_address=1, values=[2 << 8],
                                          device_id=VGC10_UNIT))  # FC 23: channel B idle, read both controls
    assert both.registers == [0, 2 << 8]


def test_vgc10_takes_a_target_above_80_percent_and_regulates_at_80(vgc10, world):
    client = vgc10
    put_nozzle_on_a_sphere(world)
    _ok(client.write_registers(0, [1 << 8 | 100, 1 << 8 | 100], device_id=VGC10_UNIT))  # both channels: grip, 100 %
    assert _ok(client.read_holding_registers(0, count=2, device_id=VGC10_UNIT)).registers == [356, 356]  # as written
    assert _until(lambda: _vacuum(client, 258), lambda v: v == [800, 800], "80 % on A and B") == [800, 800]
    time.sleep(0.2)
    assert _vacuum(client, 258) == [800, 800]  # and no further
    _ok(client.write_registers(0, [0, 0], device_id=VGC10_UNIT))
