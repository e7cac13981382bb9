"""Robotiq EPick driver's exact bytes against a scripted peer (on TCP and on a pty), and its register codec.

Addressing on the RTU line, in exact bytes over both transports: the simulator answers only its own device id
(silence for id 8, a broadcast write to id 0 executed and unanswered), and the driver never takes another
device's frame for its reply."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest
from pydantic import ValidationError

from drivers.grippers.epick import EPickGripper
from drivers.grippers.epick_registers import (
    OBJ_AT_MAX,
    EPickCommand,
    EPickStatus,
    decode_command,
    decode_status,
    encode_command,
    encode_status,
)
from drivers.grippers.modbus_link import ModbusReplyError, NoReply
from drivers.interfaces import (
    DeviceError,
    DeviceState,
)
from drivers.sim.servers.epick import EPickServer

from tests.support.grippers import (
    h,
)
from tests.support.wire import WirePeer

# -- the exact bytes on the wire ----------------------------------------------------



WRITE_OK = h("09 10 03 E8 00 03 01 30")  # the manual's reply to a 3-register write at 0x03E8
READ_STATUS = h("09 04 07 D0 00 03 B1 CE")
RESET = h("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30")  # the manual's "clear rACT" request
ACTIVATE = h("09 10 03 E8 00 03 06 03 00 00 64 0A 50 34 40")  # rACT, advanced mode; rPR 100, rSP 1.0 s, rFR 80
GRIP = h("09 10 03 E8 00 03 06 0B 00 00 28 0A 50 F4 DF")  # + rGTO, rPR 40 (60 kPa vacuum)
RELEASE = h("09 10 03 E8 00 03 06 0B 00 00 64 0A 50 35 08")  # rPR 100: passive release
OPERATIONAL = h("09 04 06 33 00 00 64 64 00 69 8F")  # gACT, gMOD 1, gSTA 3; 100 kPa
HOLDING = h("09 04 06 BB 01 00 28 28 00 BF D0")  # gGTO, gOBJ 2, gVAS 1; echo 40, 40 kPa
RELEASED = h("09 04 06 FB 02 00 64 64 00 00 07")  # gOBJ 3, gVAS 2; 100 kPa


def scripted_driver(peer, **options) -> EPickGripper:
    settings = {"transport": "tcp", "port": peer.port, "grip_timeout_s": 1.0, "timeout_s": 0.2, "retries": 0, **options}
    return EPickGripper.create("epick", settings)


def test_wire_exchanges_for_activate_grip_status_release():
    peer = WirePeer([
        (RESET, WRITE_OK), (ACTIVATE, WRITE_OK), (READ_STATUS, OPERATIONAL),
        (GRIP, WRITE_OK), (READ_STATUS, HOLDING),
        (READ_STATUS, HOLDING),
        (READ_STATUS, HOLDING), (RELEASE, WRITE_OK), (READ_STATUS, RELEASED),
    ])
    gripper = scripted_driver(peer)
    try:
        gripper.connect()
        assert gripper.grip() is True
        status = gripper.status()
        assert (status.vacuum_kpa, status.object_detected, status.gripping) == (60.0, True, True)
        assert gripper.last_status.object == OBJ_AT_MAX
        gripper.release()
        assert gripper.last_status.actuator == 2 and gripper.last_status.pressure_kpa == 100
    finally:
        gripper.close()
        peer.close()
    assert peer.errors == []
    assert len(peer.received) == 9


def test_requests_are_paced_at_least_5_ms_apart():
    peer = WirePeer([(RESET, WRITE_OK), (ACTIVATE, WRITE_OK), (READ_STATUS, OPERATIONAL)] + [(READ_STATUS, OPERATIONAL)] * 5)
    gripper = scripted_driver(peer)
    sent_at = []  # when each request went out: the link's own trace of the bytes it sends
    trace = gripper.link._trace

    def timed_trace(sending: bool, data: bytes) -> bytes:
        if sending:
            sent_at.append(time.monotonic())
        return trace(sending, data)

    gripper.link._trace = timed_trace  # taken by the client when the link opens
    try:
        gripper.connect()
        for _ in range(5):
            gripper.status()
        assert len(sent_at) == 8
        assert min(np.diff(sent_at)) >= 0.005
    finally:
        gripper.close()
        peer.close()
    assert peer.errors == []


def test_scripted_malformed_and_exception_replies():
    bad_crc = h("09 04 06 33 00 00 64 64 00 69 8E")
    exception = h("09 84 02 43 03")
    peer = WirePeer([(RESET, WRITE_OK), (ACTIVATE, WRITE_OK), (READ_STATUS, OPERATIONAL),
                         (READ_STATUS, bad_crc), (READ_STATUS, exception), (READ_STATUS, OPERATIONAL)])
    gripper = scripted_driver(peer, timeout_s=0.1)
    try:
        gripper.connect()
        with pytest.raises(ModbusReplyError, match="got 09 04 06 33 00 00 64 64 00 69 8E, which is not a valid RTU frame"):
            gripper.status()
        with pytest.raises(ModbusReplyError, match=r"exception 2 \(illegal data address\)"):
            gripper.status()
        assert gripper.status().vacuum_kpa == 0.0
    finally:
        gripper.close()
        peer.close()
    assert peer.errors == []


def test_silent_device_times_out_instead_of_hanging():
    peer = WirePeer([(RESET, WRITE_OK), (ACTIVATE, WRITE_OK), (READ_STATUS, OPERATIONAL), (READ_STATUS, None)])
    gripper = scripted_driver(peer, timeout_s=0.1)
    try:
        gripper.connect()
        started = time.monotonic()
        with pytest.raises(NoReply, match="no reply to the FC04 read"):
            gripper.status()
        assert time.monotonic() - started < 1.0
        assert gripper.state is DeviceState.FAULTED
    finally:
        gripper.close()
        peer.close()


def test_activation_that_never_completes_is_an_error():
    not_yet = h("09 04 06 11 00 00 64 64 00")  # gACT, gSTA 1 (in progress)
    from pymodbus.framer.rtu import FramerRTU

    not_yet += FramerRTU.compute_CRC(not_yet).to_bytes(2, "big")
    peer = WirePeer([(RESET, WRITE_OK), (ACTIVATE, WRITE_OK)] + [(READ_STATUS, not_yet)] * 200)
    gripper = scripted_driver(peer, activation_timeout_s=0.1)
    try:
        with pytest.raises(DeviceError, match=r"activation did not complete within 0.1 s \(gSTA=1"):
            gripper.connect()
        assert gripper.state is DeviceState.CREATED
    finally:
        gripper.close()
        peer.close()


# -- addressing on an RTU line: only the addressed device answers ------------------------------
# Modbus over serial line (modbus.org, V1.02): every device hears every frame; only the one whose id
# the request names executes and answers it; id 0 is a broadcast, whose writes every device executes
# and none answers. The EPick is device 9; device 8 is some other device on the same RS-485 line.

READ_STATUS_8 = h("08 04 07 D0 00 03 B0 1F")  # device 8's status block: the EPick stays silent
ACTIVATE_8 = h("08 10 03 E8 00 03 06 01 00 00 64 0A 50 37 23")  # rACT for device 8: not executed here
READ_STATUS_0 = h("00 04 07 D0 00 03 B1 57")  # a broadcast read: nobody may answer it
ACTIVATE_0 = h("00 10 03 E8 00 03 06 01 00 00 64 0A 50 28 6B")  # broadcast rACT: executed, never answered
NOT_ACTIVATED = h("09 04 06 00 00 00 00 64 00 2D 93")  # gACT 0; gPR 0; 100 kPa
ACTIVATED = h("09 04 06 31 00 00 64 64 00 68 6D")  # gACT 1, gSTA 3; gPR 100; 100 kPa
STRAY_STATUS = h("08 04 06 33 00 00 64 64 00 64 1F")  # device 8's answer to a status read
STRAY_EXCEPTION = h("08 84 02 12 C3")  # device 8's exception 2


def crc16_modbus(frame: bytes) -> bytes:
    """The RTU CRC from the serial-line specification (polynomial 0xA001, initial 0xFFFF, low byte first),
    written here so the pinned frames are checked without pymodbus."""
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def test_pinned_frames_carry_their_crc():
    for frame in (READ_STATUS, WRITE_OK, RESET, ACTIVATE, GRIP, RELEASE, OPERATIONAL, HOLDING, RELEASED,
                  READ_STATUS_8, ACTIVATE_8, READ_STATUS_0, ACTIVATE_0, NOT_ACTIVATED, ACTIVATED,
                  STRAY_STATUS, STRAY_EXCEPTION):
        assert crc16_modbus(frame[:-2]) == frame[-2:], frame.hex(" ")


class RawLine:
    """The master's end of the line as raw bytes: a TCP socket to the simulator, or one end of a pty pair."""

    def __init__(self, transport: str, server: EPickServer, pty_end: str):
        self.sock = self.port = None
        if transport == "tcp":
            self.sock = socket.create_connection(("127.0.0.1", server.port), timeout=1.0)
        else:
            import serial

            self.port = serial.Serial(pty_end, 115200, timeout=0)

    def exchange(self, request: bytes, quiet_s: float = 0.25) -> bytes:
        """Send `request`; return every byte that arrives until the line has been quiet for `quiet_s`."""
        if self.sock is not None:
            self.sock.sendall(request)
        else:
            self.port.write(request)
        got = b""
        deadline = time.monotonic() + quiet_s
        while time.monotonic() < deadline:
            chunk = self._read()
            if chunk:
                got += chunk
                deadline = time.monotonic() + quiet_s
            else:
                time.sleep(0.005)
        return got

    def _read(self) -> bytes:
        if self.port is not None:
            return self.port.read(256)
        self.sock.setblocking(False)
        try:
            return self.sock.recv(256)
        except BlockingIOError:
            return b""

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        if self.port is not None:
            self.port.close()


