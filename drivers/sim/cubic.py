"""Separable cubic (four-point Lagrange) interpolation from a coarse grid to fine sample positions: the
simulator evaluates smooth things (the inverse distortion, a far-defocused blur) on a coarse grid and
interpolates, at an error far below what a sensor resolves (fourth order in the grid step)."""

from __future__ import annotations

import numpy as np


def taps(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For positions `t` in coarse-grid index units: the index of the first of each one's four coarse
    neighbours (floor(t) - 1 .. floor(t) + 2) and their weights, shape (len(t), 4)."""
    first = np.floor(t).astype(int)
    f = t - first
    weights = np.column_stack([-f * (f - 1) * (f - 2) / 6, (f + 1) * (f - 1) * (f - 2) / 2,
                               -(f + 1) * f * (f - 2) / 2, (f + 1) * f * (f - 1) / 6])
    return first - 1, weights


def interpolate(coarse: np.ndarray, rows, cols) -> np.ndarray:
    """The coarse grid (rows, columns) at the fine positions whose `taps` are `rows` and `cols`: two small
    matrix products with the (banded) weight matrices."""
    return _matrix(rows, coarse.shape[0]) @ coarse @ _matrix(cols, coarse.shape[1]).T


def _matrix(taps_, size: int) -> np.ndarray:
    first, weights = taps_
    W = np.zeros((first.size, size))
    np.put_along_axis(W, first[:, None] + np.arange(4), weights, axis=1)
    return W
