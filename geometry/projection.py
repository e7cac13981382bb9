"""Pinhole projection with square pixels and where cameras look from.

A point p in camera coordinates (z forward, y down) is seen at u = f p_x / p_z + c_u, v = f p_y / p_z + c_v.
"""

from __future__ import annotations

import math

import numpy as np

from geometry.transforms import look_at

# where the VR cells' overhead camera turns toward from the side camera: up, and a little in front
OVERHEAD = np.array([0.0, 0.35, 1.0]) / math.hypot(0.35, 1.0)


def unit_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """The unit vector at an azimuth (from +x toward +y) and an elevation (above the xy plane)."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def camera_direction(azimuth_deg: float, elevation_deg: float, turn_deg: float = 0.0) -> np.ndarray:
    """From the look-at point toward a camera of the VR cells' layout: the side camera at an azimuth and
    elevation; the overhead camera turned from it by the inter-camera angle toward OVERHEAD, so that at
    90 deg it looks down from above, still in front of the receptacle."""
    d = unit_direction(azimuth_deg, elevation_deg)
    w = OVERHEAD - (OVERHEAD @ d) * d
    w /= np.linalg.norm(w)
    t = math.radians(turn_deg)
    return math.cos(t) * d + math.sin(t) * w


def layout_view(target, distance: float, azimuth_deg: float, elevation_deg: float, turn_deg: float = 0.0) -> np.ndarray:
    """V (world -> camera) of a camera of the VR cells' layout: `distance` from `target` toward
    camera_direction(azimuth_deg, elevation_deg, turn_deg), looking at it."""
    return look_at(target + distance * camera_direction(azimuth_deg, elevation_deg, turn_deg), target)


def focal_px(width: int, height: int, distance: float, vfov_deg: float, view_width: float | None = None) -> float:
    """Focal length (px) of a camera `distance` from what it looks at: zoomed so that `view_width` spans the
    image there, else that of its lens's vertical field of view."""
    if view_width is not None:
        return width * distance / view_width
    return (height / 2) / math.tan(math.radians(vfov_deg) / 2)


def pinhole(points_cam: np.ndarray, f: float, cu: float, cv: float) -> np.ndarray:
    """(n, 2) pixels of (n, 3) points in camera coordinates."""
    p = points_cam
    return np.column_stack([f * p[:, 0] / p[:, 2] + cu, f * p[:, 1] / p[:, 2] + cv])


def face_footprint(poly: np.ndarray, f: float, cu: float, cv: float, width: int, height: int,
                   near: float = 1e-3):
    """Where a convex face (k, 3) in camera coordinates falls in a width x height image: its projected corners
    (k, 2) and the pixel box (u0, v0, u1, v1) around them, clipped to the image; None when the face reaches
    behind `near`, turns its back to the camera (faces are counter-clockwise seen from outside) or falls
    outside the image. What a z-buffer needs before it fills the face."""
    if np.any(poly[:, 2] <= near):
        return None
    if np.cross(poly[1] - poly[0], poly[2] - poly[0]) @ poly[0] >= 0:
        return None
    uv = pinhole(poly, f, cu, cv)
    u0, v0 = np.floor(uv.min(axis=0)).astype(int)
    u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 1
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width), min(v1, height)
    if u0 >= u1 or v0 >= v1:
        return None
    return uv, (u0, v0, u1, v1)
