import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.errors import CalibrationInputError
from calibration.models.rototranslation import Rototranslation, fit_rototranslation


@settings(max_examples=40, deadline=None)
@given(theta=st.floats(-np.pi, np.pi), x0=st.floats(-200, 200), y0=st.floats(-200, 200),
       n=st.integers(2, 20), seed=st.integers(0, 2**31))
def test_recovers_the_transform_from_exact_points(theta, x0, y0, n, seed):
    truth = Rototranslation(theta, x0, y0)
    cam = np.random.default_rng(seed).uniform(-8, 8, (n, 2))
    if np.ptp(cam, axis=0).max() < 1e-3:
        return
    fit = fit_rototranslation(cam, truth.apply(cam))
    np.testing.assert_allclose(fit.apply(cam), truth.apply(cam), atol=1e-9)
    np.testing.assert_allclose(fit.inverse(fit.apply(cam)), cam, atol=1e-9)


def test_noisy_points_within_their_uncertainty():
    rng = np.random.default_rng(3)
    truth = Rototranslation(0.3, 40.0, 30.0)
    errors = []
    for _ in range(200):
        cam = rng.uniform(-6, 6, (4, 2))
        fit = fit_rototranslation(cam, truth.apply(cam) + rng.normal(0, 0.002, (4, 2)))
        errors.append((fit.theta - truth.theta) / np.sqrt(fit.covariance[0, 0]))
    assert 0.6 < np.std(errors) < 1.6  # the reported covariance is honest


@pytest.mark.parametrize("cam, robot, message", [
    ([[0, 0]], [[1, 1]], "at least 2 points"),
    ([[0, 0], [0, 0]], [[1, 1], [1, 1]], "coincide"),
    ([[0, 0], [np.nan, 1]], [[1, 1], [2, 2]], "NaN"),
    ([[0, 0, 0]], [[1, 1]], "equal shape"),
])
def test_bad_input(cam, robot, message):
    with pytest.raises(CalibrationInputError, match=message):
        fit_rototranslation(cam, robot)
