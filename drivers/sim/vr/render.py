"""Images of the VR world: flat-shaded faces (so every fold is an intensity step), optical blur,
optional blooming, sensor noise and 8-bit quantisation.

Faces are rasterised with a z-buffer at `supersample` x the sensor resolution and
averaged down, which anti-aliases the edges.
"""

from __future__ import annotations

import cv2
import numpy as np

from drivers.sim.vr.config import VrCamera, VrRendering
from drivers.sim.vr.geometry import rasterise


def render(V: np.ndarray, f: float, cam: VrCamera, look: VrRendering, polys_world: list[np.ndarray],
           shades: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A (height, width) uint8 frame of world polygons with the given shade (fraction of full scale) each."""
    width, height = cam.resolution_px
    s = look.supersample
    polys_cam = [p @ V[:3, :3].T + V[:3, 3] for p in polys_world]
    # pixel centres of the fine grid: fine pixel (i + 0.5)/s - 0.5 in sensor pixels
    _, ids = rasterise(width * s, height * s, polys_cam, f * s, (width * s - 1) / 2, (height * s - 1) / 2)
    level = np.append(np.asarray(shades, np.float32), np.float32(look.background))
    fine = level[ids]  # id -1 picks the background
    if look.blooming:
        fine = np.where(fine > 0.6, fine * look.bloom_gain, fine).astype(np.float32)
    image = cv2.resize(fine, (width, height), interpolation=cv2.INTER_AREA)
    if look.blooming and look.bloom_px > 0:  # light above saturation spreads into the neighbours
        excess = np.clip(image - 1.0, 0, None)
        spread = cv2.GaussianBlur(excess, (0, 0), look.bloom_px) * 4.0
        image = np.maximum(image, np.minimum(image + spread, 1.0))
    if cam.blur_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), cam.blur_px)
    if cam.noise_pct > 0:
        image = image + rng.standard_normal(image.shape, dtype=np.float32) * np.float32(cam.noise_pct / 100)
    return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)


def face_shades(normals_world: np.ndarray, albedo: float, look: VrRendering) -> np.ndarray:
    key = np.asarray(look.light_dir, float) / np.linalg.norm(look.light_dir)
    fill = np.asarray(look.fill_dir, float) / np.linalg.norm(look.fill_dir)
    lit = np.clip(normals_world @ key, 0, None) + look.fill * np.clip(normals_world @ fill, 0, None)
    return albedo * (look.ambient + (1 - look.ambient) * np.clip(lit, 0, 1))
