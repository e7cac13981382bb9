"""The UR simulator on the wire, in this process, with raw sockets (no ur_rtde: its constructors hold the GIL):
the UR5e joint angles RTDE reports, the primary and secondary interfaces, the options.

Each simulator here moves a small arm of the test's own, so the pinned values do not depend on a cell file.
Loopback addresses 127.0.0.14 and .15 (UR ports are fixed; tests/drivers/test_ur.py uses .2 to .13)."""

from __future__ import annotations

import math
import socket
import struct
import threading
import time

import numpy as np
import pytest

from drivers.interfaces import Pose
from drivers.sim.servers.ur import UrSimulator, primary
from drivers.sim.servers.ur import rtde as wire
from drivers.sim.servers.ur.controller import UrSimOptions, flange_to_tcp, matrix_of_rotvec, parse_options
from drivers.sim.servers.ur.kinematics import UrKinematics
from drivers.sim.servers.ur.server import PortsTaken

from tests.support.ur import KNOWN_Q, TestArm
from tests.support.wait import eventually

HOST, OTHER_HOST = "127.0.0.14", "127.0.0.15"
KNOWN = Pose(0.050, 0.040, 0.010, 0.5)




def _recv(sock, kind=None) -> bytes:
    size, got = struct.unpack(">HB", sock.recv(3, socket.MSG_WAITALL))
    payload = sock.recv(size - 3, socket.MSG_WAITALL) if size > 3 else b""
    if kind is not None:
        assert got == kind, f"expected {chr(kind)}, got {chr(got)}"
    return payload


def _stream(sock, names: str) -> wire.Recipe:
    sock.sendall(wire.frame(ord("O"), struct.pack(">d", 500.0) + names.encode()))
    reply = _recv(sock, ord("O"))
    recipe = wire.Recipe(reply[0], tuple(names.split(",")), tuple(reply[1:].decode().split(",")))
    sock.sendall(wire.frame(ord("S")))
    assert _recv(sock, ord("S")) == b"\x01"
    return recipe


def _fk_tcp(q, tcp=(0.0,) * 6) -> np.ndarray:
    """The TCP pose for q through the simulator's UR5e (T_mount · FK(q) · TCP), as [x, y, z, R (3x3)]."""
    T = UrKinematics().forward(q)
    T_tcp = np.eye(4)
    T_tcp[:3, :3] = matrix_of_rotvec(tcp[3:])
    T_tcp[:3, 3] = tcp[:3]
    return T @ T_tcp


def _assert_same_pose(T: np.ndarray, ur_pose, tol: float) -> None:
    assert T[:3, 3] == pytest.approx(ur_pose[:3], abs=tol)
    assert np.abs(T[:3, :3] - matrix_of_rotvec(ur_pose[3:])).max() < tol


# --- RTDE: actual_q is a UR5e's joint angles ----------------------------------------------------------------

def test_rtde_output_recipe_values_for_a_known_pose():
    """The data package of a recipe with the arm at KNOWN: the exact bytes of its fixed part, the TCP pose of
    the tool-down convention, and actual_q/target_q the UR5e angles whose forward kinematics is that pose."""
    with UrSimulator(TestArm(KNOWN), HOST) as sim, socket.create_connection((HOST, 30004), timeout=2.0) as sock:
        recipe = _stream(sock, "robot_mode,safety_mode,runtime_state,robot_status_bits,safety_status_bits,"
                               "actual_TCP_pose,actual_q,target_q")
        assert recipe.types == ("INT32", "INT32", "UINT32", "UINT32", "UINT32", "VECTOR6D", "VECTOR6D", "VECTOR6D")
        payload = _recv(sock, ord("U"))
        assert len(payload) == 1 + 5 * 4 + 3 * 48
        # recipe 1; RUNNING (7), NORMAL (1), STOPPED (1); power on (bit 0); normal (bit 0)
        assert payload[:21] == bytes.fromhex("01" "00000007" "00000001" "00000001" "00000001" "00000001")
        values = recipe.unpack(payload)
        half = math.pi * np.array([math.cos(0.25), math.sin(0.25), 0.0])  # Rz(0.5)·Rx(180°): half a turn
        assert values["actual_TCP_pose"] == pytest.approx((0.050, 0.040, 0.010, *half), abs=1e-15)
        assert values["actual_q"] == pytest.approx(KNOWN_Q, abs=1e-12)
        assert values["target_q"] == values["actual_q"]
        _assert_same_pose(_fk_tcp(values["actual_q"]), values["actual_TCP_pose"], 1e-12)
        assert sim.controller.joints() == values["actual_q"]


