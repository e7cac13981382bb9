"""End-effector offset from the rotation axis (seed 001 section 8.1).

Rotating the tool by alpha_j (relative to alpha_cal) about the vertical axis moves the
nozzle by dP_j = (R(alpha_j) - I) [dx, dy]^T, where (dx, dy) is the nozzle's offset
from the axis at alpha_cal. The seed solves the stacked system dP = A [dx, dy]^T
with the pseudo-inverse, dP measured against the alpha_cal measurement of the same
position. Here each position's centre P_k is an unknown too, so the alpha_cal
measurement carries no more weight than the others:

    m_kj = P_k + (R(alpha_j) - I) d,    linear least squares in (P_1 .. P_K, d).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.errors import CalibrationInputError


def rot(alpha):
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[c, -s], [s, c]])


@dataclass(frozen=True)
class ToolOffset:
    dx: float
    dy: float
    covariance: np.ndarray  # 2x2 of (dx, dy)
    sigma: float  # residual std per axis
    residuals: np.ndarray  # (N, 2) measured minus model

    def shift(self, alpha_rel: float) -> np.ndarray:
        """Where the nozzle moves when the tool turns by alpha_rel from alpha_cal."""
        return (rot(alpha_rel) - np.eye(2)) @ [self.dx, self.dy]

    def compensated_target(self, target_xy, alpha_rel: float) -> np.ndarray:
        """The command that puts the nozzle at target_xy (as calibrated at alpha_cal) when turned by alpha_rel."""
        return np.asarray(target_xy, dtype=float) - self.shift(alpha_rel)


def fit_tool_offset(position_ids, alpha_rel, xy) -> ToolOffset:
    ids = np.asarray(position_ids)
    alpha = np.asarray(alpha_rel, dtype=float)
    xy = np.asarray(xy, dtype=float)
    n = len(ids)
    if xy.shape != (n, 2) or alpha.shape != (n,):
        raise CalibrationInputError(f"tool offset fit needs matching pos_id, alpha and (x, y) rows, got {n}, "
                                    f"{alpha.shape} and {xy.shape}")
    if not (np.all(np.isfinite(alpha)) and np.all(np.isfinite(xy))):
        bad = int(np.nonzero(~(np.isfinite(alpha) & np.all(np.isfinite(xy), axis=1)))[0][0])
        raise CalibrationInputError(f"tool offset sample {bad} has a non-finite angle or position")
    positions, index = np.unique(ids, return_inverse=True)
    spread = [np.ptp(np.mod(alpha[index == k], 2 * np.pi)) for k in range(len(positions))]
    if max(spread, default=0.0) < np.radians(10):
        raise CalibrationInputError("the rotations span less than 10 degrees at every position: "
                                    "the offset cannot be seen; rotate through a wide range (e.g. 360 in 20 degree steps)")
    # each position's centre is the mean of its measurements less the offset's turn there: eliminating the
    # centres leaves a least squares in d alone on the rows centred per position, with exactly the solution
    # of the full stack (P_1 .. P_K, d) and the same covariance of d (its Schur complement), in O(n)
    c, s = np.cos(alpha) - 1.0, np.sin(alpha)
    turn = np.stack([np.column_stack([c, -s]), np.column_stack([s, c])], axis=1)  # (n, 2, 2): R(alpha) - I
    counts = np.bincount(index)[:, None, None]

    def centred(x):
        sums = np.zeros((len(positions),) + x.shape[1:])
        np.add.at(sums, index, x)
        return x - (sums / counts.reshape((-1,) + (1,) * (x.ndim - 1)))[index]

    turn_c, xy_c = centred(turn), centred(xy)
    normal = np.einsum("nij,nik->jk", turn_c, turn_c)
    solve = np.linalg.pinv(normal)
    d = solve @ np.einsum("nij,ni->j", turn_c, xy_c)
    residuals = xy_c - turn_c @ d
    dof = max(2 * n - 2 * len(positions) - 2, 1)
    sigma = float(np.sqrt(np.sum(residuals**2) / dof))
    return ToolOffset(float(d[0]), float(d[1]), sigma**2 * solve, sigma, residuals)
