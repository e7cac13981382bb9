"""Sphere centres at different heights, seen by a planar camera model (seed 001 section 6.3: "it is
essential to check the sphere diameter").

A B1+B2 map knows one plane. A sphere lies on the substrate, so its centre sits one radius above it;
with a diameter tolerance of +/-0.2 mm the centres spread over +/-0.1 mm in height, and a camera at
working distance W sees a centre dz above the map's plane displaced away from its optical axis by
(p - axis) dz / (W - dz): 3 um at 7 mm from the axis of a 250 mm camera, 12 um for the 60 mm on-board
camera. The camera measures each sphere's apparent diameter, which gives its height:

    d = diameter_px * (local map scale),   dz = (d - d_ref) / 2

with d_ref the mean diameter of the spheres a calibration was fitted with (their mean centre height
is the map's plane). The working distance is the lens's nominal one: a 10 % error in W leaves 10 %
of the effect.

`to_map_plane` turns a sphere's true position into where the map's plane sees it (for fitting);
`to_true` turns a mapped position back into the sphere's position (for measuring).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .planar import PlanarMap


def local_scale(map_: PlanarMap, uv) -> np.ndarray:
    """Metres per pixel at each pixel: the square root of the map's Jacobian determinant."""
    uv = np.atleast_2d(np.asarray(uv, dtype=float))
    h = 0.5
    du = (map_.pixel_to_plane(uv + [h, 0.0]) - map_.pixel_to_plane(uv - [h, 0.0])) / (2 * h)
    dv = (map_.pixel_to_plane(uv + [0.0, h]) - map_.pixel_to_plane(uv - [0.0, h])) / (2 * h)
    return np.sqrt(np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]))


@dataclass(frozen=True)
class SphereHeights:
    """How to correct sphere positions seen through `map`: its axis, the lens's working distance and the
    reference diameter of the map's plane."""

    working_distance: float  # m
    reference_diameter: float  # m
    axis: np.ndarray  # where the optical axis meets the map's plane, map coordinates

    @classmethod
    def for_map(cls, map_: PlanarMap, uv, diameter_px, working_distance: float, image_size) -> "SphereHeights":
        """Reference: the mean diameter of the spheres at `uv` (those the map was fitted with)."""
        reference = float(np.mean(diameters(map_, uv, diameter_px)))
        return cls(working_distance, reference, optical_axis(map_, image_size))

    def dz(self, map_: PlanarMap, uv, diameter_px) -> np.ndarray:
        return (diameters(map_, uv, diameter_px) - self.reference_diameter) / 2

    def to_map_plane(self, xy, dz) -> np.ndarray:
        """Where the map's plane sees a sphere centre at `xy` standing `dz` above it."""
        xy = np.atleast_2d(xy)
        return self.axis + (xy - self.axis) * (self.working_distance / (self.working_distance - dz))[:, None]

    def to_true(self, xy_mapped, dz) -> np.ndarray:
        """The sphere centre seen at `xy_mapped` in the map's plane, standing `dz` above it."""
        xy = np.atleast_2d(xy_mapped)
        return self.axis + (xy - self.axis) * ((self.working_distance - dz) / self.working_distance)[:, None]

    def to_dict(self) -> dict:
        return {"working_distance_mm": self.working_distance * 1e3, "reference_diameter_mm": self.reference_diameter * 1e3,
                "axis_mm": (np.asarray(self.axis) * 1e3).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "SphereHeights":
        return cls(d["working_distance_mm"] * 1e-3, d["reference_diameter_mm"] * 1e-3, np.asarray(d["axis_mm"]) * 1e-3)


def diameters(map_: PlanarMap, uv, diameter_px) -> np.ndarray:
    return np.asarray(diameter_px, dtype=float) * local_scale(map_, uv)


def optical_axis(map_: PlanarMap, image_size) -> np.ndarray:
    """The image centre mapped to the plane: the principal point is within a few tens of pixels of it,
    which moves the correction by a negligible dz * offset / W."""
    w, h = image_size
    return map_.pixel_to_plane([[(w - 1) / 2, (h - 1) / 2]])[0]