@pytest.mark.parametrize("transport", ["tcp", "serial"])
def test_simulator_answers_only_its_own_device_id(sim_gripper, pty_pair, transport):
    kind = "rtu-over-tcp" if transport == "tcp" else "serial"
    with EPickServer(sim_gripper, kind=kind, serial_port=pty_pair[1], activation_s=0.0) as server:
        line = RawLine(transport, server, pty_pair[0])
        try:
            assert line.exchange(READ_STATUS_8) == b""  # another device's read: silence, not an exception
            assert line.exchange(ACTIVATE_8) == b""  # another device's write: silence, and not executed
            assert line.exchange(READ_STATUS) == NOT_ACTIVATED
            assert line.exchange(READ_STATUS_0) == b""  # a broadcast read: ignored
            assert line.exchange(ACTIVATE_0) == b""  # a broadcast write: never answered ...
            assert line.exchange(READ_STATUS) == ACTIVATED  # ... but executed
            assert line.exchange(READ_STATUS_8 + READ_STATUS) == ACTIVATED  # two frames in one read: ours answered
            assert line.exchange(STRAY_STATUS) == b""  # another device's reply on the line: not a request to us
            assert line.exchange(READ_STATUS) == ACTIVATED
        finally:
            line.close()
        assert (server.messages_total, server.broadcasts) == (4, 1)


