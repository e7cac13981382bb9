"""Fixtures the gripper driver tests share: one simulated world and its in-process gripper."""

import pytest

from drivers.sim.devices import SimGripper
from drivers.sim.micro.world import World


@pytest.fixture
def world(microcell_sim):
    return World(microcell_sim)


@pytest.fixture
def gripper(make_device):
    """A gripper driver from the test module's `make_device`, connected, closed after the test."""
    gripper = make_device()
    gripper.connect()
    yield gripper
    gripper.close()


@pytest.fixture
def sim_gripper(world):
    gripper = SimGripper("gripper", world, SimGripper.Settings())
    gripper.connect()
    return gripper
