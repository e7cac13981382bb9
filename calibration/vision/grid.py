"""Number the dots of a photographed calibration grid by row and column.

The grid's frame (seed 001 section 6.1.1): origin at the top-left dot seen, x along
the rows, y down the columns, as they run in the image. Dots cut by the image
border are left out (their centres would be biased); the rest are numbered on the
lattice, so a grid a little larger than the field of view still calibrates.
"""

from __future__ import annotations

import numpy as np

from calibration.errors import VisionError
from calibration.vision.centroid import Blob


def order_grid(blobs: list[Blob], rows: int, cols: int, min_fraction: float = 0.75) -> list[tuple[int, int, Blob]]:
    """(column i, row j, blob) for every dot seen; VisionError unless they form (most of) a rows x cols lattice."""
    need = max(9, int(np.ceil(min_fraction * rows * cols)))
    if not need <= len(blobs) <= rows * cols:
        raise VisionError(f"found {len(blobs)} dots; expected {need} to {rows * cols} of a {cols} x {rows} grid: "
                          "check that the grid is in view, in focus and evenly lit")
    p = np.array([[b.u, b.v] for b in blobs])
    middle = int(np.argmin(np.linalg.norm(p - p.mean(axis=0), axis=1)))
    d = p - p[middle]
    near = d[np.argsort(np.linalg.norm(d, axis=1))[1:5]]  # the four neighbours of an inner dot
    a = near[np.argmax(near[:, 0])]  # along the rows, towards +u
    b = near[np.argmax(near[:, 1])]  # down the columns, towards +v
    if abs(a[0] * b[1] - a[1] * b[0]) < 0.5 * np.linalg.norm(a) * np.linalg.norm(b):
        raise VisionError("the dots do not form a regular lattice; is the grid distorted, or rotated by 45 degrees?")
    ij = np.linalg.solve(np.column_stack([a, b]), d.T).T
    index = np.rint(ij).astype(int)
    if np.max(np.abs(ij - index)) > 0.3:
        raise VisionError("the dots are too far from a regular lattice to be numbered; check the grid and the focus")
    index -= index.min(axis=0)
    if index[:, 0].max() >= cols or index[:, 1].max() >= rows or len({tuple(x) for x in index}) != len(index):
        raise VisionError(f"the dots span {index[:, 0].max() + 1} x {index[:, 1].max() + 1} positions; "
                          f"a {cols} x {rows} grid was expected")
    return [(int(i), int(j), blob) for (i, j), blob in zip(index, blobs)]
