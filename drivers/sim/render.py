"""Images of the simulated world: anti-aliased discs and rings seen through a true camera.

Each pixel is traced back to the feature's plane through the camera's exact inverse
(distortion, perspective), so perspective and lens distortion shape the feature as
they would on a real sensor. Edges get an analytic one-pixel coverage ramp, then
Gaussian blur (wider out of focus), sensor noise and quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .config import SimCamera
from .optics import TrueCamera


@dataclass(frozen=True)
class Disc:
    """A round feature in a horizontal plane: a sphere's outline, a nozzle's end face (a ring), a printed
    dot (negative contrast), a plate (a large disc)."""

    centre: np.ndarray  # world (m); the plane is z = centre[2]
    outer_radius: float  # m
    inner_radius: float = 0.0  # m; > 0 for a ring
    contrast: float | None = None  # added to what lies behind (fraction of full scale), e.g. a dark dot on a plate
    level: float | None = None  # else: absolute level over the camera's background; None: its feature level


def render(camera: TrueCamera, cfg: SimCamera, discs: list[Disc], rng: np.random.Generator) -> np.ndarray:
    """A full frame (height, width) of dtype uint8 or uint16."""
    if cfg.noise_pct > 0:  # start from the noise: one full-frame pass fewer
        image = rng.standard_normal((camera.height, camera.width), dtype=np.float32)
        image *= np.float32(cfg.noise_pct / 100)
        image += np.float32(cfg.background)
    else:
        image = np.full((camera.height, camera.width), cfg.background, dtype=np.float32)
    for disc in discs:
        _draw(image, camera, cfg, disc)
    full_scale = 255 if cfg.bit_depth == 8 else 65535
    np.clip(image, 0, 1, out=image)
    image *= np.float32(full_scale)
    image += np.float32(0.5)  # round half up on the way to integers
    return image.astype(np.uint8 if cfg.bit_depth == 8 else np.uint16)


def _draw(image: np.ndarray, camera: TrueCamera, cfg: SimCamera, disc: Disc) -> None:
    depth = camera.depth_of(disc.centre)
    if depth <= 0:
        return  # behind the camera
    metres_per_px = depth / camera.fx
    sigma = _blur_sigma(camera, cfg, depth)
    centre_px = camera.project(disc.centre)[0]
    half = disc.outer_radius / metres_per_px * 1.05 + 4 * sigma + 3
    u0, u1 = int(np.floor(centre_px[0] - half)), int(np.ceil(centre_px[0] + half)) + 1
    v0, v1 = int(np.floor(centre_px[1] - half)), int(np.ceil(centre_px[1] + half)) + 1
    cu0, cu1 = max(u0, 0), min(u1, camera.width)
    cv0, cv1 = max(v0, 0), min(v1, camera.height)
    if cu0 >= cu1 or cv0 >= cv1:
        return  # outside the field of view

    if disc.inner_radius == 0 and _covers_view(camera, disc, metres_per_px):  # a plate filling the view
        image += np.float32(_contrast(cfg, disc))
        return
    # render on the whole (unclipped) window so blur near the border stays right
    uu, vv = np.meshgrid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
    plane = camera.backproject_to_plane(np.column_stack([uu.ravel(), vv.ravel()]), disc.centre[2])
    radius_px = np.hypot(plane[:, 0] - disc.centre[0], plane[:, 1] - disc.centre[1]) / metres_per_px
    coverage = _coverage(radius_px, disc.outer_radius / metres_per_px)
    if disc.inner_radius > 0:
        coverage -= _coverage(radius_px, disc.inner_radius / metres_per_px)
    patch = coverage.reshape(uu.shape).astype(np.float32) * np.float32(_contrast(cfg, disc))
    if sigma > 0:
        patch = cv2.GaussianBlur(patch, (0, 0), sigmaX=sigma, borderType=cv2.BORDER_CONSTANT)
    image[cv0:cv1, cu0:cu1] += patch[cv0 - v0 : cv1 - v0, cu0 - u0 : cu1 - u0]


def _contrast(cfg: SimCamera, disc: Disc) -> float:
    if disc.contrast is not None:
        return disc.contrast
    return (cfg.feature_level if disc.level is None else disc.level) - cfg.background


def _covers_view(camera: TrueCamera, disc: Disc, metres_per_px: float) -> bool:
    """True when the whole image lies well inside the disc (then every pixel is simply covered)."""
    corners = np.array([[0, 0], [camera.width - 1, 0], [0, camera.height - 1], [camera.width - 1, camera.height - 1]],
                       dtype=float)
    plane = camera.backproject_to_plane(corners, disc.centre[2])
    reach = np.hypot(plane[:, 0] - disc.centre[0], plane[:, 1] - disc.centre[1]).max()
    return reach < disc.outer_radius - 20 * metres_per_px


def _coverage(radius_px: np.ndarray, edge_px: float) -> np.ndarray:
    """Fraction of a pixel inside a circle: a one-pixel linear ramp across the edge."""
    return np.clip(edge_px - radius_px + 0.5, 0.0, 1.0)


def _blur_sigma(camera: TrueCamera, cfg: SimCamera, depth: float) -> float:
    """In-focus blur widened by defocus: +2 px sigma at the edge of the depth of field."""
    defocus = abs(depth - camera.focus_distance) / (cfg.depth_of_field_mm * 1e-3 / 2)
    return float(np.hypot(cfg.blur_px, 2.0 * defocus))
