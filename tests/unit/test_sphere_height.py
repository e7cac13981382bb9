"""Sphere heights from apparent diameters: a tilted pinhole camera looking down on spheres of several sizes."""

import numpy as np
import pytest

from calibration.models.planar import PlanarModelOptions, fit_planar_map
from calibration.models.sphere_height import SphereHeights, camera_centre, local_scale

W = 0.25  # camera distance to the plane of the centres of 1 mm spheres, m
F = 10_000.0  # px
SIZE = (1360, 1024)
CENTRE = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
TILT = np.radians(1.5)
AIM = np.array([0.110, 0.040])  # where the optical axis meets the plane


def camera():
    """Down-looking (u along x, v against y), tilted about the plane's y axis; its centre and rotation."""
    down = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # columns: camera axes in the plane's frame
    c, s = np.cos(TILT), np.sin(TILT)
    tilt = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    R_wc = tilt @ down  # camera axes in the world
    C = np.array([*AIM, 0.0]) - W * R_wc[:, 2]
    return C, R_wc


def project(xy, dz):
    """Pixels of sphere centres at xy standing dz above the reference plane, and their pixel diameters."""
    C, R_wc = camera()
    p = np.column_stack([np.atleast_2d(xy), dz]) - C
    cam = p @ R_wc  # camera coordinates
    uv = F * cam[:, :2] / cam[:, 2:3] + CENTRE
    return uv, (1e-3 + 2 * dz) * F / cam[:, 2]


def fitted(grid, dz):
    uv, d = project(grid, dz)
    options = PlanarModelOptions(radial_terms=0, tangential=False, fit_centre=False, loss="linear")
    plain = fit = fit_planar_map(uv, grid, SIZE, options)
    for _ in range(2):
        heights = SphereHeights.for_map(fit.map, uv, d, W)
        fit = fit_planar_map(uv, heights.to_map_plane(grid, heights.dz(fit.map, uv, d)), SIZE, options)
    return plain, fit, SphereHeights.for_map(fit.map, uv, d, W)


def test_round_trip_and_the_direction_of_the_shift():
    h = SphereHeights(W, 1e-3, AIM)
    xy = np.array([[0.120, 0.050], [0.100, 0.030]])
    dz = np.array([1e-4, -1e-4])
    seen = h.to_map_plane(xy, dz)
    # a higher sphere looks farther from the camera's foot point, a lower one nearer
    assert np.linalg.norm(seen[0] - AIM) > np.linalg.norm(xy[0] - AIM)
    assert np.linalg.norm(seen[1] - AIM) < np.linalg.norm(xy[1] - AIM)
    assert h.to_true(seen, dz) == pytest.approx(xy, abs=1e-12)
    assert SphereHeights.from_dict(h.to_dict()).to_true(seen, dz) == pytest.approx(xy, abs=1e-12)


def test_the_camera_centre_from_the_map():
    grid = np.array([[x, y] for x in np.linspace(0.095, 0.125, 5) for y in np.linspace(0.028, 0.052, 4)])
    _, fit, _ = fitted(grid, np.zeros(len(grid)))
    foot, height = camera_centre(fit.map, W)
    C, _ = camera()
    assert foot == pytest.approx(C[:2], abs=0.05e-3)  # 6.5 mm from where the axis meets the plane
    assert np.linalg.norm(C[:2] - AIM) > 6e-3
    assert height == pytest.approx(C[2], rel=1e-3)


def test_heights_from_diameters_recover_the_true_positions():
    rng = np.random.default_rng(4)
    grid = np.array([[x, y] for x in np.linspace(0.095, 0.125, 5) for y in np.linspace(0.028, 0.052, 4)])
    plain, fit, heights = fitted(grid, rng.uniform(-1e-4, 1e-4, len(grid)))
    assert local_scale(fit.map, [CENTRE]) == pytest.approx(W / F, rel=2e-3)
    test = rng.uniform([0.096, 0.029], [0.124, 0.051], (30, 2))
    dz = rng.uniform(-1e-4, 1e-4, len(test))
    uv, d = project(test, dz)
    corrected = heights.to_true(fit.map.pixel_to_plane(uv), heights.dz(fit.map, uv, d))
    err = np.linalg.norm(corrected - test, axis=1)
    assert err.max() < 0.3e-6  # what is left: the reference plane is the calibration spheres' mean height
    assert np.linalg.norm(plain.map.pixel_to_plane(uv) - test, axis=1).max() > 4e-6  # without: several µm
