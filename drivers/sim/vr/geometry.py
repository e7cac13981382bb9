"""The objects' real shapes and a z-buffer rasteriser for the VR world (poses and camera placement:
geometry.transforms and geometry.projection).

The model file format is the one documented in calibration/models/edge_model.py
(vertices + convex faces, counter-clockwise from outside); it is read again here
because drivers never import calibration.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geometry.projection import face_footprint

INCH = 0.0254
UNITS = {"m": 1.0, "mm": 1e-3, "in": INCH}
REPO_CONFIG = Path(__file__).resolve().parents[3] / "config"


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
    """Z-buffer of convex polygons in camera coordinates: (depth, index of the nearest polygon or -1).

    Exact point sampling at pixel centres (half-plane tests): no fill-rule bias at the edges. Depth is kept as
    its inverse, which is affine in the pixel over a planar face, so each face's test is a few broadcast
    operations over its pixel box."""
    nearness = np.zeros((height, width))  # 1 / depth of the nearest face so far; 0: none
    ids = np.full((height, width), -1, np.int32)
    for k, poly in enumerate(polys_cam):
        footprint = face_footprint(poly, f, cu, cv, width, height)
        if footprint is None:
            continue  # behind the camera, facing away or outside the image
        uv, (u0, v0, u1, v1) = footprint
        gu = np.arange(u0, u1, dtype=float)[None, :]
        gv = np.arange(v0, v1, dtype=float)[:, None]
        inside = np.ones((v1 - v0, u1 - u0), bool)
        nxt = np.roll(uv, -1, axis=0)
        orient = np.sign(np.sum(uv[:, 0] * nxt[:, 1] - nxt[:, 0] * uv[:, 1]))  # the loop's turning sense
        for (ax, ay), (bx, by) in zip(uv, nxt):
            inside &= orient * ((bx - ax) * (gv - ay) - (by - ay) * (gu - ax)) >= 0
        n = np.cross(poly[1] - poly[0], poly[2] - poly[0])
        # the ray through pixel (u, v) is ((u - cu) / f, (v - cv) / f, 1); it meets the face at depth
        # z = (n . p0) / (n . ray), so 1 / z is affine in u and v
        near = (n[0] * (gu - cu) / f + n[1] * (gv - cv) / f + n[2]) / (n @ poly[0])
        box = nearness[v0:v1, u0:u1]
        closer = inside & (near > box) & (near < 1e3)  # nearer than what is drawn, beyond 1 mm
        box[closer] = np.broadcast_to(near, closer.shape)[closer]
        ids[v0:v1, u0:u1][closer] = k
    with np.errstate(divide="ignore"):
        return 1.0 / nearness, ids
