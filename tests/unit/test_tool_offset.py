"""The tool-offset fit (seed 001 section 8.1): eliminating each position's centre gives the full stack's answer."""

import numpy as np

from calibration.models.tool_offset import fit_tool_offset, rot


def stacked(ids, alpha, xy):
    """The fit as the module describes it: one linear least squares in (P_1 .. P_K, d)."""
    positions, index = np.unique(ids, return_inverse=True)
    n, K = len(ids), len(positions)
    A = np.zeros((2 * n, 2 * K + 2))
    for i, (k, a) in enumerate(zip(index, alpha)):
        A[2 * i:2 * i + 2, 2 * k:2 * k + 2] = np.eye(2)
        A[2 * i:2 * i + 2, -2:] = rot(a) - np.eye(2)
    solution, *_ = np.linalg.lstsq(A, xy.ravel(), rcond=None)
    residuals = (xy.ravel() - A @ solution).reshape(n, 2)
    sigma2 = np.sum(residuals**2) / (2 * n - A.shape[1])
    return solution[-2:], sigma2 * np.linalg.inv(A.T @ A)[-2:, -2:], residuals


def test_the_offset_its_covariance_and_residuals_are_the_full_stacks():
    rng = np.random.default_rng(3)
    d = np.array([-68.7e-6, 137.2e-6])
    ids = np.repeat([4, 1, 9], [18, 7, 12])  # positions seen a different number of times, in any order
    alpha = rng.uniform(0, 2 * np.pi, ids.size)
    centres = {4: [0.01, 0.02], 1: [0.03, 0.0], 9: [-0.01, 0.005]}
    xy = np.array([centres[k] + (rot(a) - np.eye(2)) @ d for k, a in zip(ids, alpha)])
    xy += rng.normal(0, 1.7e-6, xy.shape)
    fit = fit_tool_offset(ids, alpha, xy)
    want, cov, residuals = stacked(ids, alpha, xy)
    np.testing.assert_allclose([fit.dx, fit.dy], want, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(fit.covariance, cov, rtol=1e-7, atol=1e-25)
    np.testing.assert_allclose(fit.residuals, residuals, atol=1e-15)
    assert np.hypot(fit.dx - d[0], fit.dy - d[1]) < 3e-6
