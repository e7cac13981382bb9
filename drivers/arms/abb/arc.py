"""The circular arc of a MoveC (open_abb codes 35 + 36): from where the TCP stands, through a circle point,
to an end point. Pure geometry, in mm; the driver checks the whole arc against its workspace box before
sending anything, the simulator before it moves.

The RAPID reference's limits for MoveC, as read here (to be checked on a controller): the start, the
circle point and the end at least 0.1 mm apart, and, seen from the start, at least 1 degree between the
circle point and the end (so the three points are not on one line, where no circle passes through them).
"""

from __future__ import annotations

import math

import numpy as np

MIN_DISTANCE_MM = 0.1
MIN_ANGLE_DEG = 1.0


def arc_points(start, via, end, step_mm: float = 1.0) -> np.ndarray:
    """Points (N x 3, mm) along the circle from `start` through `via` to `end`, at most `step_mm` apart, the
    three given points included. Raises ValueError naming what makes the three points no arc."""
    a, b, c = (np.asarray(p, dtype=float).reshape(3) for p in (start, via, end))
    if not all(np.isfinite(p).all() for p in (a, b, c)):
        raise ValueError("an arc point is not finite")
    for (name1, p1), (name2, p2) in ((("start", a), ("circle point", b)), (("start", a), ("end", c)),
                                     (("circle point", b), ("end", c))):
        if np.linalg.norm(p2 - p1) < MIN_DISTANCE_MM:
            raise ValueError(f"the {name1} and the {name2} of the arc are {np.linalg.norm(p2 - p1):.4f} mm apart; "
                             f"MoveC needs at least {MIN_DISTANCE_MM} mm")
    u, v = b - a, c - a
    cos_angle = float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)))
    angle = math.degrees(math.acos(max(-1.0, min(1.0, cos_angle))))
    if not MIN_ANGLE_DEG <= angle <= 180.0 - MIN_ANGLE_DEG:
        raise ValueError(f"seen from the start, the circle point and the end are {angle:.3f} degrees apart: the three "
                         f"points (nearly) lie on one line; MoveC needs {MIN_ANGLE_DEG}..{180 - MIN_ANGLE_DEG} degrees")
    w = np.cross(u, v)
    ww = float(np.dot(w, w))
    center = a + (np.dot(u, u) * np.cross(v, w) + np.dot(v, v) * np.cross(w, u)) / (2.0 * ww)
    radius = float(np.linalg.norm(a - center))
    e1 = (a - center) / radius
    e2 = np.cross(w / math.sqrt(ww), e1)  # a -> b -> c runs counter-clockwise about w

    def angle_of(p) -> float:
        d = p - center
        return math.atan2(float(np.dot(d, e2)), float(np.dot(d, e1))) % math.tau

    sweep = angle_of(c)
    n = max(2, min(100_000, math.ceil(sweep * radius / step_mm) + 1))
    angles = np.union1d(np.linspace(0.0, sweep, n), [angle_of(b)])
    points = center + radius * (np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2)
    points[0], points[-1] = a, c
    return points


def arc_length(points: np.ndarray) -> float:
    """Length (mm) of the polyline through `points` (close to the arc's for a fine step)."""
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
