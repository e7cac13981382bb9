"""The true cameras of the simulated world: pinhole + Brown-Conrady distortion.

This is the hidden truth the calibration must discover; it is deliberately a
different model (forward distortion in normalised coordinates about the
principal point) from the one the calibration fits (seed 001 appendix B).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from geometry.transforms import rotation

from drivers.sim import cubic
from drivers.sim.micro.config import SimCamera


@dataclass(frozen=True)
class TrueCamera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    k2: float
    p1: float
    p2: float
    R_cw: np.ndarray  # columns: camera x, y, z axes in world coordinates
    C: np.ndarray  # camera centre in world coordinates (m)
    focus_distance: float  # m along the optical axis to the plane in focus
    mirror: bool = False

    # -- world -> pixel ----------------------------------------------------
    def project(self, points_w) -> np.ndarray:
        p = np.atleast_2d(np.asarray(points_w, dtype=float))
        pc = (p - self.C) @ self.R_cw  # world -> camera coordinates
        x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        xd, yd = self._distort(x, y)
        u = self.fx * xd + self.cx
        v = self.fy * yd + self.cy
        if self.mirror:
            u = (self.width - 1) - u
        return np.column_stack([u, v])

    def _distort(self, x, y):
        r2 = x * x + y * y
        radial = 1 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return xd, yd

    # -- pixel -> world ----------------------------------------------------
    def undistort(self, uv) -> tuple[np.ndarray, np.ndarray]:
        """Normalised ideal coordinates of pixels, by fixed-point iteration (converges fast at these distortions)."""
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        u = uv[:, 0]
        if self.mirror:
            u = (self.width - 1) - u
        xd = (u - self.cx) / self.fx
        yd = (uv[:, 1] - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        for _ in range(50):
            r2 = x * x + y * y
            radial = 1 + self.k1 * r2 + self.k2 * r2 * r2
            x_new = (xd - 2 * self.p1 * x * y - self.p2 * (r2 + 2 * x * x)) / radial
            y_new = (yd - self.p1 * (r2 + 2 * y * y) - 2 * self.p2 * x * y) / radial
            done = max(np.max(np.abs(x_new - x), initial=0), np.max(np.abs(y_new - y), initial=0)) < 1e-15
            x, y = x_new, y_new
            if done:
                break
        return x, y

    def undistort_grid(self, us, vs) -> tuple[np.ndarray, np.ndarray]:
        """`undistort` of every pixel (u, v) of a grid, as (len(vs), len(us)) arrays; `us` and `vs` evenly
        spaced. The inverse distortion is exact on a coarse grid (every GRID_STEP_PX) and cubic in between:
        smooth at the scale of the image, so the interpolation is off by under 1e-6 px, at a fraction of
        the cost of iterating every pixel."""
        us, vs = np.asarray(us, dtype=float), np.asarray(vs, dtype=float)
        coarse_u, taps_u = _coarse(us)
        coarse_v, taps_v = _coarse(vs)
        cu, cv = np.meshgrid(coarse_u, coarse_v)
        x, y = self.undistort(np.column_stack([cu.ravel(), cv.ravel()]))
        return tuple(cubic.interpolate(c.reshape(cu.shape), taps_v, taps_u) for c in (x, y))

    def backproject_to_plane(self, uv, z: float) -> np.ndarray:
        """World points on the horizontal plane at height z seen at pixels uv."""
        px, py = self.plane_xy(*self.undistort(uv), z)
        return np.column_stack([px, py, np.full_like(px, z)])

    def plane_xy(self, x, y, z: float) -> tuple[np.ndarray, np.ndarray]:
        """Where the rays through normalised ideal coordinates (x, y) meet the horizontal plane at height z:
        its world x and y, arrays of x's shape (written out per component: this runs on every rendered pixel)."""
        R, C = self.R_cw, self.C
        t = (z - C[2]) / (R[2, 0] * x + R[2, 1] * y + R[2, 2])
        return C[0] + t * (R[0, 0] * x + R[0, 1] * y + R[0, 2]), C[1] + t * (R[1, 0] * x + R[1, 1] * y + R[1, 2])

    def depth_of(self, point_w) -> float:
        return float((np.asarray(point_w) - self.C) @ self.R_cw[:, 2])

    def moved(self, C, R_cw) -> "TrueCamera":
        return replace(self, C=np.asarray(C, dtype=float), R_cw=np.asarray(R_cw, dtype=float))


def draw_true_camera(cfg: SimCamera, rng: np.random.Generator) -> TrueCamera:
    """One plausible camera within the cell file's budget."""
    width, height = cfg.resolution_px
    pixel_m = cfg.pixel_um * 1e-6
    distance = cfg.working_distance_mm * 1e-3
    f = distance / pixel_m

    offset = cfg.principal_offset_px * np.sqrt(rng.uniform()) * np.array(_unit(rng.uniform(0, 2 * np.pi)))
    cx, cy = (width - 1) / 2 + offset[0], (height - 1) / 2 + offset[1]

    if cfg.view == "down":
        base = np.column_stack([[1, 0, 0], [0, -1, 0], [0, 0, -1]]).astype(float)
    else:  # looking up through the glass substrate
        base = np.eye(3)
    yaw = np.radians(rng.uniform(*cfg.yaw_deg))
    tilt = np.radians(rng.uniform(*cfg.tilt_deg))
    azimuth = rng.uniform(0, 2 * np.pi)
    tilt_axis = [np.cos(azimuth), np.sin(azimuth), 0.0]
    R_cw = rotation(tilt_axis, tilt) @ base @ rotation([0, 0, 1], yaw)

    centre = np.array([cfg.centre_mm[0] * 1e-3, cfg.centre_mm[1] * 1e-3, cfg.focus_z_mm * 1e-3])
    C = centre - distance * R_cw[:, 2]

    # distortion sized by the displacement it causes at the image corners
    r_corner = np.hypot(width / 2, height / 2) / f
    shift = rng.uniform(*cfg.distortion.corner_displacement_px) * rng.choice([-1.0, 1.0])
    share_k2 = rng.uniform(*cfg.distortion.k2_fraction)
    k1 = shift * (1 - share_k2) / (f * r_corner**3)
    k2 = shift * share_k2 / (f * r_corner**5)
    tangential = abs(shift) * rng.uniform(*cfg.distortion.tangential_fraction) / (3 * f * r_corner**2)
    p1, p2 = tangential * np.array(_unit(rng.uniform(0, 2 * np.pi)))
    return TrueCamera(width, height, f, f, cx, cy, k1, k2, p1, p2, R_cw, C, distance, cfg.mirror)


GRID_STEP_PX = 16  # exact inverse distortion this often, cubic in between (see undistort_grid)


def _coarse(fine: np.ndarray):
    """Coarse positions around evenly spaced `fine` ones, every GRID_STEP_PX from one step before the first
    to two past the last, and the fine ones' cubic taps on them."""
    spacing = fine[1] - fine[0] if fine.size > 1 else 1.0
    every = max(1, int(GRID_STEP_PX // spacing))  # fine samples per coarse step
    first, weights = cubic.taps(np.arange(fine.size) / every + 1.0)
    return fine[0] + (np.arange(first[-1] + 4) - 1) * every * spacing, (first, weights)


def _unit(angle: float) -> tuple[float, float]:
    return float(np.cos(angle)), float(np.sin(angle))
