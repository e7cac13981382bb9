"""The EPick driver's fixtures: its simulator on TCP and on a pty pair, and drivers on the TCP one."""

from __future__ import annotations

import pytest

from drivers.sim.servers.epick import EPickServer

from tests.support.grippers import (
    tcp_driver,
)


@pytest.fixture
def tcp_server(sim_gripper):
    with EPickServer(sim_gripper, kind="rtu-over-tcp") as server:
        yield server


@pytest.fixture
def serial_server(sim_gripper, pty_pair):
    with EPickServer(sim_gripper, kind="serial", serial_port=pty_pair[1]) as server:
        yield server


@pytest.fixture
def make_device(tcp_server):
    """Drivers on the TCP simulator: for the contract over TCP and conftest's connected `gripper`."""
    return lambda: tcp_driver(tcp_server)