def test_forward_kinematics_of_actual_q_is_actual_tcp_pose_in_every_package_along_a_move():
    """A moveL (alpha 0 -> 150 deg) through the emulated control script (register protocol on raw RTDE) with a TCP
    offset set, while the arm takes 0.4 s: in every data package FK(actual_q) · TCP = actual_TCP_pose (1e-12), and q
    stays on one branch (no jumps), ending at the target's angles."""
    arm = TestArm(Pose(0.020, 0.020, 0.020, 0.0), seconds=0.4)
    tcp = (0.001, -0.002, 0.030, 0.0, 0.0, 0.4)
    target_flange = Pose(0.140, 0.090, 0.000, math.radians(150))
    target = flange_to_tcp(target_flange, tcp)  # moveL takes the TCP's pose
    with UrSimulator(arm, HOST) as sim:
        with socket.create_connection((HOST, 30003), timeout=2.0) as script:
            script.sendall(b"def rtde_control():\n  rtde_cmd()\nend\n")
        eventually(lambda: sim.controller.runtime_state == 2, timeout=2.0, every=0.01, what="the program PLAYING")
        sim.controller.tcp = tcp
        with socket.create_connection((HOST, 30004), timeout=2.0) as sock:
            names = "input_int_register_0,input_int_register_1," + ",".join(
                f"input_double_register_{i}" for i in range(8))
            sock.sendall(wire.frame(ord("I"), names.encode()))
            inputs = _recv(sock, ord("I"))
            command = wire.Recipe(inputs[0], tuple(names.split(",")), tuple(inputs[1:].decode().split(",")))
            recipe = _stream(sock, "timestamp,actual_q,actual_TCP_pose,output_int_register_0")
            sock.sendall(wire.frame(ord("U"), command.pack({
                "input_int_register_0": 3, "input_int_register_1": 0,  # moveL, synchronous
                **{f"input_double_register_{i}": v for i, v in enumerate([*target[:6], 0.25, 1.2])}})))
            packages = []
            while True:
                values = recipe.unpack(_recv(sock, ord("U")))
                packages.append(values)
                if values["output_int_register_0"] == 2:  # done
                    break
                assert len(packages) < 2000, "the move never finished"
    moving = [p for p in packages if p["actual_q"] != packages[0]["actual_q"]]
    assert len(moving) > 50  # 0.4 s at 500 Hz, less the start
    for p in packages:
        _assert_same_pose(_fk_tcp(p["actual_q"], tcp), p["actual_TCP_pose"], 1e-12)
    k = UrKinematics()
    for p in packages:  # each q is the IK solution of its own pose: one branch, no flip nor 2 pi wrap, however the
        T = k.forward(p["actual_q"])  # host kept the 2 ms pace (a busy one skips cycles, and the steps grow)
        assert p["actual_q"] == pytest.approx(k.joints(Pose(*T[:3, 3], k.alpha_of(T))), abs=1e-9)
    assert packages[-1]["actual_q"] == pytest.approx(UrKinematics().joints(target_flange), abs=1e-9)


# --- primary (30001) and secondary (30002) interfaces ------------------------------------------------------------

VERSION_5_15 = bytes.fromhex(
    "00000037" "14"                # size 55, robot message
    "0000000000000000" "fe" "03"   # timestamp 0, source -2 (controller), version message
    "09" + b"URControl".hex() +    # project name
    "05" "0f" "00000000" "00000000" + b"01-01-2024, 00:00:00".hex())  # 5.15, bugfix 0, build 0, build date


