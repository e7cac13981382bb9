"""Using the active calibrations: where is what a camera sees, and the arm with its tool compensated.

Every calibration here maps into one frame: the commanded robot position at alpha_cal
that puts the nozzle on the point (the virtual-grid principle: the robot is the
reference). The tool compensation keeps that true at any alpha.
"""

from __future__ import annotations

import math

import numpy as np

from drivers.interfaces import Arm, Pose, move_via

from calibration.errors import CalibrationInputError
from calibration.models.planar import MapUncertainty, PlanarMap
from calibration.models.sphere_height import SphereHeights
from calibration.models.tool_offset import rot

# said of a located point outside the calibrated region, by every front end
OUTSIDE_REGION = ("outside the calibrated region (the hull of the pixels the calibration was fitted on): the map "
                  "extrapolates here; sigma_um is its grown uncertainty")


class CellCalibration:
    def __init__(self, calibrations: dict[str, dict], tool: str = "nozzle"):
        self.calibrations = calibrations
        self.tool = tool

    def _model(self, target: str) -> dict:
        try:
            return self.calibrations[target]
        except KeyError:
            raise CalibrationInputError(f"no active calibration of {target!r} (active: "
                                        f"{', '.join(sorted(self.calibrations)) or 'none'})") from None

    def camera_map(self, camera: str) -> PlanarMap:
        model = self._model(camera)
        if not isinstance(model.get("map"), dict):
            raise CalibrationInputError(f"the active calibration of {camera!r} ({model.get('kind', 'no kind')}) "
                                        "maps no pixels: it is not a camera's")
        return PlanarMap.from_dict(model["map"])

    def check_on_image(self, camera: str, uv) -> None:
        """CalibrationInputError naming the first pixel of `uv` that is not on `camera`'s image: the map would
        answer there too, with a number that means nothing."""
        map_ = self.camera_map(camera)
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        off = np.nonzero(~map_.on_image(uv))[0]
        if off.size:
            raise CalibrationInputError(map_.off_image(*uv[off[0]], f"{camera}'s"))

    def in_calibrated_region(self, camera: str, uv) -> np.ndarray | None:
        """Per pixel: inside the hull of the pixels `camera`'s calibration was fitted on; None if it keeps no hull
        (made before it was kept)."""
        return self.camera_map(camera).in_region(np.atleast_2d(np.asarray(uv, dtype=float)))

    def rides_arm(self, camera: str) -> bool:
        """Whether `camera`'s active calibration places it on the arm (locating with it needs the arm's pose)."""
        return self.calibrations.get(camera, {}).get("kind") == "onboard-camera"

    def locate(self, camera: str, uv, arm_pose: Pose | None = None, diameter_px=None) -> np.ndarray:
        """Robot (x, y) of what pixel uv of `camera` shows. A camera on the arm needs the arm's reported pose
        (seed 001 eq. 5: P_k + (I - R_k) D + R_k A_b). `diameter_px`: the sphere's apparent diameter, for a
        calibration fitted with sphere heights (its centre is corrected for its height)."""
        return self.locate_with_sigma(camera, uv, arm_pose, diameter_px)[0]

    def locate_with_sigma(self, camera: str, uv, arm_pose: Pose | None = None,
                          diameter_px=None) -> tuple[np.ndarray, np.ndarray]:
        """`locate`, and the 1-σ per-axis uncertainty (m) of each point: sqrt(trace(C) / 2) of the 2x2 covariance C
        of the located point, propagated from the calibration's parameter covariance (the map's; for a camera on
        the arm also D's and its correlation with the map). It is the error the calibration itself may have there,
        the same for every feature seen at that pixel; the feature's own centroid noise is not in it. NaN when the
        calibration keeps no covariance (made before it was kept)."""
        model = self._model(camera)
        map_ = self.camera_map(camera)
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        relative = map_.pixel_to_plane(uv)
        cov = self._map_covariance(model, uv)  # (N, 2, 2), or None
        if diameter_px is not None and model.get("sphere_heights"):
            heights = SphereHeights.from_dict(model["sphere_heights"])
            dz = heights.dz(map_, uv, np.atleast_1d(diameter_px))
            relative = heights.to_true(relative, dz)
            if cov is not None:  # to_true scales about the camera's foot point
                cov = cov * (((heights.height - dz) / heights.height) ** 2)[:, None, None]
        if not self.rides_arm(camera):
            return relative, _per_axis(cov, len(uv))
        if arm_pose is None:
            raise CalibrationInputError(f"{camera} rides the arm: locating with it needs the arm's pose")
        R = rot(arm_pose.alpha - math.radians(model["alpha1_deg"]))
        D = np.array([model["d_x_um"], model["d_y_um"]]) * 1e-6
        located = np.array([arm_pose.x, arm_pose.y]) + (np.eye(2) - R) @ D + relative @ R.T
        if cov is not None and "d_covariance_um2" in model:
            cov = self._onboard_covariance(model, uv, cov, R)
        return located, _per_axis(cov, len(uv))

    @staticmethod
    def _map_covariance(model: dict, uv: np.ndarray) -> np.ndarray | None:
        if "uncertainty" not in model:
            return None
        full = MapUncertainty.from_dict(model["uncertainty"]).point_covariance(uv)
        return np.array([full[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(len(uv))])

    @staticmethod
    def _onboard_covariance(model: dict, uv: np.ndarray, map_cov: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Of P + (I - R) D + R A_b: the map's part turned by R, D's through (I - R), and their correlation."""
        J = MapUncertainty.from_dict(model["uncertainty"]).jacobian(uv)  # (2N, n): theta -> m
        c_dd = np.asarray(model["d_covariance_um2"], dtype=float) * 1e-12
        c_md = np.asarray(model.get("d_map_covariance", np.zeros((J.shape[1], 2))), dtype=float) * 1e-6
        I_R = np.eye(2) - R
        out = []
        for i, c in enumerate(map_cov):
            cross = R @ J[2 * i:2 * i + 2] @ c_md @ I_R.T
            out.append(R @ c @ R.T + I_R @ c_dd @ I_R.T + cross + cross.T)
        return np.array(out)

    def tool_shift(self, alpha_rel: float) -> np.ndarray:
        """How far the nozzle sits, turned by alpha_rel from alpha_cal, from where the cameras' maps expect it
        (zero if uncalibrated). The maps refer to the nozzle as it was when they were made: its offset then is
        the calibration's `reference_*_um` (a nozzle touched up since: the offset before; else the offset)."""
        model = self.calibrations.get(self.tool)
        if model is None:
            return np.zeros(2)
        offset = np.array([model["dx_um"], model["dy_um"]]) * 1e-6
        reference = np.array([model.get("reference_dx_um", model["dx_um"]),
                              model.get("reference_dy_um", model["dy_um"])]) * 1e-6
        return rot(alpha_rel) @ offset - reference


def map_sigma(model: dict, uv) -> np.ndarray:
    """1-σ per axis (plane units) of a camera model's map at each pixel, from its covariance (it grows outside the
    calibrated region); NaN when the model keeps none."""
    uv = np.atleast_2d(np.asarray(uv, dtype=float))
    return _per_axis(CellCalibration._map_covariance(model, uv), len(uv))


def _per_axis(cov: np.ndarray | None, n: int) -> np.ndarray:
    if cov is None:
        return np.full(n, np.nan)
    return np.sqrt(np.clip(np.trace(cov, axis1=1, axis2=2) / 2, 0, None))


class ToolCompensatedArm:
    """An Arm whose targets are where the nozzle should be, at any rotation: it commands the axis off the
    target by the calibrated tool offset (seed 001 section 8)."""

    def __init__(self, arm: Arm, calibration: CellCalibration, alpha_cal: float = 0.0):
        self.arm, self.calibration, self.alpha_cal = arm, calibration, alpha_cal

    def __getattr__(self, name):  # everything else is the arm's own
        return getattr(self.arm, name)

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        shift = self.calibration.tool_shift(target.alpha - self.alpha_cal)
        self.arm.move_linear(Pose(target.x - shift[0], target.y - shift[1], target.z, target.alpha), speed)

    def move_through(self, target: Pose, speed: float | None = None) -> None:
        """A via point (MovesThrough), compensated alike."""
        shift = self.calibration.tool_shift(target.alpha - self.alpha_cal)
        move_via(self.arm, Pose(target.x - shift[0], target.y - shift[1], target.z, target.alpha), speed)
