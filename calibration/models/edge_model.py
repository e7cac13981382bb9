"""3D edge models of the objects a VR calibration matches (seed 000: the ORU and its receptacle).

File format (JSON, files under `config/models/`):

    {"name": "oru", "units": "in" | "mm" | "m",
     "vertices": [[x, y, z], ...],
     "faces": [[i, j, k, ...], ...]}

Optional: "face_albedo": [a, ...], the relative reflectance of each face (the
simulator shades faces with it; matching ignores it).

Faces are convex polygons given as vertex-index loops, counter-clockwise seen from
outside (so their normals point out; the renderer shades by them and the z-buffer
hides what lies behind them). Edges are not listed: they are derived as the face
sides whose two faces have different normals (a fold, an intensity step in the
image) or that belong to one face only. Coordinates are converted to metres.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

UNITS = {"m": 1.0, "mm": 1e-3, "in": 0.0254}
REPO_CONFIG = Path(__file__).resolve().parents[2] / "config"


@dataclass(frozen=True)
class EdgeModel:
    name: str
    vertices: np.ndarray  # (n, 3) metres, object frame
    faces: tuple[np.ndarray, ...]  # vertex-index loops
    normals: np.ndarray  # (n_faces, 3) outward unit normals
    edges: np.ndarray  # (n_edges, 2) vertex indices

    @classmethod
    def from_dict(cls, d: dict) -> EdgeModel:
        unit = d.get("units", "m")
        if unit not in UNITS:
            raise ValueError(f"model {d.get('name')!r}: units {unit!r}; allowed: {', '.join(UNITS)}")
        v = np.asarray(d["vertices"], dtype=float) * UNITS[unit]
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"model {d.get('name')!r}: vertices must be [[x, y, z], ...]")
        faces = tuple(np.asarray(f, dtype=int) for f in d["faces"])
        for k, f in enumerate(faces):
            if len(f) < 3 or f.min() < 0 or f.max() >= len(v):
                raise ValueError(f"model {d.get('name')!r}: face {k} needs >= 3 vertex indices in 0..{len(v) - 1}")
        normals = np.array([newell_normal(v[f]) for f in faces])
        return cls(str(d.get("name", "model")), v, faces, normals, feature_edges(faces, normals))

    @classmethod
    def load(cls, path: str | Path) -> EdgeModel:
        return cls.from_dict(json.loads(resolve_model_path(path).read_text()))


def resolve_model_path(path: str | Path) -> Path:
    """As given (absolute or relative to the working directory), else relative to the repository's config/."""
    p = Path(path)
    if p.exists():
        return p
    if (REPO_CONFIG / p).exists():
        return REPO_CONFIG / p
    raise FileNotFoundError(f"model file {str(path)!r} not found (also looked in {REPO_CONFIG})")


def newell_normal(poly: np.ndarray) -> np.ndarray:
    n = np.zeros(3)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        n += [(a[1] - b[1]) * (a[2] + b[2]), (a[2] - b[2]) * (a[0] + b[0]), (a[0] - b[0]) * (a[1] + b[1])]
    return n / np.linalg.norm(n)


def feature_edges(faces, normals, fold_deg: float = 1.0) -> np.ndarray:
    owners: dict[tuple[int, int], list[int]] = {}
    for k, f in enumerate(faces):
        for a, b in zip(f, np.roll(f, -1)):
            owners.setdefault((min(a, b), max(a, b)), []).append(k)
    keep = []
    for edge, fs in owners.items():
        if len(fs) == 1 or any(np.dot(normals[fs[0]], normals[j]) < np.cos(np.radians(fold_deg)) for j in fs[1:]):
            keep.append(edge)
    return np.array(sorted(keep), dtype=int).reshape(-1, 2)
