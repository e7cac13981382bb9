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
    """Z-buffer of convex polygons in camera coordinates: (depth, index of the nearest polygon or -1)."""
    zbuf = np.full((height, width), np.inf)
    ids = np.full((height, width), -1, np.int32)
    for k, poly in enumerate(polys_cam):
        footprint = face_footprint(poly, f, cu, cv, width, height)
        if footprint is None:
            continue  # behind the camera, facing away or outside the image
        uv, (u0, v0, u1, v1) = footprint
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
