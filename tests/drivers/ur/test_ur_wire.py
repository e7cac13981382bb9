"""The UR simulator's own wire, from raw sockets (an in-process simulator: no ur_rtde here, whose constructors
hold the GIL): the RTDE handshake, recipes and data packages, input registers in use, the fault knobs, the script
and dashboard ports; and its pose math against the driver's orientation convention."""

from __future__ import annotations

import itertools
import math
import socket
import struct

import numpy as np
import pytest

from drivers.interfaces import (
    Pose,
)
from drivers.sim.servers.ur import rtde as wire

from tests.conftest import MICROCELL
from tests.support.ur import ur_arm
from tests.support.wait import eventually


@pytest.fixture
def local_sim():
    """An in-process simulator for raw-socket clients (never for ur_rtde: its constructors hold the GIL)."""
    from drivers.sim.servers.ur import UrSimulator
    from drivers.sim.servers.ur.server import build_arm

    with UrSimulator(build_arm(MICROCELL), "127.0.0.8") as server:
        yield server


def _recv(sock, kind=None):
    size, got = struct.unpack(">HB", sock.recv(3, socket.MSG_WAITALL))
    payload = sock.recv(size - 3, socket.MSG_WAITALL) if size > 3 else b""
    if kind is not None:
        assert got == kind, f"expected reply {chr(kind)}, got {chr(got)}"
    return payload


def _start_stream(sock, names: str, frequency: float = 500.0) -> wire.Recipe:
    sock.sendall(wire.frame(ord("O"), struct.pack(">d", frequency) + names.encode()))
    reply = _recv(sock, ord("O"))
    recipe = wire.Recipe(reply[0], tuple(names.split(",")), tuple(reply[1:].decode().split(",")))
    sock.sendall(wire.frame(ord("S")))
    assert _recv(sock, ord("S")) == b"\x01"
    return recipe


def test_raw_rtde_handshake_types_and_not_found(local_sim):
    """The wire format itself: versions, recipe types, NOT_FOUND, a data package per cycle."""
    with socket.create_connection((local_sim.host, 30004), timeout=2.0) as sock:
        sock.sendall(wire.frame(ord("V"), struct.pack(">H", 2)))
        assert _recv(sock, ord("V")) == b"\x01"
        sock.sendall(wire.frame(ord("v")))
        assert struct.unpack(">IIII", _recv(sock, ord("v")))[0] >= 5
        sock.sendall(wire.frame(ord("O"), struct.pack(">d", 500.0) + b"timestamp,actual_q,no_such_thing,"))
        reply = _recv(sock, ord("O"))
        assert reply[0] == 0 and reply[1:].decode() == "DOUBLE,VECTOR6D,NOT_FOUND"
        names = "timestamp,actual_TCP_pose,runtime_state,joint_mode,safety_status_bits,actual_tool_accelerometer"
        recipe = _start_stream(sock, names)
        assert recipe.types == ("DOUBLE", "VECTOR6D", "UINT32", "VECTOR6INT32", "UINT32", "VECTOR3D")
        stamps = [recipe.unpack(_recv(sock, ord("U")))["timestamp"] for _ in range(20)]
        assert all(b > a for a, b in itertools.pairwise(stamps))
        sock.sendall(wire.frame(ord("P")))


def test_input_registers_in_use_by_another_client(local_sim):
    setup = wire.frame(ord("I"), b"input_int_register_0,input_double_register_0,")
    with socket.create_connection((local_sim.host, 30004), timeout=2.0) as first:
        first.sendall(setup)
        assert _recv(first, ord("I"))[1:] == b"INT32,DOUBLE"
        with socket.create_connection((local_sim.host, 30004), timeout=2.0) as second:
            second.sendall(setup)
            reply = _recv(second, ord("I"))
            assert reply[0] == 0 and reply[1:] == b"IN_USE,IN_USE"
    eventually(lambda: not local_sim._input_owner, timeout=2.0, every=0.01,
               what="the inputs released when the owner's connection ends")
    with socket.create_connection((local_sim.host, 30004), timeout=2.0) as third:
        third.sendall(setup)
        assert _recv(third, ord("I"))[1:] == b"INT32,DOUBLE"


