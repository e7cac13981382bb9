"""The vacuum grippers' tests share: quick settings, hex frames, a sphere under the nozzle, vacuum lost."""

from __future__ import annotations

import numpy as np

from drivers.grippers.epick import EPickGripper
from drivers.interfaces import (
    Pose,
    VacuumLost,
)
from drivers.limits import WorkspaceBox
from drivers.sim.devices import SimArm
from drivers.sim.servers.epick import EPickServer

from tests.support.wait import eventually

FAST = {"grip_timeout_s": 0.3, "timeout_s": 0.5, "retries": 1}  # room for a loaded machine; time-out tests give theirs


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def put_nozzle_on_a_sphere(world) -> None:
    """Lay a 1 mm sphere and bring the nozzle tip (not the axis) onto its top, as test_sim_world does."""
    box = WorkspaceBox(x_mm=(-10, 160), y_mm=(-10, 110), z_mm=(-5, 40))  # the micro cell's
    arm = SimArm("arm", world, SimArm.Settings(limits=box))
    arm.connect()
    world.add_sphere(0.045, 0.030, 0.0, diameter=1e-3)
    arm.move_linear(Pose(0.045, 0.030, 1e-3))
    tip_offset = world.nozzle_tip()[:2] - np.array([0.045, 0.030])
    arm.move_linear(Pose(0.045 - tip_offset[0], 0.030 - tip_offset[1], 1e-3))


def wait_for_vacuum_lost(gripper, within_s: float = 2.0) -> None:
    """The gripper's status raises VacuumLost ("lost") within `within_s`."""
    def raised() -> bool:
        try:
            gripper.status()
        except VacuumLost as exc:
            assert "lost" in str(exc), exc
            return True
        return False

    eventually(raised, timeout=within_s, every=0.01, what="VacuumLost from the gripper's status")


def tcp_driver(server, **options) -> EPickGripper:
    return EPickGripper.create("epick", {"transport": "tcp", "host": "127.0.0.1", "port": server.port, **FAST, **options})


def serial_driver(port: str, **options) -> EPickGripper:
    return EPickGripper.create("epick", {"transport": "serial", "serial_port": port, **FAST, **options})


def served_driver(transport: str, sim_gripper, pty_pair, **options) -> tuple[EPickServer, EPickGripper]:
    """A started simulator on `transport` ("tcp" or "serial") and a driver for it; the test closes both."""
    if transport == "tcp":
        server = EPickServer(sim_gripper, kind="rtu-over-tcp").start()
        return server, tcp_driver(server, **options)
    server = EPickServer(sim_gripper, kind="serial", serial_port=pty_pair[1]).start()
    return server, serial_driver(pty_pair[0], **options)
