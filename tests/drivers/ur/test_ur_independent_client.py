"""The UR simulator's secondary interface (30002) read by an independent client, not part of the project: urx's
SecondaryMonitor (urx 0.11, pinned in the test extra), which parses the robot-state stream as it does a real
controller's and sends URScript on the same port."""

from __future__ import annotations

import math

import pytest
from urx import ursecmon

from drivers.interfaces import Pose
from drivers.sim.servers.ur import UrSimulator

from tests.support.ur import KNOWN_Q, TestArm
from tests.support.wait import eventually

HOST = "127.0.0.20"  # UR ports are fixed: an address of this module's own
KNOWN = Pose(0.050, 0.040, 0.010, 0.5)


def test_urx_reads_the_pose_and_joints_and_sends_a_program():
    with UrSimulator(TestArm(KNOWN), HOST) as sim:
        monitor = ursecmon.SecondaryMonitor(HOST)
        try:
            monitor.wait(timeout=2.0)  # until it has parsed a state message
            cartesian = monitor.get_cartesian_info(wait=True)
            joints = monitor.get_joint_data(wait=True)
            assert (cartesian["X"], cartesian["Y"], cartesian["Z"]) == pytest.approx((0.050, 0.040, 0.010), abs=1e-12)
            rotvec = (cartesian["Rx"], cartesian["Ry"], cartesian["Rz"])
            assert rotvec == pytest.approx((math.pi * math.cos(0.25), math.pi * math.sin(0.25), 0.0), abs=1e-12)
            assert [joints[f"q_actual{i}"] for i in range(6)] == pytest.approx(KNOWN_Q, abs=1e-12)
            assert not monitor.is_program_running()
            monitor.send_program("def rtde_control():\n  rtde_cmd()\nend\n")
            eventually(monitor.is_program_running, timeout=3.0, every=0.05, what="the program running, as urx sees it")
            assert sim.controller.runtime_state == 2
        finally:
            monitor.close()
