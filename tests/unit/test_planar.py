"""The planar B1+B2 model: recovered from exact samples to numerical precision, from noisy ones
within the error the noise explains, robust to outliers, and clear about bad input."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.errors import CalibrationInputError
from calibration.models.planar import PlanarMap, PlanarModelOptions, fit_planar_map

SIZE = (2448, 2050)
PIXEL = 6.6e-6  # m per px at the focal plane (camera 1 of seed 001)


def random_map(rng, corner_px, radial_terms=2) -> PlanarMap:
    """A B1+B2 map of a camera within the budget: any rotation, mirror or not, 0-2° tilt, offset up to 0.2 m."""
    angle = rng.uniform(-np.pi, np.pi)
    mirror = rng.choice([-1.0, 1.0])
    c, s = np.cos(angle), np.sin(angle)
    A = PIXEL * np.array([[c, -s], [s, c]]) @ np.diag([mirror, 1.0])
    tilt = np.radians(rng.uniform(0, 2))
    g, h = np.tan(tilt) * PIXEL / 0.2 * np.array([np.cos(angle), np.sin(angle)])  # plane 0.2 m away
    offset = rng.uniform(-0.2, 0.2, 2)
    H = np.array([[A[0, 0], A[0, 1], offset[0]], [A[1, 0], A[1, 1], offset[1]], [g, h, 1.0]])
    H[:2, 2] -= H[:2, :2] @ [1224, 1025]  # the optical axis near the image centre
    scale = max(SIZE) / 2
    r_corner = np.hypot(SIZE[0] / 2, SIZE[1] / 2) / scale
    k = tuple(rng.uniform(-1, 1) * corner_px / scale / r_corner ** (2 * i + 3) / radial_terms for i in range(radial_terms))
    p = tuple(rng.uniform(-0.2, 0.2, 2) * corner_px / scale / r_corner**2 / 3)
    centre = (1223.5 + rng.uniform(-20, 20), 1024.5 + rng.uniform(-20, 20))
    return PlanarMap(SIZE, H, centre, scale, k, p)


def grid_pixels(rows=7, cols=8, fill=0.9):
    u = np.linspace(SIZE[0] * (1 - fill) / 2, SIZE[0] * (1 + fill) / 2, cols)
    v = np.linspace(SIZE[1] * (1 - fill) / 2, SIZE[1] * (1 + fill) / 2, rows)
    return np.array([[a, b] for b in v for a in u])


def check_pixels(rng, n=200, fill=0.9):
    lo = np.array(SIZE) * (1 - fill) / 2
    return rng.uniform(lo, np.array(SIZE) - lo, size=(n, 2))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), corner_px=st.floats(0.0, 8.0))
def test_exact_samples_are_recovered_to_numerical_precision(seed, corner_px):
    rng = np.random.default_rng(seed)
    truth = random_map(rng, corner_px)
    xy = truth.pixel_to_plane(grid_pixels())  # the true map generated the grid
    fit = fit_planar_map(grid_pixels(), xy, SIZE)
    probe = check_pixels(rng)
    err = np.linalg.norm(fit.map.pixel_to_plane(probe) - truth.pixel_to_plane(probe), axis=1)
    assert err.max() < 1e-10  # metres: 0.0001 µm
    assert not fit.rejected


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_round_trip_plane_to_pixel(seed):
    rng = np.random.default_rng(seed)
    m = random_map(rng, 8.0)
    uv = check_pixels(rng, 50, fill=1.0)
    np.testing.assert_allclose(m.plane_to_pixel(m.pixel_to_plane(uv)), uv, atol=1e-8)
    assert m.pixel_to_plane(uv[0]).shape == (1, 2)


def pinhole_camera(rng):
    """A physical camera (pinhole + Brown distortion, tilted) generating plane <-> pixel pairs."""
    import cv2

    f = 0.2 / PIXEL
    K = np.array([[f, 0, 1223.5 + rng.uniform(-5, 5)], [0, f, 1024.5 + rng.uniform(-5, 5)], [0, 0, 1]])
    r_corner = np.hypot(1224, 1025) / f
    shift = rng.uniform(3, 8) * rng.choice([-1, 1])
    dist = np.array([shift / (f * r_corner**3), 0.0, *(rng.uniform(-1, 1, 2) * 0.15 * abs(shift) / (3 * f * r_corner**2)), 0.0])
    tilt = np.radians(rng.uniform(1, 2))
    azimuth = rng.uniform(0, 2 * np.pi)
    rvec = np.array([np.cos(azimuth), np.sin(azimuth), 0]) * tilt + [0, 0, rng.uniform(-np.pi, np.pi)]
    tvec = np.array([0.0, 0.0, 0.2])

    def to_pixel(xy):
        pts = np.column_stack([xy, np.zeros(len(xy))])
        return cv2.projectPoints(pts, rvec, tvec, K, dist)[0].reshape(-1, 2)

    def to_plane(uv):  # exact inverse: undistort by fixed point, then intersect the ray with z = 0
        k1, _, p1, p2 = dist[:4]
        xd, yd = (uv[:, 0] - K[0, 2]) / f, (uv[:, 1] - K[1, 2]) / f
        x, y = xd.copy(), yd.copy()
        for _ in range(100):
            r2 = x * x + y * y
            x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / (1 + k1 * r2)
            y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / (1 + k1 * r2)
        R = cv2.Rodrigues(rvec)[0]
        out = []
        for ray in np.column_stack([x, y, np.ones_like(x)]):
            a, b, _ = np.linalg.solve(np.column_stack([R[:, 0], R[:, 1], -ray]), -tvec)
            out.append([a, b])
        return np.array(out)

    return to_pixel, to_plane


def plane_grid(rows=7, cols=8):
    x = np.linspace(-7.3e-3, 7.3e-3, cols)
    y = np.linspace(-6.0e-3, 6.0e-3, rows)
    return np.array([[a, b] for b in y for a in x])


@pytest.mark.parametrize("seed", range(5))
def test_physical_camera_is_modelled_within_a_tenth_of_a_micron(seed):
    """B2 inverts Brown distortion only approximately; the difference must stay negligible."""
    rng = np.random.default_rng(seed)
    to_pixel, to_plane = pinhole_camera(rng)
    xy = plane_grid()
    fit = fit_planar_map(to_pixel(xy), xy, SIZE)
    probe = to_pixel(rng.uniform([-7.3e-3, -6e-3], [7.3e-3, 6e-3], size=(200, 2)))
    err = np.linalg.norm(fit.map.pixel_to_plane(probe) - to_plane(probe), axis=1)
    assert err.max() < 0.1e-6


def test_noisy_samples_within_the_expected_error_and_honest_prediction():
    """σ = 1.7 µm robot noise, 56 samples, 14 parameters: the map's error at unseen pixels is about
    σ·sqrt(p/n_obs) per axis; map_std predicts it."""
    rng = np.random.default_rng(42)
    sigma = 1.7e-6
    means, predicted, actual = [], [], []
    for _ in range(20):
        to_pixel, to_plane = pinhole_camera(rng)
        xy = plane_grid()
        fit = fit_planar_map(to_pixel(xy), xy + rng.normal(0, sigma, xy.shape), SIZE)
        probe = to_pixel(rng.uniform([-7e-3, -5.8e-3], [7e-3, 5.8e-3], size=(56, 2)))
        err = np.linalg.norm(fit.map.pixel_to_plane(probe) - to_plane(probe), axis=1)
        means.append(err.mean())
        actual.append(np.sqrt(np.mean(err**2)))
        predicted.append(np.sqrt(np.mean(fit.map_std(probe) ** 2)))
        assert fit.sigma == pytest.approx(sigma, rel=0.35)
    expected_rms = sigma * np.sqrt(2 * 14 / 112)  # radial, averaged over the field
    assert np.mean(actual) < 1.5 * expected_rms
    assert np.mean(means) < 1.2e-6
    assert 0.7 < np.mean(predicted) / np.mean(actual) < 1.4


def test_outliers_are_rejected_and_listed():
    rng = np.random.default_rng(7)
    to_pixel, to_plane = pinhole_camera(rng)
    xy = plane_grid()
    noisy = xy + rng.normal(0, 1.7e-6, xy.shape)
    noisy[[5, 30]] += [50e-6, -50e-6]
    fit = fit_planar_map(to_pixel(xy), noisy, SIZE)
    assert sorted(r["index"] for r in fit.rejected) == [5, 30]
    assert fit.inliers.sum() == 54
    probe = to_pixel(plane_grid(5, 5) * 0.9)
    err = np.linalg.norm(fit.map.pixel_to_plane(probe) - to_plane(probe), axis=1)
    assert err.max() < 3e-6


def test_options_fewer_parameters():
    rng = np.random.default_rng(1)
    truth = random_map(rng, 5.0, radial_terms=1)
    truth = PlanarMap(truth.image_size, truth.H, (1223.5, 1024.5), truth.scale, truth.radial, (0.0, 0.0))
    uv = grid_pixels(4, 4)
    fit = fit_planar_map(uv, truth.pixel_to_plane(uv), SIZE,
                         PlanarModelOptions(radial_terms=1, tangential=False, fit_centre=False))
    assert len(fit.param_names) == 9
    np.testing.assert_allclose(fit.map.pixel_to_plane(uv), truth.pixel_to_plane(uv), atol=1e-12)
    with pytest.raises(ValueError, match="radial_terms"):
        PlanarModelOptions(radial_terms=5)
    with pytest.raises(ValueError, match="loss"):
        PlanarModelOptions(loss="cauchy-ish")


def test_serialisation_round_trip_and_bad_documents():
    rng = np.random.default_rng(3)
    m = random_map(rng, 6.0)
    again = PlanarMap.from_dict(m.to_dict())
    uv = check_pixels(rng, 20)
    np.testing.assert_array_equal(again.pixel_to_plane(uv), m.pixel_to_plane(uv))
    d = m.to_dict()
    del d["g"]
    with pytest.raises(CalibrationInputError, match=r"missing keys \['g'\]"):
        PlanarMap.from_dict(d)
    with pytest.raises(CalibrationInputError, match="version"):
        PlanarMap.from_dict(dict(m.to_dict(), version=7))
    with pytest.raises(CalibrationInputError, match="non-numeric"):
        PlanarMap.from_dict(dict(m.to_dict(), a="x"))


GRID = grid_pixels()
XY = GRID * PIXEL


@pytest.mark.parametrize("uv, xy, message", [
    (GRID[:5], XY[:5], "5 points given; the model with 14 parameters needs at least 9"),
    (np.vstack([GRID[:-1], [[np.nan, 1.0]]]), XY, "pixel coordinates of sample 55 are not finite"),
    (GRID, np.vstack([XY[:-1], [[np.inf, 1.0]]]), "plane coordinates of sample 55"),
    (np.column_stack([np.arange(56.0), 2 * np.arange(56.0)]), XY, "pixel points are collinear"),
    (np.vstack([GRID[:-1], GRID[:1]]), XY, "sample 55 repeats the pixel"),
    (GRID, XY[:-1], "must both be (N, 2)"),
])
def test_bad_input(uv, xy, message):
    with pytest.raises(CalibrationInputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        fit_planar_map(uv, xy, SIZE)


# -- the solver and the model order ---------------------------------------------------


def noisy_pinhole_samples(rng, sigma=1.7e-6):
    to_pixel, to_plane = pinhole_camera(rng)
    xy = plane_grid()
    return to_pixel, to_plane, to_pixel(xy), xy + rng.normal(0, sigma, xy.shape)


@pytest.mark.parametrize("options", [PlanarModelOptions(select_model=False),
                                     PlanarModelOptions(radial_terms=3, tangential=False, select_model=False),
                                     PlanarModelOptions(radial_terms=1, fit_centre=False)])
def test_analytic_jacobian_matches_finite_differences(options):
    rng = np.random.default_rng(11)
    truth = random_map(rng, 8.0, radial_terms=2)
    fit = fit_planar_map(grid_pixels(), truth.pixel_to_plane(grid_pixels()), SIZE, options)
    theta = fit.theta + rng.normal(0, 1e-3, fit.theta.size) * np.maximum(np.abs(fit.theta), 1e-3)
    probe = check_pixels(rng, 30)
    J = fit.uncertainty_with(theta, fit.covariance, fit.sigma, 1).jacobian(probe)
    numeric = np.empty_like(J)
    for j in range(theta.size):
        step = 1e-5 * max(abs(theta[j]), 0.1)  # not too small: the differences must stand out of rounding
        up, down = theta.copy(), theta.copy()
        up[j] += step
        down[j] -= step
        numeric[:, j] = (fit.pixel_to_plane_with(up, probe) - fit.pixel_to_plane_with(down, probe)).ravel() / (2 * step)
    np.testing.assert_allclose(J, numeric, rtol=1e-5, atol=1e-6 * np.abs(J).max())


@pytest.mark.parametrize("select", [True, False])
def test_the_solver_reaches_the_least_squares_optimum(select):
    """scipy's Levenberg-Marquardt, started from our fit, finds nothing lower; the condition number is J's."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(5)
    to_pixel, _, uv, xy = noisy_pinhole_samples(rng)
    fit = fit_planar_map(uv, xy, SIZE, PlanarModelOptions(select_model=select))

    def residuals(theta):
        return (fit.pixel_to_plane_with(theta, uv[fit.inliers]) - xy[fit.inliers]).ravel() * 1e6

    cost = 0.5 * np.sum(residuals(fit.theta) ** 2)
    best = least_squares(residuals, fit.theta, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert cost - best.cost <= 1e-9 * cost
    probe = to_pixel(plane_grid(5, 5) * 0.9)
    assert np.abs(fit.pixel_to_plane_with(best.x, probe) - fit.map.pixel_to_plane(probe)).max() < 1e-10  # m
    singular = np.linalg.svd(fit.uncertainty().jacobian(uv[fit.inliers]), compute_uv=False)
    assert fit.condition_number == pytest.approx(singular[0] / singular[-1], rel=1e-6)


@pytest.mark.parametrize("loss", ["soft_l1", "huber"])
def test_the_robust_loss_reaches_its_minimum(loss):
    """Reweighted least squares with the loss's curvature lands where scipy's robust least squares does."""
    from scipy.optimize import least_squares

    from calibration.models import planar_solver

    rng = np.random.default_rng(7)
    _, _, uv, xy = noisy_pinhole_samples(rng)
    xy[[5, 30]] += [50e-6, -50e-6]
    model = planar_solver.Parameterisation(uv, xy, SIZE, PlanarModelOptions(select_model=False))
    every, free = np.ones(len(uv), dtype=bool), np.ones(len(model.names), dtype=bool)
    linear = model.solve(model.state(model.initial()), every, free, "linear")
    f_scale = model.robust_sigma(linear.r, free.sum())
    ours = model.solve(linear, every, free, loss, f_scale=f_scale)
    best = least_squares(lambda t: model.state(t).r.ravel(), ours.theta, loss=loss, f_scale=f_scale,
                         x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15)

    def cost(theta):
        z = (model.state(theta).r.ravel() / f_scale) ** 2
        rho = 2 * (np.sqrt(1 + z) - 1) if loss == "soft_l1" else np.where(z <= 1, z, 2 * np.sqrt(z) - 1)
        return np.sum(rho)

    assert cost(ours.theta) - cost(best.x) <= 1e-9 * cost(best.x)


@pytest.mark.parametrize("loss", ["soft_l1", "huber", "linear"])
def test_every_loss_rejects_the_outliers(loss):
    rng = np.random.default_rng(7)
    _, _, uv, xy = noisy_pinhole_samples(rng)
    xy[[5, 30]] += [50e-6, -50e-6]
    fit = fit_planar_map(uv, xy, SIZE, PlanarModelOptions(loss=loss))
    assert sorted(r["index"] for r in fit.rejected) == [5, 30]


def test_model_order_follows_the_data():
    """Exact samples keep every term they need; 56 noisy ones of a lens with k4 and tangential terms
    below the noise drop the free centre (told only by k4) and k4, and map better between the samples
    than the full model, while the covariance still predicts the error."""
    rng = np.random.default_rng(3)
    truth = random_map(rng, 8.0)  # centre up to 20 px off, k2 and k4
    xy = truth.pixel_to_plane(grid_pixels())
    assert fit_planar_map(grid_pixels(), xy, SIZE).param_names == fit_planar_map(
        grid_pixels(), xy, SIZE, PlanarModelOptions(select_model=False)).param_names
    assert len(fit_planar_map(grid_pixels(), xy, SIZE).param_names) == 14

    errors = {True: [], False: []}
    predicted, names = [], set()
    for _ in range(20):
        to_pixel, to_plane, uv, noisy = noisy_pinhole_samples(rng)
        probe = to_pixel(rng.uniform([-7e-3, -5.8e-3], [7e-3, 5.8e-3], size=(100, 2)))
        for select in (True, False):
            fit = fit_planar_map(uv, noisy, SIZE, PlanarModelOptions(select_model=select))
            err = np.linalg.norm(fit.map.pixel_to_plane(probe) - to_plane(probe), axis=1)
            errors[select].append(np.sqrt(np.mean(err**2)))
            if select:
                names.add(tuple(fit.param_names[8:]))
                predicted.append(np.sqrt(np.mean(fit.map_std(probe) ** 2)))
            else:
                assert len(fit.param_names) == 14
    assert ("k2", "p1", "p2") in names
    assert np.mean(errors[True]) < 0.95 * np.mean(errors[False])
    assert 0.7 < np.mean(predicted) / np.mean(errors[True]) < 1.4