def _scripted(transport: str, pty_pair, script) -> tuple[WirePeer, EPickGripper]:
    """A scripted device 9 on TCP or on a pty, and a driver for it (0.2 s time-out, no retry)."""
    if transport == "tcp":
        peer = WirePeer(script)
        return peer, scripted_driver(peer)
    peer = WirePeer(script, serial_port=pty_pair[1])
    return peer, EPickGripper.create("epick", {"transport": "serial", "serial_port": pty_pair[0],
                                               "grip_timeout_s": 1.0, "timeout_s": 0.2, "retries": 0})


@pytest.mark.parametrize("transport", ["tcp", "serial"])
def test_driver_ignores_replies_from_other_device_ids(pty_pair, transport):
    peer, gripper = _scripted(transport, pty_pair, [
        (RESET, WRITE_OK), (ACTIVATE, WRITE_OK), (READ_STATUS, OPERATIONAL),
        (READ_STATUS, STRAY_STATUS + HOLDING),  # another device's frame and ours in one read
        (READ_STATUS, [STRAY_EXCEPTION, HOLDING]),  # another device's exception first, ours 20 ms later
        (READ_STATUS, STRAY_STATUS),  # only another device answers: no reply from ours
    ])
    try:
        gripper.connect()
        assert gripper.read_status().object == OBJ_AT_MAX  # our HOLDING, not device 8's status
        assert gripper.read_status().object == OBJ_AT_MAX  # not device 8's exception
        started = time.monotonic()
        with pytest.raises(NoReply, match=r"no reply to the FC04 read .* within 0.2 s \(1 attempt\); ignored 1 frame "
                                          r"from other device ids: 08 04 06 33 00 00 64 64 00 64 1F \(device 8\)"):
            gripper.read_status()
        assert time.monotonic() - started < 1.5
        assert gripper.state is DeviceState.FAULTED
        strays = [data for kind, data in gripper.link.wire_log if kind == "stray"]
        assert strays == [STRAY_STATUS, STRAY_EXCEPTION, STRAY_STATUS]
    finally:
        gripper.close()
        peer.close()
    assert peer.errors == []


