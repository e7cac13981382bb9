"""Via points on a UR (issue 31): UrArm does not offer MovesThrough (drivers/arms/ur/arm.py says why: through
ur_rtde a move either settles or is killed, a blend needs a path re-uploaded with the whole control script), so
`move_via` gives it a settled move_linear: the arm arrives and is checked there, and the simulated cell time counts
the settling. Against the UR simulator in its own process, moving a World this process owns."""

from __future__ import annotations

import pytest

from drivers.interfaces import MovesThrough, Pose, move_via
from drivers.registry import DriverContext, backend_class
from drivers.sim.servers.ur import SimulatorProcess

from tests.support.ur import LIMITS, ur_arm

pytestmark = pytest.mark.long  # a simulator process: see conftest.py

pytest.importorskip("rtde_control")

HOST = "127.0.0.63"  # this module's own loopback address (RTDE's port 30004 is fixed)


@pytest.fixture(scope="module")
def cell():
    """This process's World, its SimArm served to a UR simulator; a UrArm connected to that simulator."""
    from drivers.sim.micro.config import SimWorldConfig
    from drivers.sim.remote import ArmHost

    from tests.conftest import microcell_data

    context = DriverContext(sim_config=SimWorldConfig(**microcell_data()["sim"]))
    sim_arm = backend_class("arm", "sim").create("arm", {"limits": LIMITS}, context)
    sim_arm.connect()
    host = ArmHost(sim_arm)
    process = SimulatorProcess(HOST, host)
    try:
        process.start()
        arm = ur_arm(HOST)
        arm.connect()
        try:
            yield context.sim_world(), arm
        finally:
            arm.close()
    finally:
        process.terminate()
        code = process.stop()
        host.close()
    assert code == 0


def test_a_via_point_on_a_ur_is_a_settled_move(cell):
    world, arm = cell
    assert not isinstance(arm, MovesThrough)
    start, above = Pose(0.040, 0.030, 0.010), Pose(0.060, 0.045, 0.013)
    arm.move_linear(start)
    t0 = world.clock.now()
    move_via(arm, above)
    motion = world.motion_time(start, above, arm.settings.speed_m_s)
    assert world.clock.now() - t0 == pytest.approx(motion + world.config.motion.settle_s)
    assert arm.pose().xyz == pytest.approx(above.xyz, abs=1e-6)  # arrived (the driver checked it too)