def test_malformed_frame_fault_knob(local_sim):
    local_sim.controller.faults.malformed_after_packets = 3
    with socket.create_connection((local_sim.host, 30004), timeout=2.0) as sock:
        _start_stream(sock, "timestamp")
        for _ in range(3):
            wire.read_message(sock)
        with pytest.raises(wire.ProtocolError, match="below the 3-byte header"):
            wire.read_message(sock)


def test_client_sending_garbage_is_dropped_with_a_clear_note(local_sim):
    with socket.create_connection((local_sim.host, 30004), timeout=2.0) as sock:
        sock.sendall(wire.frame(ord("U"), b"\x07\x00\x00\x00\x01"))  # input recipe 7 was never set up
        assert sock.recv(16) == b""  # closed
    assert any("never set up" in event for event in local_sim.controller.events)


def test_slow_dashboard_fault_knob(local_sim):
    local_sim.controller.faults.slow_reply_s = 0.3
    with socket.create_connection((local_sim.host, 29999), timeout=2.0) as sock:
        reader = sock.makefile("rb")
        assert reader.readline().startswith(b"Connected: Universal Robots Dashboard Server")
        sock.settimeout(0.05)
        sock.sendall(b"robotmode\n")
        with pytest.raises(socket.timeout):
            sock.recv(64)  # a client with a short time-out gives up
        sock.settimeout(2.0)
        assert reader.readline() == b"Robotmode: RUNNING\n"


def test_script_port_runs_only_the_rtde_control_script(local_sim):
    with socket.create_connection((local_sim.host, 30003), timeout=2.0) as sock:
        sock.sendall(b"def other():\n  movel(p[0, 0, 0, 0, 0, 0])\nend\n")
        eventually(lambda: any("only ur_rtde" in e for e in local_sim.controller.events), timeout=2.0, every=0.01,
                   what="the controller refusing a script that is not ur_rtde's")
    assert local_sim.controller.runtime_state == 1  # STOPPED: nothing runs it




def test_simulator_pose_math_agrees_with_the_drivers_orientation_convention():
    """The simulator's numpy rotations and UrArm's (geometry/orientation.py, scipy) are one convention."""
    from scipy.spatial.transform import Rotation

    from drivers.arms.ur.rtde_driver import pose_of, ur_pose_of
    from drivers.sim.servers.ur.controller import flange_to_tcp, tcp_to_flange

    rng = np.random.default_rng(7)
    for alpha in (0.0, math.pi, -math.pi / 2, *rng.uniform(-math.pi, math.pi, 20)):
        tcp = (*rng.uniform(-0.05, 0.05, 3), 0.0, 0.0, rng.uniform(-1, 1))  # a TCP turned about the tool axis
        flange = Pose(*rng.uniform(-0.2, 0.2, 3), alpha)
        ur = flange_to_tcp(flange, tcp)
        expected = Rotation.from_rotvec(ur_pose_of(flange)[3:]) * Rotation.from_rotvec(tcp[3:])
        assert (Rotation.from_rotvec(ur[3:]) * expected.inv()).magnitude() < 1e-9
        back = tcp_to_flange(ur, tcp, near_alpha=alpha)
        assert math.dist(back.xyz, flange.xyz) < 1e-12 and abs(back.alpha - alpha) < 1e-9
        assert abs(math.remainder(pose_of(flange_to_tcp(flange, (0,) * 6)).alpha - alpha, math.tau)) < 1e-9
    with pytest.raises(ValueError, match="tilt"):
        tcp_to_flange([0, 0, 0, 0.1, 0, 0], (0,) * 6)


def test_settings_errors_name_the_field():
    with pytest.raises(ValueError, match="speed_m_s"):
        ur_arm("127.0.0.2", speed_m_s=-1)
    with pytest.raises(ValueError, match="joint_limits_rad"):
        ur_arm("127.0.0.2", joint_limits_rad=[[0, 1]])