def _messages(sock, count: int) -> list[tuple[int, bytes]]:
    data, out = b"", []
    while len(out) < count:
        data += sock.recv(65536)
        got, data = primary.parse(data)
        out += got
    return out


@pytest.mark.parametrize("port", [30001, 30002])
def test_client_interface_first_packets(port):
    """On connect: the version message (exact bytes), then robot state messages of 1186 bytes with robot mode,
    joint, cartesian, kinematics, masterboard, tool and configuration data, sized as a UR5e's on 5.x."""
    with UrSimulator(TestArm(KNOWN), HOST), socket.create_connection((HOST, port), timeout=2.0) as sock:
        first = sock.recv(len(VERSION_5_15), socket.MSG_WAITALL)
        assert first == VERSION_5_15
        (kind, body), = _messages(sock, 1)
    assert kind == primary.ROBOT_STATE and len(body) + 5 == 1186
    subs = primary.sub_packages(body)
    assert [(k, len(v) + 5) for k, v in subs.items()] == [(0, 47), (1, 251), (4, 101), (5, 225), (3, 75), (2, 37),
                                                          (6, 445)]
    # robot mode data after its timestamp: connected, enabled, powered, no e-stop, no protective stop, no program
    # running or paused, RUNNING (7), position control (0), speed fraction 1.0, scaling 1.0, limit 1.0, reserved
    assert subs[0][8:] == bytes.fromhex("01010100000000" "07" "00" + "3ff0000000000000" * 3 + "00")
    joints = [struct.unpack(">dddffffB", subs[1][i * 41:(i + 1) * 41]) for i in range(6)]
    assert [j[0] for j in joints] == pytest.approx(KNOWN_Q, abs=1e-12)  # q_actual
    assert [j[1] for j in joints] == pytest.approx(KNOWN_Q, abs=1e-12)  # q_target
    assert {j[7] for j in joints} == {253}  # JOINT_RUNNING
    cartesian = struct.unpack(">12d", subs[4])
    half = math.pi * np.array([math.cos(0.25), math.sin(0.25), 0.0])
    assert cartesian == pytest.approx((0.050, 0.040, 0.010, *half, *(0.0,) * 6), abs=1e-15)
    kin = struct.unpack(">6I24dI", subs[5])
    assert kin[:6] == (0xFFFFFFFF,) * 6 and kin[6:12] == (0.0,) * 6  # uncalibrated, theta offsets 0
    assert kin[12:18] == (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)  # a
    assert kin[18:24] == (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)  # d
    assert kin[24:30] == (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)  # alpha
    config = struct.unpack(">12d12d5d24d4i", subs[6])
    assert config[-4:] == (6, 4, 1, 3)  # masterboard version, controller box, robot type UR5, sub type (UR5e's)
    assert config[29:35] == kin[12:18] and config[35:41] == kin[18:24]
    masterboard = struct.unpack(">IIbbddbbddffffB??IB?B", subs[3])
    assert masterboard[14] == 1  # safety mode NORMAL


def test_client_interface_streams_at_10_hz_and_takes_urscript():
    """A program sent on 30002 replaces the running one as on 30003: ur_rtde's control script starts (the next
    state messages say 'program running'), another program stops it."""
    with UrSimulator(TestArm(KNOWN), HOST) as sim, socket.create_connection((HOST, 30002), timeout=2.0) as sock:
        assert _messages(sock, 1)[0][0] == primary.ROBOT_MESSAGE
        sock.sendall(b"def rtde_control():\n  rtde_cmd()\nend\n")
        running = False
        start = time.monotonic()
        states = 0
        while time.monotonic() - start < 1.05:
            for _kind, body in _messages(sock, 1):
                states += 1
                running = running or primary.sub_packages(body)[0][8 + 5] == 1  # isProgramRunning
        assert running and sim.controller.runtime_state == 2
        assert 5 <= states <= 12  # 10 Hz (fewer on a busy host, never a burst)
        sock.sendall(b"def other():\n  textmsg(\"hi\")\nend\n")
        eventually(lambda: sim.controller.runtime_state == 1, timeout=2.0, every=0.01, what="the program STOPPED")
        assert any("only ur_rtde's rtde_control script is emulated" in e for e in sim.controller.events)


