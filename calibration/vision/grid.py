"""Order the dots of a photographed calibration grid into rows and columns.

The grid's frame (seed 001 section 6.1.1): origin at the top-left dot of the image,
x along the topmost row, y orthogonal and downwards in the image.
"""

from __future__ import annotations

import numpy as np

from ..errors import VisionError
from .centroid import Blob


def order_grid(blobs: list[Blob], rows: int, cols: int) -> list[tuple[int, int, Blob]]:
    """(column i, row j, blob) for every dot; VisionError unless exactly a rows x cols lattice is seen."""
    if len(blobs) != rows * cols:
        raise VisionError(f"found {len(blobs)} dots; a {cols} x {rows} grid has {rows * cols}: "
                          "check that the whole grid is in view and evenly lit")
    p = np.array([[b.u, b.v] for b in blobs])
    origin = int(np.argmin(p[:, 0] + p[:, 1]))
    d = p - p[origin]
    near = np.argsort(np.linalg.norm(d, axis=1))[1:3]  # the two neighbours of a corner dot
    a, b = d[near[0]], d[near[1]]
    if abs(a[0]) < abs(b[0]):
        a, b = b, a  # a: along the row (mostly +u); b: down the column (mostly +v)
    if a[0] <= 0 or b[1] <= 0 or abs(np.cross(a, b)) < 0.5 * np.linalg.norm(a) * np.linalg.norm(b):
        raise VisionError("the dots do not form a regular grid from the top-left dot; is the grid distorted or cut?")
    ij = np.linalg.solve(np.column_stack([a, b]), d.T).T
    index = np.rint(ij).astype(int)
    if np.max(np.abs(ij - index)) > 0.3:
        raise VisionError("the dots are too far from a regular lattice to be numbered; check the grid and the focus")
    seen = {tuple(x) for x in index}
    expected = {(i, j) for i in range(cols) for j in range(rows)}
    if seen != expected:
        raise VisionError(f"the dots do not number as a {cols} x {rows} grid from the top-left "
                          f"(missing {sorted(expected - seen)[:3]}...); is the grid rotated by more than 45 degrees?")
    return [(int(i), int(j), blob) for (i, j), blob in zip(index, blobs)]
