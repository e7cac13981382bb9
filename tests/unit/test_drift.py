"""The drift test (calibration/models/drift.py) on synthetic readings: its false-alarm rate is what it says, and
it finds and estimates a drift that is there."""

import numpy as np

from calibration.models.drift import Group, fit_drift, leave_one_out


class Readings:
    """Readings of a camera at n points: white noise plus a correlated map error (known covariance), the covariance
    computed from a sigma estimated with `dof` degrees of freedom, as a calibration would."""

    def __init__(self, rng, n_points=24, sigma=1.7, dof=200):
        self.rng, self.n, self.sigma, self.dof = rng, 2 * n_points, sigma, dof
        points = rng.uniform(-6, 6, (n_points, 2))
        basis = np.column_stack([np.tile([1.0, 0.0], n_points), np.tile([0.0, 1.0], n_points), points.ravel()])
        self.cov = sigma**2 * (np.eye(self.n) + basis @ np.diag([0.04, 0.04, 0.001]) @ basis.T / 1.7**2)
        self.chol = np.linalg.cholesky(self.cov)
        self.design = {"cam.dx_um": np.tile([1.0, 0.0], n_points), "cam.dy_um": np.tile([0.0, 1.0], n_points)}

    def group(self, drift=(0.0, 0.0)) -> Group:
        y = self.chol @ self.rng.normal(size=self.n) + drift[0] * self.design["cam.dx_um"] \
            + drift[1] * self.design["cam.dy_um"]
        estimated = self.rng.chisquare(self.dof) / self.dof  # sigma_hat^2 / sigma^2
        return Group("area", y, self.cov * estimated, self.design, self.dof, ("cam",))


NAMES = ["cam.dx_um", "cam.dy_um"]
TRIALS = 1000  # 10 false alarms expected at 1 %, binomial sd 3.1


def test_the_false_alarm_rate_is_the_one_asked():
    readings = Readings(np.random.default_rng(0))
    fits = [fit_drift([readings.group()], NAMES) for _ in range(TRIALS)]
    alarms = sum(f.tests["cam"].p_value < 0.01 for f in fits)
    misfits = sum(f.misfit["area"].p_value < 0.01 for f in fits)
    assert 2 <= alarms <= 22 and 2 <= misfits <= 22, (alarms, misfits)


def test_an_uncertain_sigma_widens_the_test_instead_of_raising_alarms():
    """Few degrees of freedom (a camera calibrated from 12 spheres): still about 1 % false alarms."""
    readings = Readings(np.random.default_rng(1), n_points=8, dof=15)
    alarms = sum(fit_drift([readings.group()], NAMES).tests["cam"].p_value < 0.01 for _ in range(TRIALS))
    assert 2 <= alarms <= 22, alarms


def test_a_drift_is_found_and_estimated():
    fit = fit_drift([Readings(np.random.default_rng(2)).group(drift=(3.0, -1.0))], NAMES)
    (dx, sx), (dy, sy) = fit.of("cam")["dx_um"], fit.of("cam")["dy_um"]
    assert fit.tests["cam"].p_value < 1e-6
    assert abs(dx - 3.0) < 4 * sx and abs(dy + 1.0) < 4 * sy and sx < 0.6


def test_leave_one_out_on_exact_readings_leaves_nothing():
    group = Readings(np.random.default_rng(3)).group()
    group.residuals = 5.0 * group.design["cam.dx_um"] + 2.0 * group.design["cam.dy_um"]
    errors = leave_one_out([group], NAMES, "area")
    assert errors.shape == (24, 2) and np.max(np.abs(errors)) < 1e-9


def test_readings_the_model_cannot_explain_fail_the_fit():
    readings = Readings(np.random.default_rng(4))
    group = readings.group()
    group.residuals[:24] += 8.0 * (np.arange(24) % 2)  # x readings of the first half moved: no shift does that
    fit = fit_drift([group], NAMES)
    assert fit.misfit["area"].p_value < 1e-4
