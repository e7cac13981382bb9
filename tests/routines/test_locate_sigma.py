"""locate's sigma_um is honest: over 100 pixels spread over a camera's field, the true error of the located point
(against the simulated world, seed 5 after calibrate-cell) divided by its sigma has an RMS between 0.5 and 2.

The truth of a pixel: the commanded position at alpha_cal that puts the feature exactly where the pixel looks, the
bare nozzle in camera 1's focal plane, a sphere of nominal size resting on the substrate for camera 2 (located with
the apparent diameter such a sphere has there, as a user locates one)."""

import math

import numpy as np
import pytest

from drivers.sim.micro.truth import true_command_for_pixel
from drivers.sim.micro.world import World

from calibration.usage import CellCalibration

from cellctl.config import load_cell_file
from cellctl.core.runs import with_seed
from cellctl.errors import InvalidRequest, NotFound, Unavailable
from cellctl.service.local import LocalService

from tests.conftest import MICROCELL

LOCATE_KEYS = {"camera", "u_px", "v_px", "x_mm", "y_mm", "sigma_um", "outside_calibrated_region", "warning",
               "calibration_id", "version", "health", "calibrations"}


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
    assert 0.5 <= ratio_rms <= 2.0
    first = answers[0]
    assert first["calibration_id"] == first["calibrations"][camera] and first["version"] == 1
    assert first["health"] == "unchecked"  # no check has run on this store


def truth_at(config, world, camera: str, area: str, uv: np.ndarray):
    """The true position (mm) of what each pixel shows, and the diameters to locate with (camera 2: spheres)."""
    a = config.areas_by_name()[area]
    if camera == "cam2":
        z = config.sim.floor_z_mm * 1e-3 + config.sim.spheres.diameter_mm * 0.5e-3
        diameters = apparent_diameter_px(world, camera, uv, z, a.alpha_cal, config.sim.spheres.diameter_mm * 1e-3)
    else:
        z, diameters = a.z, [None] * len(uv)
    return true_command_for_pixel(world, camera, uv, z, a.alpha_cal) * 1e3, diameters


@pytest.mark.parametrize("camera, area", [("cam1", "area1"), ("cam2", "area2")])
def test_outside_the_calibrated_region_locate_warns_and_its_grown_sigma_stays_honest(calibrated_cell, tmp_path,
                                                                                    camera, area):
    """Just outside the hull of the calibration's pixels (30 px beyond each corner of it that is still on the image):
    the answer says so, its sigma is larger than at the corner, and the true error stays within 3 sigma. Inside:
    no warning, and x, y, sigma are the calibration's own answer, unchanged."""
    config, _ = load_cell_file(MICROCELL)
    config = with_seed(config, calibrated_cell.seed)
    world = World(config.sim)
    store = calibrated_cell.store_copy(tmp_path / "store")
    service = LocalService.of_store(config, store)
    cam_map = CellCalibration(store.active_models()).camera_map(camera)
    corners = np.array(cam_map.region)
    outward = (corners - corners.mean(axis=0)) / np.linalg.norm(corners - corners.mean(axis=0), axis=1)[:, None]
    beyond = corners + 30 * outward
    keep = cam_map.on_image(beyond)
    corners, beyond = corners[keep], beyond[keep]
    assert len(corners) >= 4

    def locate(uv, diameters):
        return [service.locate(camera, float(u), float(v), diameter_px=None if d is None else float(d))
                for (u, v), d in zip(uv, diameters)]

    true, diameters = truth_at(config, world, camera, area, beyond)
    outside = locate(beyond, diameters)
    at_corner = locate(corners, truth_at(config, world, camera, area, corners)[1])
    assert all(r["outside_calibrated_region"] is True and "outside the calibrated region" in r["warning"]
               for r in outside)
    assert all(r["outside_calibrated_region"] is False and r["warning"] is None for r in at_corner)
    grown = np.array([r["sigma_um"] for r in outside]) / np.array([r["sigma_um"] for r in at_corner])
    err_um = (np.array([[r["x_mm"], r["y_mm"]] for r in outside]) - true) * 1e3
    ratio = np.abs(err_um) / np.array([r["sigma_um"] for r in outside])[:, None]
    assert (grown > 1.0).all() and ratio.max() <= 3.0

    centre = corners.mean(axis=0)  # inside: the calibration's answer as it always was
    d = truth_at(config, world, camera, area, centre[None])[1][0]
    inside = locate([centre], [d])[0]
    xy, sigma = CellCalibration(store.active_models()).locate_with_sigma(camera, [centre], None, d)
    assert inside["outside_calibrated_region"] is False and inside["warning"] is None
    assert (inside["x_mm"], inside["y_mm"], inside["sigma_um"]) == (xy[0][0] * 1e3, xy[0][1] * 1e3, sigma[0] * 1e6)


def test_locate_refuses_a_pixel_off_the_image_and_an_unknown_camera(calibrated_cell, tmp_path):
    config, _ = load_cell_file(MICROCELL)
    store = calibrated_cell.store_copy(tmp_path / "store")
    service = LocalService.of_store(config, store)
    with pytest.raises(InvalidRequest, match=r"^pixel \(99999, -5\) is outside cam1's 2448 x 2050 image: allowed "
                                             r"u_px -0.5 to 2447.5, v_px -0.5 to 2049.5$"):
        service.locate("cam1", 99999.0, -5.0)
    with pytest.raises(NotFound, match=r"^no camera 'cam9'; cameras: cam1, cam2, cam3$"):
        service.locate("cam9", 1.0, 1.0)
    # a calibration made before the region was kept: nothing is claimed either way
    model = store.active("cam1").result
    model["model"]["map"].pop("region_px")
    older = store.save("cam1", model, "")
    where = service.locate("cam1", 5.0, 5.0)
    assert where["calibration_id"] == older.id
    assert where["outside_calibrated_region"] is None and where["warning"] is None


def test_locate_says_what_it_used_and_features_needs_the_daemon(calibrated_cell, tmp_path):
    config, _ = load_cell_file(MICROCELL)
    store = calibrated_cell.store_copy(tmp_path / "store")
    service = LocalService.of_store(config, store)
    where = service.locate("cam3", 1296.0, 972.0, arm_pose=(75.0, 25.0, 30.0), diameter_px=160.0)
    assert set(where) == LOCATE_KEYS and where["sigma_um"] > 0
    assert where["calibrations"] == {c.target: c.id for c in store.list() if c.active}
    with pytest.raises(Unavailable, match="needs the cell daemon"):
        service.features("cam2")
