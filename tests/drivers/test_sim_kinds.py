"""The world-kind table: every cell file builds the world of its kind, its fakes run on it and on no other."""

import pytest

from drivers.interfaces import ConnectionLost, DeviceState, Pose, ProtectiveStop
from drivers.registry import DriverContext, backend_class
from drivers.sim.base import SimWorld
from drivers.sim.kinds import WORLD_KINDS, build_world, world_kind
from drivers.sim.servers import sim_device

from cellctl.config import CellFileError, load_cell_file, parse_cell_file

from tests.conftest import ROOT

CELLS = {"micro-cell": "sim-microcell.yaml", "irb120-csm": "sim-irb120-csm.yaml", "vr": "sim-vr.yaml",
         "ur5e-handeye": "sim-ur5e-handeye.yaml"}


@pytest.fixture(scope="module")
def worlds():
    return {kind: build_world(load_cell_file(ROOT / "config" / name)[0].sim) for kind, name in CELLS.items()}


def test_every_kind_has_a_cell_file_and_builds_its_world(worlds):
    assert set(CELLS) == set(WORLD_KINDS)
    for kind, world in worlds.items():
        assert world_kind(world.config) == kind
        assert isinstance(world, SimWorld)
        assert type(world).__name__ == WORLD_KINDS[kind].world.rpartition(":")[2]


@pytest.mark.parametrize("kind", sorted(CELLS))
def test_the_fakes_of_a_cell_file_run_on_its_world_and_share_it(kind):
    config, _ = load_cell_file(ROOT / "config" / CELLS[kind])
    context = DriverContext(sim_config=config.sim)
    devices = [backend_class(device, dev.backend).create(name, dev.options, context)
               for device, name, dev in config.devices()]
    assert all(d.world is context.existing_world for d in devices)
    for d in devices:
        d.connect()
    camera = next(d for (device, _, _), d in zip(config.devices(), devices) if device == "camera")
    frame = camera.capture()
    assert frame.image.shape[:2] == tuple(reversed(camera.resolution))
    assert (frame.meta["sim_camera"], frame.frame_id) in context.existing_world.frame_truth


def test_a_fake_refuses_the_world_of_another_kind(worlds):
    with pytest.raises(ValueError, match=r"arm: VrArm needs a 'sim:' section with world: vr \(backend 'sim-vr'\); "
                                         r"this one has world: micro-cell"):
        backend_class("arm", "sim-vr").create("arm", {"limits": {"x_mm": (0, 1), "y_mm": (0, 1), "z_mm": (0, 1)}},
                                              DriverContext.around(worlds["micro-cell"]))
    with pytest.raises(ValueError, match=r"SimGripper needs .* world: micro-cell \(backend 'sim'\) or world: ur5e-handeye \(backend 'sim'\); "
                                         r"this one has world: vr"):
        backend_class("gripper", "sim").create("gripper", {}, DriverContext.around(worlds["vr"]))
    with pytest.raises(ValueError, match="the irb120-csm world simulates no gripper"):
        sim_device("gripper", worlds["irb120-csm"])


def test_the_cell_file_names_the_fake_its_world_offers():
    text = (ROOT / "config" / "sim-microcell.yaml").read_text().replace("  backend: sim\n", "  backend: sim-vr\n", 1)
    with pytest.raises(CellFileError, match=r"arm.backend: 'sim-vr' does not run on the simulated world "
                                            r"\(sim.world: micro-cell\); allowed: sim"):
        parse_cell_file(text)
    text = (ROOT / "config" / "sim-vr.yaml").read_text().replace("world: vr", "world: moon")
    with pytest.raises(CellFileError, match=r"sim: Input tag 'moon' .* expected tags: 'micro-cell', 'irb120-csm', 'ur5e-handeye', 'vr'"):
        parse_cell_file(text)


def test_the_fault_knobs_work_on_every_world():
    """The VR arm, which had none, now drops its link and stops as the other worlds' arms do."""
    config, _ = load_cell_file(ROOT / "config" / CELLS["vr"])
    limits = config.arm.options["limits"]
    faults = config.sim.faults.model_copy(update={"arm_drop_after_moves": 2})
    world = build_world(config.sim.model_copy(update={"faults": faults}))
    arm = sim_device("arm", world, {"limits": limits})
    start = arm.pose()
    arm.move_linear(start)
    arm.move_linear(start)
    with pytest.raises(ConnectionLost, match="simulated after 2 moves"):
        arm.move_linear(start)
    assert arm.state is DeviceState.FAULTED
    faults = config.sim.faults.model_copy(update={"protective_stop_after_moves": 1})
    arm = sim_device("arm", build_world(config.sim.model_copy(update={"faults": faults})), {"limits": limits})
    arm.move_linear(start)
    with pytest.raises(ProtectiveStop):
        arm.move_linear(Pose(start.x, start.y, start.z, orientation=start.orientation))
