"""Which pixels of a frame a flat shape can cover, so a render paints each shape on that window only.

A camera's pixels each have a ray (normalised image coordinates x, y: `Camera.pixel_rays`). A convex flat shape in
front of the camera projects inside the box spanned by its vertices' projections (x = X/Z, y = Y/Z); a pixel can
show the shape only if its ray lies in that box, hence only if its column's x-range and its row's y-range meet the
box. The window is the rows and columns whose ranges do, padded by a few pixels, so every pixel that the full-frame
test would paint lies inside it and the frame comes out the same to the bit. A shape that straddles the camera's
plane gets the whole frame (no box bounds it there); one wholly behind that plane, none (the flange's board, seen
from the wrist camera).
"""

from __future__ import annotations

import numpy as np

FULL = (slice(None), slice(None))
MARGIN_PX = 4  # beyond the box: float32 rounding of the rays and of the paint's own hit test is far below a pixel
BEHIND_M = 1e-4  # a shape this far behind the camera's plane, all of it, is out of view (rounding: ~1e-7 m)


class RayBounds:
    """Per column, the least and the greatest x of its pixels' rays; per row, the same of y."""

    def __init__(self, x: np.ndarray, y: np.ndarray):
        self.col_lo, self.col_hi = x.min(axis=0).astype(float), x.max(axis=0).astype(float)
        self.row_lo, self.row_hi = y.min(axis=1).astype(float), y.max(axis=1).astype(float)
        h, w = x.shape
        self.margin = MARGIN_PX * float(abs(x[h // 2, w // 2 + 1] - x[h // 2, w // 2]))

    def window(self, vertices: np.ndarray) -> tuple[slice, slice] | None:
        """(rows, columns) of the pixels whose rays can meet the convex polygon with these vertices (n, 3 in the
        camera frame); FULL when it straddles the camera's plane; None when no pixel can see it."""
        z = vertices[:, 2]
        if np.all(z < -BEHIND_M):
            return None  # wholly behind the camera: a ray meets its plane in front of the camera, never the shape
        if not np.all(z > 1e-9):
            return FULL
        px, py = vertices[:, 0] / z, vertices[:, 1] / z
        cols = np.flatnonzero((self.col_hi >= px.min() - self.margin) & (self.col_lo <= px.max() + self.margin))
        rows = np.flatnonzero((self.row_hi >= py.min() - self.margin) & (self.row_lo <= py.max() + self.margin))
        if not len(cols) or not len(rows):
            return None
        return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def octagon(centre: np.ndarray, u: np.ndarray, v: np.ndarray, radius: float) -> np.ndarray:
    """(8, 3) vertices of the regular octagon about a disc of `radius` at `centre` in the plane of unit vectors u, v
    (the disc lies inside it)."""
    angles = np.arange(8) * (np.pi / 4)
    r = radius / np.cos(np.pi / 8)
    return centre + r * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
