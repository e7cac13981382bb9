"""find_features tells the nozzle (a ring seen from below) from a sphere (a disc), on frames of the simulated cell."""

from drivers.interfaces import Pose

from calibration.vision.features import find_features

from cellctl.config import load_cell_file
from cellctl.core.cell import Cell
from cellctl.core.runs import with_seed

from tests.conftest import MICROCELL


def test_the_nozzle_is_a_ring_and_a_held_sphere_a_disc():
    config, text = load_cell_file(MICROCELL)
    with Cell(with_seed(config, 2), text) as cell:
        cell.arm.move_linear(Pose(0.040, 0.030, 0.0, 0.0))  # over camera 1, in its focal plane
        bare = find_features(cell.cameras["cam1"].capture().image)
        cell.arm.move_linear(Pose(0.070, 0.030, 0.003, 0.0))  # the feeder's sphere
        cell.arm.move_linear(Pose(0.070, 0.030, 0.0008, 0.0))
        assert cell.gripper.grip()
        cell.arm.move_linear(Pose(0.040, 0.030, 0.0005, 0.0))
        held = find_features(cell.cameras["cam1"].capture().image)
    assert [f.kind for f in bare] == ["nozzle"]
    assert [f.kind for f in held] == ["sphere"]
    assert held[0].blob.diameter_px > 1.5 * bare[0].blob.diameter_px
