"""Tool orientation conventions shared by the six-axis drivers, their simulators and the routines.

The cell works with a tool pointing straight down, turned by `alpha` about the
vertical: R = Rz(alpha) · Rx(180°). ABB speaks quaternions (w first), UR rotation
vectors; both map to and from the `alpha` of `Pose`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def tool_down(alpha: float) -> Rotation:
    return Rotation.from_euler("z", alpha) * Rotation.from_euler("x", math.pi)


def quaternion_wxyz(rotation: Rotation) -> tuple[float, float, float, float]:
    x, y, z, w = rotation.as_quat()
    return (float(w), float(x), float(y), float(z))


def rotation_from_wxyz(q) -> Rotation:
    w, x, y, z = (float(v) for v in q)
    if not math.isclose(w * w + x * x + y * y + z * z, 1.0, abs_tol=1e-3):
        raise ValueError(f"quaternion {tuple(q)} is not of unit length")
    return Rotation.from_quat([x, y, z, w])


def alpha_of(rotation: Rotation) -> float:
    """The turn of the tool's x axis about the vertical (meaningful for a tool pointing down)."""
    m = rotation.as_matrix()
    return float(math.atan2(m[1, 0], m[0, 0]))


def tilt_of(rotation: Rotation) -> float:
    """Angle (rad) between the tool axis and straight down."""
    z_axis = rotation.as_matrix()[:, 2]
    return float(math.acos(np.clip(-z_axis[2], -1.0, 1.0)))
