"""sim.faults.random: faults drawn from one seeded stream per process, so a job's fresh world (its resumption)
meets new draws where a count knob would fire again at the same call."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from drivers.interfaces import ConnectionLost, DeviceError, Pose, ProtectiveStop
from drivers.limits import WorkspaceBox
from drivers.sim.base import RandomFaults
from drivers.sim.devices import SimArm
from drivers.sim.fault_dice import drawn
from drivers.sim.micro.world import World

BOX = WorkspaceBox(x_mm=(-10, 160), y_mm=(-10, 110), z_mm=(-5, 40))


def world_with(microcell_sim, **random):
    faults = microcell_sim.faults.model_copy(update={"random": RandomFaults(**random)})
    return World(microcell_sim.model_copy(update={"faults": faults}))


def moves_until_a_fault(world, limit: int = 2000) -> tuple[int, DeviceError]:
    arm = SimArm("arm", world, SimArm.Settings(limits=BOX))
    arm.connect()
    for n in range(1, limit + 1):
        try:
            arm.move_linear(Pose(0.040 + 1e-5 * (n % 2), 0.030, 0.0))
        except DeviceError as exc:
            return n, exc
    raise AssertionError(f"no fault in {limit} moves")


def test_faults_fall_at_their_rate_and_a_fresh_world_goes_on_where_the_last_stopped(microcell_sim):
    # a seed of this test's own: the stream is the process's, and other tests' worlds must not share it
    at = [moves_until_a_fault(world_with(microcell_sim, seed=90210, link_drop=0.02, protective_stop=0.02))
          for _ in range(40)]
    kinds = {type(exc) for _, exc in at}
    assert kinds == {ConnectionLost, ProtectiveStop}, kinds
    assert all("at random" in str(exc) for _, exc in at)
    mean = sum(n for n, _ in at) / len(at)
    assert 12 < mean < 45, mean  # one fault in 25 moves on average
    # each fresh world met its fault at its own move, not all at the same count as a count knob would
    assert len({n for n, _ in at}) > 10


def test_no_fault_without_chances_and_the_stream_left_alone(microcell_sim):
    quiet = RandomFaults(seed=90211)
    assert drawn(None, "move") is None and drawn(quiet, "capture") is None
    world = world_with(microcell_sim, seed=90211)
    arm = SimArm("arm", world, SimArm.Settings(limits=BOX))
    arm.connect()
    for n in range(50):
        arm.move_linear(Pose(0.040 + 1e-5 * (n % 2), 0.030, 0.0))


@pytest.mark.parametrize("bad", [{"link_drop": 0.5}, {"corrupt_frame": -0.1}, {"seed": -1}, {"flood": 0.1}])
def test_bad_chances_are_refused_naming_the_knob(bad):
    with pytest.raises(ValidationError) as info:
        RandomFaults(**bad)
    assert next(iter(bad)) in str(info.value)
