"""Sphere centres at different heights, seen by a planar camera model (seed 001 section 6.3: "it is
essential to check the sphere diameter").

A B1+B2 map knows one plane. A sphere lies on the substrate, so its centre sits one radius above it;
with a diameter tolerance of +/-0.2 mm the centres spread over +/-0.1 mm in height, and the ray from
the camera centre C through a centre dz above the plane meets the plane displaced away from C's foot
point n by (p - n) dz / (h - dz), h the camera's height: 3 um at 7 mm from n for a 250 mm camera,
12 um for the 60 mm on-board camera. A camera tilted by 1.5 deg has n some W tan(1.5 deg) from where
its axis meets the plane (6.5 mm at 250 mm), so n matters. The camera measures each sphere's
apparent diameter, which gives its height:

    d = diameter_px * (local map scale),   dz = (d - d_ref) / 2

with d_ref the mean diameter of the spheres a calibration was fitted with (their mean centre height
is the map's plane). C comes from the map's homography: with square pixels, the principal point at
the distortion centre and the focal length that the lens's nominal working distance W gives at the
image centre, the homography is K [r1 r2 t] (Zhang's decomposition), and C = -R^T t. A 10 % error
in W leaves about 10 % of the effect.

`to_map_plane` turns a sphere's true position into where the map's plane sees it (for fitting);
`to_true` turns a mapped position back into the sphere's position (for measuring).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.errors import CalibrationInputError
from calibration.models.planar import PlanarMap


def local_scale(map_: PlanarMap, uv) -> np.ndarray:
    """Metres per pixel at each pixel: the square root of the map's Jacobian determinant."""
    uv = np.atleast_2d(np.asarray(uv, dtype=float))
    h = 0.5
    du = (map_.pixel_to_plane(uv + [h, 0.0]) - map_.pixel_to_plane(uv - [h, 0.0])) / (2 * h)
    dv = (map_.pixel_to_plane(uv + [0.0, h]) - map_.pixel_to_plane(uv - [0.0, h])) / (2 * h)
    return np.sqrt(np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]))


@dataclass(frozen=True)
class SphereHeights:
    """How to correct sphere positions seen through `map`: the camera centre's foot point and height
    over the map's plane, and the reference diameter of that plane."""

    height: float  # m, the camera centre over the map's plane (negative: it looks up at the plane)
    reference_diameter: float  # m
    foot: np.ndarray  # the camera centre's foot point, map coordinates

    @classmethod
    def for_map(cls, map_: PlanarMap, uv, diameter_px, working_distance: float) -> "SphereHeights":
        """Reference: the mean diameter of the spheres at `uv` (those the map was fitted with)."""
        reference = float(np.mean(diameters(map_, uv, diameter_px)))
        foot, height = camera_centre(map_, working_distance)
        return cls(height, reference, foot)

    def dz(self, map_: PlanarMap, uv, diameter_px) -> np.ndarray:
        return (diameters(map_, uv, diameter_px) - self.reference_diameter) / 2

    def to_map_plane(self, xy, dz) -> np.ndarray:
        """Where the map's plane sees a sphere centre at `xy` standing `dz` above it."""
        xy = np.atleast_2d(xy)
        return self.foot + (xy - self.foot) * (self.height / (self.height - dz))[:, None]

    def to_true(self, xy_mapped, dz) -> np.ndarray:
        """The sphere centre seen at `xy_mapped` in the map's plane, standing `dz` above it."""
        xy = np.atleast_2d(xy_mapped)
        return self.foot + (xy - self.foot) * ((self.height - dz) / self.height)[:, None]

    def to_dict(self) -> dict:
        return {"camera_height_mm": self.height * 1e3, "reference_diameter_mm": self.reference_diameter * 1e3,
                "foot_mm": (np.asarray(self.foot) * 1e3).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "SphereHeights":
        return cls(d["camera_height_mm"] * 1e-3, d["reference_diameter_mm"] * 1e-3, np.asarray(d["foot_mm"]) * 1e-3)


def diameter_column(rows: list[dict]) -> np.ndarray:
    """The rows' `diameter_px`, which the correction needs in every measured row."""
    try:
        d = np.array([float(r["diameter_px"]) for r in rows])
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationInputError(f"the sphere-height correction needs a diameter_px column with a number in every "
                                    f"measured row ({exc}); set working_distance_mm to none to fit without it") from None
    if not np.all(np.isfinite(d) & (d > 0)):
        raise CalibrationInputError("diameter_px must be a positive number in every measured row")
    return d


def diameters(map_: PlanarMap, uv, diameter_px) -> np.ndarray:
    return np.asarray(diameter_px, dtype=float) * local_scale(map_, uv)


def camera_centre(map_: PlanarMap, working_distance: float) -> tuple[np.ndarray, float]:
    """The camera centre's foot point on the map's plane (map coordinates) and its height over it."""
    centre = np.asarray(map_.centre, dtype=float)
    f = working_distance / float(local_scale(map_, [centre])[0])  # px: the scale at the axis is W / f
    K = np.array([[f, 0.0, centre[0]], [0.0, f, centre[1]], [0.0, 0.0, 1.0]])
    M = np.linalg.solve(K, np.linalg.inv(map_.H))  # plane -> camera rays: lambda [r1 r2 t]
    lam = 2.0 / (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1]))
    r1, r2, t = lam * M[:, 0], lam * M[:, 1], lam * M[:, 2]
    if t[2] < 0:  # the plane lies in front of the camera
        r1, r2, t = -r1, -r2, -t
    r3 = np.cross(r1, r2)
    r3 /= np.linalg.norm(r3)
    # C = -R^T t; its height along r1 x r2 (the plane's normal, up in a right-handed frame) is positive for a
    # camera looking down on the plane, negative for one looking up at it. A view through a mirror flips
    # that sign: such maps (camera 1) are not corrected here.
    return -np.array([r1 @ t, r2 @ t]), -float(r3 @ t)
