"""Parts on the hand-eye cell's table, and the vacuum cup on its flange that picks them.

A part is a flat puck lying on the table: its top face, a bright disc, is what the cameras see (looking down,
the side wall hides under it, and is not drawn). Where each part really lies is drawn from the seed around the
position the cell file gives (the feeder drops them roughly there); the routine has to find it with the camera.
The cup grips a part when it comes down on the part's top within `capture_mm` of its centre; the miss (how far
the cup's centre was from the part's) is the pick's truth. A held part rides the cup; released, it lies on the
table under it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from drivers.sim.base import Strict
from drivers.sim.ur5e_handeye.footprint import FULL, RayBounds, octagon

Triple = tuple[float, float, float]


class HandEyePart(Strict):
    position_mm: tuple[float, float] = Field(..., description="roughly where it lies (base frame x, y)")
    position_error_mm: float = Field(10.0, ge=0, le=200, description="uniform +/- of where it really lies, per axis")
    diameter_mm: float = Field(30.0, gt=0, le=300)
    height_mm: float = Field(6.0, gt=0, le=300)
    grey: float = Field(0.85, ge=0, le=1, description="grey level of its top face")


class HandEyeGripper(Strict):
    tip_mm: Triple = Field((0.0, 0.0, 150.0), description="the vacuum cup's centre on the flange (flange frame)")
    capture_mm: float = Field(4.0, gt=0, le=50, description="a part is gripped when the cup lands this close to "
                                                            "its centre")
    height_tolerance_mm: float = Field(2.0, gt=0, le=50, description="... and this close to its top face")


@dataclass
class Part:
    name: str
    config: HandEyePart
    centre: np.ndarray  # its top face's centre (base frame, m), true


def draw_parts(parts: dict[str, HandEyePart], rng: np.random.Generator) -> dict[str, Part]:
    out = {}
    for name, cfg in sorted(parts.items()):
        xy = np.asarray(cfg.position_mm) * 1e-3 + rng.uniform(-1, 1, 2) * cfg.position_error_mm * 1e-3
        out[name] = Part(name, cfg, np.array([xy[0], xy[1], cfg.height_mm * 1e-3]))
    return out


def paint_parts(parts, T_camera_base: np.ndarray, x: np.ndarray, y: np.ndarray, image, depth,
                bounds: RayBounds | None = None) -> None:
    """Each pixel whose ray (normalised image coordinates x, y) meets a part's top face, nearer than what it
    already shows, takes the part's grey. With the rays' `bounds`, only the pixels that can see the face are
    tested (footprint.py: the same frame, sooner)."""
    R, t = T_camera_base[:3, :3], T_camera_base[:3, 3]
    for part in parts:
        centre = R @ part.centre + t  # in the camera frame
        normal = R[:, 2]  # the base's z: the face is horizontal
        window = FULL if bounds is None else bounds.window(octagon(centre, R[:, 0], R[:, 1],
                                                                     part.config.diameter_mm * 5e-4))
        if window is None:
            continue  # out of view
        xw, yw, shown, near = x[window], y[window], image[window], depth[window]  # views: painted in place
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (normal @ centre) / (normal[0] * xw + normal[1] * yw + normal[2])  # depth along each ray
        px, py = xw * z - centre[0], yw * z - centre[1]
        pz = z - centre[2]
        hit = (z > 0) & (z < near) & (px * px + py * py + pz * pz <= (part.config.diameter_mm * 5e-4) ** 2)
        shown[hit] = part.config.grey
        near[hit] = z[hit]


def cup_position(flange: np.ndarray, gripper: HandEyeGripper) -> np.ndarray:
    return flange[:3, :3] @ (np.asarray(gripper.tip_mm) * 1e-3) + flange[:3, 3]


def part_under(parts, cup: np.ndarray, gripper: HandEyeGripper) -> tuple[Part | None, float]:
    """The part the cup seals on (None if none) and the cup's lateral miss from the nearest part's centre (m)."""
    parts = list(parts)
    if not parts:
        return None, float("inf")
    misses = [float(np.hypot(*(cup[:2] - p.centre[:2]))) for p in parts]
    k = int(np.argmin(misses))
    near = parts[k]
    sealed = (misses[k] <= gripper.capture_mm * 1e-3
              and abs(cup[2] - near.centre[2]) <= gripper.height_tolerance_mm * 1e-3)
    return (near if sealed else None), misses[k]