def test_primary_state_follows_a_protective_stop():
    with UrSimulator(TestArm(KNOWN), HOST) as sim, socket.create_connection((HOST, 30001), timeout=2.0) as sock:
        _messages(sock, 2)
        sim.controller.protective_stop("test")
        body = _messages(sock, 1)[0][1]
        mode = primary.sub_packages(body)[0]
        assert mode[8 + 4] == 1  # isProtectiveStopped
        assert struct.unpack(">IIbbddbbddffffB??IB?B", primary.sub_packages(body)[3])[14] == 3  # PROTECTIVE_STOP


def test_a_second_simulator_on_the_same_address_says_the_ports_are_taken():
    with UrSimulator(TestArm(KNOWN), OTHER_HOST):
        with pytest.raises(PortsTaken, match=r"cannot listen on 127\.0\.0\.15:29999 \(dashboard\).*another loopback"):
            UrSimulator(TestArm(KNOWN), OTHER_HOST).start()
    for port in (29999, 30001, 30002, 30003, 30004):  # the first one's ports are free again
        socket.create_server((OTHER_HOST, port)).close()


# --- options ----------------------------------------------------------------------------------------------------

def test_options_list_what_is_allowed():
    with pytest.raises(ValueError, match=r"unknown UR simulator option 'nonsense'; allowed: version, serial_number, "
                                         r".*base_xyz_mm, base_yaw_deg; fault knobs: drop_after_commands"):
        parse_options({"nonsense": 1})
    with pytest.raises(ValueError, match=r"option faults.slow_reply_s='abc': Input should be a valid number"):
        parse_options({"slow_reply_s": "abc"})
    with pytest.raises(ValueError, match="unknown UR simulator option 'faults.bogus'"):
        parse_options({"faults": {"bogus": 1}})
    with pytest.raises(ValueError, match="must be a mapping"):
        parse_options([1, 2])
    flat = parse_options({"slow_reply_s": 0.3, "faults": {"outage_s": 2.0}, "unlock_delay_s": 0})
    assert flat.faults.slow_reply_s == 0.3 and flat.faults.outage_s == 2.0 and flat.unlock_delay_s == 0
    assert parse_options(None) == UrSimOptions()


def test_slow_requests_delay_only_the_named_dashboard_requests():
    options = parse_options({"slow_reply_s": 1.0, "slow_requests": ["Unlock Protective Stop "]})
    with UrSimulator(TestArm(KNOWN), HOST, options) as sim:
        assert sim.controller.dashboard_delay_s("robotmode") == 0.0
        assert sim.controller.dashboard_delay_s("unlock protective stop") == 1.0
        with socket.create_connection((HOST, 29999), timeout=2.0) as sock:
            reader = sock.makefile("rb")
            reader.readline()
            for request, slow in ((b"robotmode\n", False), (b"unlock protective stop\n", True)):
                start = time.monotonic()
                sock.sendall(request)
                reader.readline()
                assert (time.monotonic() - start >= 1.0) is slow, request


def test_an_unreachable_mounting_is_refused_at_start():
    with pytest.raises(ValueError, match="out of the simulated UR5e's reach from its base at \\(2000"):
        UrSimulator(TestArm(KNOWN), HOST, {"base_xyz_mm": (2000, 0, 0)})


def test_state_threads_end_with_their_connections():
    with UrSimulator(TestArm(KNOWN), HOST):
        before = threading.active_count()
        for port in (30001, 30002):
            with socket.create_connection((HOST, port), timeout=2.0) as sock:
                _messages(sock, 2)
        eventually(lambda: threading.active_count() <= before, timeout=2.0, what="the clients' threads ended")
