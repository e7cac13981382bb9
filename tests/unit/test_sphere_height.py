"""Sphere heights from apparent diameters: a pinhole camera looking down on spheres of several sizes."""

import numpy as np
import pytest

from calibration.models.planar import PlanarModelOptions, fit_planar_map
from calibration.models.sphere_height import SphereHeights, local_scale

W = 0.25  # camera height over the plane of the sphere centres of 1 mm spheres, m
F = 10_000.0  # px
SIZE = (1360, 1024)
AXIS = np.array([0.110, 0.040])


def project(xy, dz):
    """Pixel of points at xy standing dz above the reference plane, and the pixel diameter of a sphere of
    diameter 1 mm + 2 dz there."""
    depth = W - dz
    uv = (np.atleast_2d(xy) - AXIS) * (F / depth)[:, None] + [(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]
    return uv, (1e-3 + 2 * dz) * F / depth


def test_round_trip_and_the_direction_of_the_shift():
    h = SphereHeights(W, 1e-3, AXIS)
    xy = np.array([[0.120, 0.050], [0.100, 0.030]])
    dz = np.array([1e-4, -1e-4])
    seen = h.to_map_plane(xy, dz)
    # a higher sphere looks farther from the axis, a lower one nearer
    assert np.linalg.norm(seen[0] - AXIS) > np.linalg.norm(xy[0] - AXIS)
    assert np.linalg.norm(seen[1] - AXIS) < np.linalg.norm(xy[1] - AXIS)
    assert h.to_true(seen, dz) == pytest.approx(xy, abs=1e-12)
    assert SphereHeights.from_dict(h.to_dict()).to_true(seen, dz) == pytest.approx(xy, abs=1e-12)


def test_heights_from_diameters_recover_the_true_positions():
    rng = np.random.default_rng(4)
    grid = np.array([[x, y] for x in np.linspace(0.095, 0.125, 5) for y in np.linspace(0.028, 0.052, 4)])
    dz_cal = rng.uniform(-1e-4, 1e-4, len(grid))
    uv_cal, d_cal = project(grid, dz_cal)
    options = PlanarModelOptions(radial_terms=0, tangential=False, fit_centre=False, loss="linear")
    plain = fit_planar_map(uv_cal, grid, SIZE, options)
    fit = plain
    for _ in range(2):
        heights = SphereHeights.for_map(fit.map, uv_cal, d_cal, W, SIZE)
        fit = fit_planar_map(uv_cal, heights.to_map_plane(grid, heights.dz(fit.map, uv_cal, d_cal)), SIZE, options)
    assert local_scale(fit.map, uv_cal) == pytest.approx(W / F, rel=2e-3)
    test = rng.uniform([0.096, 0.029], [0.124, 0.051], (30, 2))
    dz = rng.uniform(-1e-4, 1e-4, len(test))
    uv, d = project(test, dz)
    corrected = heights.to_true(fit.map.pixel_to_plane(uv), heights.dz(fit.map, uv, d))
    uncorrected = plain.map.pixel_to_plane(uv)
    err = np.linalg.norm(corrected - test, axis=1)
    assert err.max() < 0.3e-6  # what is left: the reference plane is the calibration spheres' mean height
    assert np.linalg.norm(uncorrected - test, axis=1).max() > 4e-6  # without it: several µm at the edges
