"""Poses, camera placement, the objects' real shapes and a z-buffer rasteriser for the VR world.

The model file format is the one documented in calibration/models/edge_model.py
(vertices + convex faces, counter-clockwise from outside); it is read again here
because drivers never import calibration.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

INCH = 0.0254
UNITS = {"m": 1.0, "mm": 1e-3, "in": INCH}
REPO_CONFIG = Path(__file__).resolve().parents[3] / "config"


def pose(rotvec=(0, 0, 0), translation=(0, 0, 0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(rotvec, float)).as_matrix()
    T[:3, 3] = translation
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def look_at(position, target, right=(0.0, 1.0, 0.0)) -> np.ndarray:
    """V (world -> camera: z forward, y down) of a camera at `position` looking at `target`, its image x axis
    along `right` as far as the viewing direction allows (the VR cells put the insertion axis across the image)."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    z = target - position
    z /= np.linalg.norm(z)
    x = np.asarray(right, float) - (np.asarray(right, float) @ z) * z
    if np.linalg.norm(x) < 1e-9:  # looking along `right`: any perpendicular will do
        x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.vstack([x, np.cross(z, x), z])
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ position
    return V


OVERHEAD = np.array([0.0, 0.35, 1.0]) / np.hypot(0.35, 1.0)  # where the overhead camera turns toward: up, in front


def camera_direction(azimuth_deg: float, elevation_deg: float, turn_deg: float = 0.0) -> np.ndarray:
    """From the look-at point toward a camera: the side camera's direction (azimuth from +x toward +y,
    elevation), turned by `turn_deg` toward OVERHEAD (the overhead camera: the turn is the inter-camera angle;
    at 90 deg it looks down from above, still in front of the receptacle)."""
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    w = OVERHEAD - (OVERHEAD @ d) * d
    w /= np.linalg.norm(w)
    t = np.radians(turn_deg)
    return np.cos(t) * d + np.sin(t) * w


@dataclass(frozen=True)
class Solid:
    """An object's faces (object frame, metres) with their outward normals."""

    name: str
    vertices: np.ndarray
    faces: tuple[np.ndarray, ...]
    normals: np.ndarray
    albedo: np.ndarray | None = None  # relative reflectance per face


def load_solid(path: str) -> Solid:
    p = Path(path)
    if not p.exists():
        p = REPO_CONFIG / path
    d = json.loads(p.read_text())
    v = np.asarray(d["vertices"], float) * UNITS[d.get("units", "m")]
    faces = tuple(np.asarray(f, int) for f in d["faces"])
    albedo = np.asarray(d["face_albedo"], float) if "face_albedo" in d else None
    return Solid(d.get("name", p.stem), v, faces, np.array([_normal(v[f]) for f in faces]), albedo)


def _normal(poly: np.ndarray) -> np.ndarray:
    n = np.cross(poly[1] - poly[0], poly[2] - poly[0])
    return n / np.linalg.norm(n)


def rasterise(width: int, height: int, polys_cam: list[np.ndarray], f: float, cu: float, cv: float):
    """Z-buffer of convex polygons in camera coordinates: (depth, index of the nearest polygon or -1)."""
    zbuf = np.full((height, width), np.inf)
    ids = np.full((height, width), -1, np.int32)
    for k, poly in enumerate(polys_cam):
        if np.any(poly[:, 2] <= 1e-3):
            continue
        if np.cross(poly[1] - poly[0], poly[2] - poly[0]) @ poly[0] >= 0:
            continue  # facing away from the camera
        uv = np.column_stack([f * poly[:, 0] / poly[:, 2] + cu, f * poly[:, 1] / poly[:, 2] + cv])
        u0, v0 = np.floor(uv.min(axis=0)).astype(int)
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 1
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width), min(v1, height)
        if u0 >= u1 or v0 >= v1:
            continue
        # exact point sampling at pixel centres (half-plane tests): no fill-rule bias at the edges
        gv, gu = np.mgrid[v0:v1, u0:u1]
        inside = np.ones(gu.shape, bool)
        nxt = np.roll(uv, -1, axis=0)
        orient = np.sign(np.sum(uv[:, 0] * nxt[:, 1] - nxt[:, 0] * uv[:, 1]))  # the loop's turning sense
        for (ax, ay), (bx, by) in zip(uv, nxt):
            inside &= orient * ((bx - ax) * (gv - ay) - (by - ay) * (gu - ax)) >= 0
        vv, uu = np.nonzero(inside)
        if not vv.size:
            continue
        n = np.cross(poly[1] - poly[0], poly[2] - poly[0])
        rays = np.column_stack([(uu + u0 - cu) / f, (vv + v0 - cv) / f, np.ones(vv.size)])
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (n @ poly[0]) / (rays @ n)
        z = np.where(np.isfinite(z) & (z > 1e-3), z, np.inf)
        closer = z < zbuf[vv + v0, uu + u0]
        zbuf[vv[closer] + v0, uu[closer] + u0] = z[closer]
        ids[vv[closer] + v0, uu[closer] + u0] = k
    return zbuf, ids
