"""Images of the simulated world: anti-aliased discs and rings seen through a true camera.

Each pixel near a feature is traced back to the feature's plane through the camera's
exact inverse (distortion, perspective), so perspective and lens distortion shape the
feature as they would on a real sensor. Edges get an analytic one-pixel coverage ramp,
then Gaussian blur (wider out of focus), sensor noise and quantisation.

Only the pixels a feature can reach are rendered: its window, out to four blur sigmas.
The rest of a frame is background (or a plate filling the view) with sensor noise taken
from a bank drawn once per camera, at a random offset each capture; fresh noise is drawn
in every feature window, where it matters for the measurements. A feature far out of
focus is rendered at a coarser resolution and scaled up: its blur hides the difference.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from drivers.sim import cubic
from drivers.sim.micro.config import SimCamera
from drivers.sim.optics import TrueCamera

NOISE_MARGIN = 64  # px of extra noise bank around a frame: each capture reads it at a random offset
COARSE_ABOVE_SIGMA_PX = 32.0  # blur beyond which a feature is rendered coarser (at sigma / 8 px per sample)


@dataclass(frozen=True)
class Disc:
    """A round feature in a horizontal plane: a sphere's outline, a nozzle's end face (a ring), a printed
    dot (negative contrast), a plate (a large disc)."""

    centre: np.ndarray  # world (m); the plane is z = centre[2]
    outer_radius: float  # m
    inner_radius: float = 0.0  # m; > 0 for a ring
    contrast: float | None = None  # added to what lies behind (fraction of full scale), e.g. a dark dot on a plate
    level: float | None = None  # else: absolute level over the camera's background; None: its feature level


class NoiseBank:
    """Sensor noise for a frame and a margin, drawn once per camera (on first use, from its own generator so
    the run's noise stream does not depend on it), and the quantised frames of it over each base level."""

    def __init__(self, width: int, height: int, noise_pct: float, bit_depth: int, rng: np.random.Generator):
        self.width, self.height, self.noise_pct, self.bit_depth, self.rng = width, height, noise_pct, bit_depth, rng
        self._noise: np.ndarray | None = None
        self._frames: dict[float, np.ndarray] = {}

    def draw(self) -> None:
        """Draw the noise now (it is drawn on first use otherwise)."""
        if self._noise is None and self.noise_pct > 0:
            self._noise = self.rng.standard_normal((self.height + NOISE_MARGIN, self.width + NOISE_MARGIN),
                                                   dtype=np.float32)
            self._noise *= np.float32(self.noise_pct / 100)

    def frame(self, level: float, rng: np.random.Generator) -> np.ndarray:
        """A full frame of `level` plus noise, quantised: the bank read at a random offset."""
        key = round(float(level), 9)
        if key not in self._frames:
            self.draw()
            base = np.full((self.height + NOISE_MARGIN, self.width + NOISE_MARGIN), level, dtype=np.float32)
            if self._noise is not None:
                base += self._noise
            self._frames[key] = quantise(base, self.bit_depth)
        dy, dx = rng.integers(0, NOISE_MARGIN, 2)
        return self._frames[key][dy:dy + self.height, dx:dx + self.width].copy()


def render(camera: TrueCamera, cfg: SimCamera, discs: list[Disc], rng: np.random.Generator,
           bank: NoiseBank) -> np.ndarray:
    """A full frame (height, width) of dtype uint8 or uint16."""
    level = cfg.background
    patches = []
    for disc in discs:
        drawn = _draw(camera, cfg, disc)
        if isinstance(drawn, float):  # a plate filling the view
            level += drawn
        elif drawn is not None:
            patches.append(drawn)
    image = bank.frame(level, rng)
    for u0, u1, v0, v1 in _merge([_clipped(p[:4], camera) for p in patches]):
        area = np.full((v1 - v0, u1 - u0), level, dtype=np.float32)
        if cfg.noise_pct > 0:
            area += rng.standard_normal(area.shape, dtype=np.float32) * np.float32(cfg.noise_pct / 100)
        for pu0, pu1, pv0, pv1, patch in patches:
            a0, a1, b0, b1 = max(u0, pu0), min(u1, pu1), max(v0, pv0), min(v1, pv1)
            if a0 < a1 and b0 < b1:
                area[b0 - v0:b1 - v0, a0 - u0:a1 - u0] += patch[b0 - pv0:b1 - pv0, a0 - pu0:a1 - pu0]
        image[v0:v1, u0:u1] = quantise(area, cfg.bit_depth)
    return image


def _draw(camera: TrueCamera, cfg: SimCamera, disc: Disc):
    """The disc's blurred contribution on its (unclipped) window, as (u0, u1, v0, v1, patch); its contrast
    alone when it fills the view; None when the camera does not see it."""
    depth = camera.depth_of(disc.centre)
    if depth <= 0:
        return None  # behind the camera
    metres_per_px = depth / camera.fx
    sigma = _blur_sigma(camera, cfg, depth)
    centre_px = camera.project(disc.centre)[0]
    half = disc.outer_radius / metres_per_px * 1.05 + 4 * sigma + 3
    u0, u1 = int(np.floor(centre_px[0] - half)), int(np.ceil(centre_px[0] + half)) + 1
    v0, v1 = int(np.floor(centre_px[1] - half)), int(np.ceil(centre_px[1] + half)) + 1
    cu0, cu1, cv0, cv1 = _clipped((u0, u1, v0, v1), camera)
    if cu0 >= cu1 or cv0 >= cv1:
        return None  # outside the field of view
    if disc.inner_radius == 0 and _covers_view(camera, disc, metres_per_px):
        return float(_contrast(cfg, disc))

    # far out of focus, sample every `k` px: the blur (>= 8 samples wide) hides the coarser edge
    k = int(sigma // 16) if sigma > COARSE_ABOVE_SIGMA_PX else 1
    u1, v1 = u0 + -(-(u1 - u0) // k) * k, v0 + -(-(v1 - v0) // k) * k  # whole samples
    # render on the whole (unclipped) window so blur near the border stays right
    us = u0 + k * np.arange((u1 - u0) // k) + (k - 1) / 2  # sample centres
    vs = v0 + k * np.arange((v1 - v0) // k) + (k - 1) / 2
    px, py = camera.plane_xy(*camera.undistort_grid(us, vs), disc.centre[2])
    radius_px = np.hypot(px - disc.centre[0], py - disc.centre[1]) / (metres_per_px * k)
    coverage = _coverage(radius_px, disc.outer_radius / (metres_per_px * k))
    if disc.inner_radius > 0:
        coverage -= _coverage(radius_px, disc.inner_radius / (metres_per_px * k))
    patch = coverage.astype(np.float32) * np.float32(_contrast(cfg, disc))
    # a coarse sample's ramp is k px wide: blur by what is left of sigma beyond it
    sigma_k = np.sqrt(max(sigma**2 - (k * k - 1) / 12, 0.0)) / k
    if sigma_k > 0:
        patch = cv2.GaussianBlur(patch, (0, 0), sigmaX=sigma_k, borderType=cv2.BORDER_CONSTANT)
    if k > 1:  # back to every pixel; beyond the window the blurred patch is nothing (BORDER_CONSTANT)
        padded = np.pad(patch, 2)
        fine = [cubic.taps((np.arange(n) - (k - 1) / 2) / k + 2) for n in (v1 - v0, u1 - u0)]
        patch = cubic.interpolate(padded, *fine).astype(np.float32)
    return u0, u1, v0, v1, patch


def _clipped(window, camera: TrueCamera) -> tuple[int, int, int, int]:
    u0, u1, v0, v1 = window
    return max(u0, 0), min(u1, camera.width), max(v0, 0), min(v1, camera.height)


def _merge(windows: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Disjoint rectangles covering the given ones (overlapping ones merged into their bounding box), so each
    pixel draws its noise once."""
    merged = [w for w in windows if w[0] < w[1] and w[2] < w[3]]
    changed = True
    while changed:
        changed = False
        for i in range(len(merged)):
            for j in range(i + 1, len(merged)):
                a, b = merged[i], merged[j]
                if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                    merged[i] = (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))
                    del merged[j]
                    changed = True
                    break
            if changed:
                break
    return merged


def quantise(image: np.ndarray, bit_depth: int = 8) -> np.ndarray:
    """Fractions of full scale -> integer grey levels (in place on the way)."""
    full_scale = 255 if bit_depth == 8 else 65535
    np.clip(image, 0, 1, out=image)
    image *= np.float32(full_scale)
    image += np.float32(0.5)  # round half up on the way to integers
    return image.astype(np.uint8 if bit_depth == 8 else np.uint16)


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


def expose(image: np.ndarray, brightness: float) -> np.ndarray:
    """A rendered frame as a longer (or shorter) exposure or a higher gain takes it: each level (a fraction of full
    scale, linear in light) times `brightness`, clipped at full scale (saturated) and quantised again in the frame's
    own depth. brightness 1 returns the frame as it is."""
    if brightness == 1.0:
        return image
    full_scale = 255 if image.dtype == np.uint8 else 65535
    light = image.astype(np.float32)
    light *= np.float32(brightness / full_scale)
    return quantise(light, 8 if image.dtype == np.uint8 else 16)
