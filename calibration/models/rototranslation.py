"""Planar rototranslation between camera and robot frames (seed 001 eq. 1, section 6.1.1).

    [x_r, y_r]^T = R(theta) [x_c, y_c]^T + [x_0, y_0]^T

First estimate from two points (the angle between the same pair of points seen in
both frames, then the offset from one point); then the seed's iterated linearised
least squares over all n points: linearise about theta_e, solve for
(d_theta, x_0, y_0) with the pseudo-inverse, update, repeat until the step is
negligible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.errors import CalibrationInputError


@dataclass(frozen=True)
class Rototranslation:
    theta: float  # rad
    x0: float
    y0: float
    iterations: int = 0
    covariance: np.ndarray | None = None  # of (theta, x0, y0)

    def apply(self, xy_camera) -> np.ndarray:
        p = np.atleast_2d(np.asarray(xy_camera, dtype=float))
        c, s = np.cos(self.theta), np.sin(self.theta)
        return p @ np.array([[c, s], [-s, c]]) + [self.x0, self.y0]

    def inverse(self, xy_robot) -> np.ndarray:
        p = np.atleast_2d(np.asarray(xy_robot, dtype=float)) - [self.x0, self.y0]
        c, s = np.cos(self.theta), np.sin(self.theta)
        return p @ np.array([[c, -s], [s, c]])

    def to_dict(self) -> dict:
        return {"model": "rototranslation-2d", "theta_rad": self.theta, "x0": self.x0, "y0": self.y0}


def fit_rototranslation(xy_camera, xy_robot, max_iterations: int = 20, tol: float = 1e-12) -> Rototranslation:
    c = np.asarray(xy_camera, dtype=float)
    r = np.asarray(xy_robot, dtype=float)
    if c.ndim != 2 or c.shape[1] != 2 or c.shape != r.shape:
        raise CalibrationInputError(f"rototranslation needs two (n, 2) arrays of equal shape, got {c.shape} and {r.shape}")
    if len(c) < 2:
        raise CalibrationInputError(f"rototranslation needs at least 2 points, got {len(c)}")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r))):
        raise CalibrationInputError("rototranslation points contain NaN or infinite values")
    # the two points farthest apart give the best-conditioned first angle
    d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    if d[i, j] <= 0:
        raise CalibrationInputError("rototranslation points coincide: at least 2 distinct points are needed")
    theta = (np.arctan2(*(r[j] - r[i])[::-1]) - np.arctan2(*(c[j] - c[i])[::-1]))
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 - read after the loop
        cos, sin = np.cos(theta), np.sin(theta)
        A = np.zeros((2 * len(c), 3))
        A[0::2, 0] = -sin * c[:, 0] - cos * c[:, 1]
        A[1::2, 0] = cos * c[:, 0] - sin * c[:, 1]
        A[0::2, 1] = 1.0
        A[1::2, 2] = 1.0
        rotated = c @ np.array([[cos, sin], [-sin, cos]])
        B = (r - rotated).ravel()
        L = np.linalg.pinv(A) @ B
        theta += L[0]
        if abs(L[0]) < tol:
            break
    x0, y0 = L[1], L[2]
    model = Rototranslation(float(np.arctan2(np.sin(theta), np.cos(theta))), float(x0), float(y0), iterations)
    dof = 2 * len(c) - 3
    if dof > 0:
        res = (model.apply(c) - r).ravel()
        cov = (res @ res / dof) * np.linalg.pinv(A.T @ A)
        model = Rototranslation(model.theta, model.x0, model.y0, iterations, cov)
    return model
