"""locate's sigma_um is honest: over 100 pixels spread over a camera's field, the true error of the located point
(against the simulated world, seed 5 after calibrate-cell) divided by its sigma has an RMS between 0.5 and 2.

The truth of a pixel: the commanded position at alpha_cal that puts the feature exactly where the pixel looks, the
bare nozzle in camera 1's focal plane, a sphere of nominal size resting on the substrate for camera 2 (located with
the apparent diameter such a sphere has there, as a user locates one)."""

import math

import numpy as np
import pytest

from cellctl.config import load_cell_file
from cellctl.errors import Unavailable
from cellctl.runs import with_seed
from cellctl.service.local import LocalService
from drivers.sim.truth import true_command_for_pixel
from drivers.sim.world import World
from tests.conftest import MICROCELL

LOCATE_KEYS = {"camera", "u_px", "v_px", "x_mm", "y_mm", "sigma_um", "calibration_id", "version", "health",
               "calibrations"}


def field_pixels(width: int, height: int, n: int = 10, edge: float = 0.05) -> np.ndarray:
    """n x n pixels spread evenly over the image, `edge` of it kept clear of the border."""
    us = np.linspace(edge * width, (1 - edge) * width, n)
    vs = np.linspace(edge * height, (1 - edge) * height, n)
    return np.array([(u, v) for v in vs for u in us])


def apparent_diameter_px(world, camera: str, uv: np.ndarray, z: float, alpha: float, diameter: float) -> np.ndarray:
    """The diameter in pixels of a sphere of `diameter` centred at height z: over the true local scale."""
    def at(d):
        return true_command_for_pixel(world, camera, uv + d, z, alpha)
    du, dv = at([0.5, 0.0]) - at([-0.5, 0.0]), at([0.0, 0.5]) - at([0.0, -0.5])
    return diameter / np.sqrt(np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]))


@pytest.mark.parametrize("camera, area", [("cam1", "area1"), ("cam2", "area2")])
def test_sigma_is_honest_over_the_field(calibrated_cell, tmp_path, camera, area):
    config, _ = load_cell_file(MICROCELL)
    config = with_seed(config, calibrated_cell.seed)
    world = World(config.sim)  # the same static truth the calibration ran on: drawn from the seed
    service = LocalService.of_store(config, calibrated_cell.store_copy(tmp_path / "store"))
    a = config.areas_by_name()[area]
    uv = field_pixels(*config.sim.cameras[camera].resolution_px)
    if camera == "cam2":
        z = config.sim.floor_z_mm * 1e-3 + config.sim.spheres.diameter_mm * 0.5e-3
        diameters = apparent_diameter_px(world, camera, uv, z, a.alpha_cal, config.sim.spheres.diameter_mm * 1e-3)
    else:
        z, diameters = a.z, [None] * len(uv)
    true = true_command_for_pixel(world, camera, uv, z, a.alpha_cal) * 1e3
    answers = [service.locate(camera, float(u), float(v), diameter_px=None if d is None else float(d))
               for (u, v), d in zip(uv, diameters)]
    assert all(set(r) == LOCATE_KEYS for r in answers)
    err_um = (np.array([[r["x_mm"], r["y_mm"]] for r in answers]) - true) * 1e3
    sigma_um = np.array([r["sigma_um"] for r in answers])
    ratio_rms = math.sqrt(np.mean((err_um / sigma_um[:, None]) ** 2))
    print(f"{camera}: error/sigma RMS {ratio_rms:.2f} over {len(uv)} pixels; error RMS per axis "
          f"{np.sqrt(np.mean(err_um ** 2)):.2f} µm, sigma mean {sigma_um.mean():.2f} µm")
    assert 0.5 <= ratio_rms <= 2.0
    first = answers[0]
    assert first["calibration_id"] == first["calibrations"][camera] and first["version"] == 1
    assert first["health"] == "unchecked"  # no check has run on this store


def test_locate_says_what_it_used_and_features_needs_the_daemon(calibrated_cell, tmp_path):
    config, _ = load_cell_file(MICROCELL)
    store = calibrated_cell.store_copy(tmp_path / "store")
    service = LocalService.of_store(config, store)
    where = service.locate("cam3", 1296.0, 972.0, arm_pose=(75.0, 25.0, 30.0), diameter_px=160.0)
    assert set(where) == LOCATE_KEYS and where["sigma_um"] > 0
    assert where["calibrations"] == {c.target: c.id for c in store.list() if c.active}
    with pytest.raises(Unavailable, match="needs the cell daemon"):
        service.features("cam2")