# -- settings and the register codec ------------------------------------------------


def test_bad_settings_name_the_field_and_allowed_values():
    with pytest.raises(ValidationError, match=r"transport\n.*'serial' or 'tcp'"):
        EPickGripper.create("epick", {"transport": "usb"})
    with pytest.raises(ValidationError, match="grip_vacuum_kpa"):
        EPickGripper.create("epick", {"grip_vacuum_kpa": 90})
    with pytest.raises(ValidationError, match="detect_vacuum_kpa .* must not exceed grip_vacuum_kpa"):
        EPickGripper.create("epick", {"grip_vacuum_kpa": 30, "detect_vacuum_kpa": 40})
    with pytest.raises(ValidationError, match="min_interval_s"):
        EPickGripper.create("epick", {"min_interval_s": 0.001})
    with pytest.raises(ValidationError, match="slave"):
        EPickGripper.create("epick", {"slave": 9})


def test_command_registers():
    assert encode_command(EPickCommand(activate=True, mode=1, regulate=True, pressure_kpa=40, timeout_ticks=10,
                                       min_pressure_kpa=80)) == [0x0B00, 0x0028, 0x0A50]
    assert encode_command(EPickCommand(activate=True, mode=0, auto_release=True, pressure_kpa=255)) == [0x1100, 0x00FF, 0x0064]
    command = EPickCommand(activate=True, mode=1, regulate=True, pressure_kpa=22, timeout_ticks=255, min_pressure_kpa=90)
    assert decode_command(encode_command(command)) == command
    with pytest.raises(ValueError, match="pressure_kpa must be an integer 0..255"):
        encode_command(EPickCommand(pressure_kpa=300))


def test_status_registers():
    status = decode_status([0xBB01, 0x0028, 0x2800])
    assert (status.activated, status.mode, status.regulating, status.activation, status.object, status.actuator) == \
        (True, 1, True, 3, 2, 1)
    assert (status.fault, status.pressure_request_kpa, status.pressure_kpa, status.vacuum_kpa) == (0, 40, 40, 60.0)
    faulted = decode_status([0x3100, 0xA864, 0x6400])
    assert faulted.fault == 0x8 and faulted.controller_fault == 0xA and faulted.major_fault
    assert "temperature" in faulted.fault_text()
    assert decode_status(encode_status(status)) == status
    over = EPickStatus(True, 0, True, 3, 3, 3, 0, 0, 110, 110)
    assert over.vacuum_kpa == 0.0  # blow-off: above the atmosphere
    with pytest.raises(ValueError, match="3 registers"):
        decode_status([0x3300, 0x0064])
