"""pick-place: the production job a calibrated cell exists for.

Pick a part (a sphere) at a robot position, or the feature a camera sees nearest to that position, and place it
at (x_mm, y_mm, alpha_deg) in an area, with the active tool compensation and camera 1's centring check as
place-test does (steps.deliver_sphere). The area's calibrated camera then measures where it landed: the result
holds each placement's measured error. An MES sends one job per part (x_mm, y_mm, alpha_deg); `places` takes
several in one job, one step each.

A target outside the area (less a margin) or the arm's limits, a pick position outside the arm's limits, or an
area whose camera has no active calibration is refused at submit (`check_targets`) and again by the plan, before
anything moves.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.routines.base import Area, Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.steps import deliver_sphere, new_spheres
from calibration.routines.tables import radial_error_tables
from calibration.stats import error_stats
from calibration.usage import CellCalibration
from calibration.vision.centroid import find_blobs


class Placement(Params):
    x_mm: float = Field(..., description="target, robot frame")
    y_mm: float = Field(..., description="target, robot frame")
    alpha_deg: float = Field(0.0, ge=-360, le=360, description="the part's rotation when placed")


class PickPlaceParams(Params):
    area: str = Field("area2", description="where the part is placed; its calibrated camera measures it")
    x_mm: float | None = Field(None, description="target (one part per job, as an MES sends it)")
    y_mm: float | None = Field(None, description="target")
    alpha_deg: float = Field(0.0, ge=-360, le=360, description="the part's rotation when placed")
    places: list[Placement] = Field(default_factory=list, max_length=1000,
                                    description="several targets in one job, instead of x_mm, y_mm, alpha_deg")
    margin_mm: float = Field(1.0, ge=0, le=100, description="targets keep this far inside the area")
    pick_mm: tuple[float, float] | None = Field(None, description="where to pick (robot frame)")
    pick_z_mm: float = Field(0.0, description="height of the surface the part lies on at the pick")
    pick_camera: str | None = Field(None, description="pick the feature this camera sees nearest to pick_mm "
                                    "(a camera on the arm looks from view_z_mm over it); none: pick at pick_mm")
    pick_radius_mm: float = Field(2.0, gt=0, le=100, description="the feature must lie this close to pick_mm")
    view_z_mm: float = Field(20.5, description="gripper height at which the on-board camera sees the floor in focus")
    mount_offset_mm: tuple[float, float] | None = Field(None, description="nominal on-board camera offset")
    park_mm: tuple[float, float, float] | None = Field(None, description="out of every fixed camera's view")
    centring_area: str | None = Field(None, description="measure the held part's offset on the nozzle with this "
                                      "area's calibrated camera (area1: camera 1) and place it compensated")
    sphere_diameter_mm: float = Field(1.0, gt=0, le=10, description="nominal")
    sphere_tolerance_mm: float = Field(0.2, ge=0, le=5, description="+/- on the diameter")

    def targets(self) -> list[Placement]:
        if self.places:
            return list(self.places)
        if self.x_mm is None or self.y_mm is None:
            return []
        return [Placement(x_mm=self.x_mm, y_mm=self.y_mm, alpha_deg=self.alpha_deg)]


class PickPlace:
    name: ClassVar[str] = "pick-place"
    truth: ClassVar[str | None] = "cellctl.truth.micro:place_test_truth"
    Params: ClassVar[type[PickPlaceParams]] = PickPlaceParams
    small_params: ClassVar[dict] = {"places": [{"x_mm": 104.0, "y_mm": 36.0, "alpha_deg": 35.0},
                                               {"x_mm": 116.0, "y_mm": 45.0, "alpha_deg": -120.0}]}
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "status", "target_x_mm", "target_y_mm", "alpha_deg", "pick_x_mm", "pick_y_mm", "landed_x_mm",
        "landed_y_mm", "meas_x_mm", "meas_y_mm", "err_um", "sigma_um", "u_px", "v_px", "diameter_px",
        "centring_x_um", "centring_y_um", "message",
    )
    fit_columns: ClassVar[tuple[str, ...]] = ("status", "target_x_mm", "target_y_mm", "meas_x_mm", "meas_y_mm")

    def inputs(self, params: PickPlaceParams, devices: Devices) -> list[str]:
        used = [devices.area(params.area).camera, "nozzle"]
        if params.centring_area:
            used.append(devices.area(params.centring_area).camera)
        if params.pick_camera:
            used.append(params.pick_camera)
        return list(dict.fromkeys(used))

    def output(self, params, devices: Devices) -> str | None:
        return None  # production, not a calibration

    def check_targets(self, params: PickPlaceParams, areas: dict[str, Area], calibrations: dict[str, dict],
                      arm_limits: dict | None = None) -> None:
        if params.area not in areas:
            raise CalibrationInputError(f"area: {params.area!r} is not an area of the cell; allowed: "
                                        f"{', '.join(sorted(areas)) or 'none'}")
        area = areas[params.area]
        if area.camera not in calibrations:
            calibrated = sorted(n for n, a in areas.items() if a.camera in calibrations)
            raise CalibrationInputError(f"area: {params.area} has no active calibration (its camera {area.camera} "
                                        f"is not calibrated); allowed: {', '.join(calibrated) or 'none yet'}")
        for name, what in (("nozzle", "the tool compensation"),
                           *(((areas[params.centring_area].camera, f"centring with {params.centring_area}"),)
                             if params.centring_area in areas else ())):
            if name not in calibrations:
                raise CalibrationInputError(f"pick-place needs an active calibration of {name!r} for {what}; "
                                            "calibrate it first (calibrate-cell)")
        if params.centring_area is not None and params.centring_area not in areas:
            raise CalibrationInputError(f"centring_area: {params.centring_area!r} is not an area of the cell; "
                                        f"allowed: {', '.join(sorted(areas))} or none")
        if params.pick_camera is not None and params.pick_camera not in calibrations:
            raise CalibrationInputError(f"pick_camera: {params.pick_camera!r} has no active calibration; allowed: "
                                        f"{', '.join(sorted(t for t in calibrations if t != 'nozzle')) or 'none'}")
        targets = params.targets()
        if not targets:
            raise CalibrationInputError("x_mm, y_mm: pick-place needs a target: x_mm and y_mm (and alpha_deg), or "
                                        "places: [{x_mm, y_mm, alpha_deg}, ...]")
        if params.places and params.x_mm is not None:
            raise CalibrationInputError("x_mm, places: give one target (x_mm, y_mm, alpha_deg) or places, not both")
        if params.pick_mm is None or params.park_mm is None:
            raise CalibrationInputError("pick_mm, park_mm: pick-place needs where to pick and where to wait out of "
                                        "view (set them under routines.pick-place in the cell file, or as parameters)")
        half = np.array(area.size) / 2 - params.margin_mm * 1e-3
        lo, hi = (np.array(area.centre) - half) * 1e3, (np.array(area.centre) + half) * 1e3
        for i, t in enumerate(targets):
            where = f"places[{i}]." if params.places else ""
            for axis, value, a, b in (("x_mm", t.x_mm, lo[0], hi[0]), ("y_mm", t.y_mm, lo[1], hi[1])):
                if not a <= value <= b:
                    raise CalibrationInputError(
                        f"{where}{axis}: {value:g} is outside area {params.area} less its margin of "
                        f"{params.margin_mm:g} mm; allowed: {a:.3f} to {b:.3f}")
            _within(arm_limits, {"x_mm": t.x_mm, "y_mm": t.y_mm, "alpha_deg": t.alpha_deg}, where)
        _within(arm_limits, dict(zip(("x_mm", "y_mm"), params.pick_mm)), "pick_mm: ")

    def plan(self, params: PickPlaceParams, devices: Devices) -> list[Step]:
        self.check_targets(params, devices.areas, devices.calibrations)
        if devices.gripper is None:
            raise CalibrationInputError("pick-place needs a gripper")
        if params.pick_camera is not None and _on_arm(devices.calibrations[params.pick_camera]) \
                and params.mount_offset_mm is None:
            raise CalibrationInputError(f"mount_offset_mm: {params.pick_camera} rides the arm: its nominal offset "
                                        "says where to look from")
        area = devices.area(params.area)
        contact = area.z + (params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
        return [Step(i, "pick-place", {"x": t.x_mm * 1e-3, "y": t.y_mm * 1e-3, "z": contact,
                                       "alpha": math.radians(t.alpha_deg)})
                for i, t in enumerate(params.targets())]

    def execute(self, step: Step, params: PickPlaceParams, devices: Devices, history=()) -> StepResult:
        a = step.args
        cal = CellCalibration(devices.calibrations)
        area = devices.area(params.area)
        target = Pose(a["x"], a["y"], a["z"], a["alpha"])
        row = {"step": step.index, "target_x_mm": a["x"] * 1e3, "target_y_mm": a["y"] * 1e3,
               "alpha_deg": math.degrees(a["alpha"])}
        frames = []
        before, frame = self._look(params, devices, cal, area.camera, (a["x"], a["y"]))  # what lay there already
        frames.append(frame)
        pick = np.array(params.pick_mm) * 1e-3
        if params.pick_camera is not None:
            seen, frame = self._look(params, devices, cal, params.pick_camera, tuple(pick))
            frames.append(frame)
            near = [s for s in seen if np.hypot(*(s[0] - pick)) <= params.pick_radius_mm * 1e-3]
            if not near:
                return StepResult(dict(row, status="no-feature", message=f"{params.pick_camera} sees no part within "
                                       f"{params.pick_radius_mm:g} mm of pick_mm {list(params.pick_mm)}"), frames)
            pick = min(near, key=lambda s: np.hypot(*(s[0] - pick)))[0]
        contact = (params.pick_z_mm + params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
        done = deliver_sphere(devices, tuple(pick), contact, target, area.alpha_cal, params.centring_area,
                              params.sphere_diameter_mm * 1e-3, tuple(v * 1e-3 for v in params.park_mm), area.camera,
                              0.0)
        frames += done.frames
        row.update(pick_x_mm=pick[0] * 1e3, pick_y_mm=pick[1] * 1e3, landed_x_mm=done.landed[0] * 1e3,
                   landed_y_mm=done.landed[1] * 1e3, centring_x_um=done.offset[0] * 1e6,
                   centring_y_um=done.offset[1] * 1e6)
        if _on_arm(devices.calibrations[area.camera]):  # the park is out of its view: look over the target
            after, frame = self._look(params, devices, cal, area.camera, (a["x"], a["y"]))
            frames.append(frame)
        else:
            after = self._located(cal, area.camera, done.frames[-1], None)
        fresh = new_spheres([s[2] for s in after], [(s[2].u, s[2].v) for s in before])
        if len(fresh) != 1:
            return StepResult(dict(row, status="no-feature", message=f"{len(fresh)} new parts seen by {area.camera}, "
                                   "expected 1"), frames)
        xy, sigma, blob = next(s for s in after if s[2] is fresh[0])
        err = float(np.hypot(*(xy - [a["x"], a["y"]])))
        return StepResult(dict(row, status="ok", meas_x_mm=xy[0] * 1e3, meas_y_mm=xy[1] * 1e3, err_um=err * 1e6,
                               sigma_um=sigma * 1e6, u_px=blob.u, v_px=blob.v, diameter_px=blob.diameter_px,
                               message=""), frames)

    def _look(self, params: PickPlaceParams, devices: Devices, cal: CellCalibration, camera: str, near):
        """The parts `camera` sees, located ([(xy m, sigma m, blob)]), and its frame: a camera on the arm from
        view_z_mm over `near`, a fixed one with the arm parked out of view."""
        if _on_arm(devices.calibrations[camera]):
            mx, my = (v * 1e-3 for v in params.mount_offset_mm)
            devices.arm.move_linear(Pose(near[0] - mx, near[1] - my, params.view_z_mm * 1e-3, 0.0))
            pose = devices.arm.pose()
        else:
            devices.arm.move_linear(Pose(*(v * 1e-3 for v in params.park_mm), 0.0))
            pose = None
        frame = devices.camera(camera).capture()
        return self._located(cal, camera, frame, pose), frame

    @staticmethod
    def _located(cal: CellCalibration, camera: str, frame, pose) -> list:
        try:
            blobs = find_blobs(frame.image)
        except VisionError:
            return []
        if not blobs:
            return []
        xy, sigma = cal.locate_with_sigma(camera, [(b.u, b.v) for b in blobs], pose, [b.diameter_px for b in blobs])
        return list(zip(xy, sigma, blobs))

    def fit(self, samples: list[dict], params, resolutions=None) -> FitOutcome:
        ok = [r for r in samples if r.get("status") == "ok"]
        err = np.array([math.hypot(float(r["meas_x_mm"]) - float(r["target_x_mm"]),
                                   float(r["meas_y_mm"]) - float(r["target_y_mm"])) for r in ok]) * 1e-3
        rejected = [{"step": r.get("step"), "reason": r.get("message")} for r in samples if r.get("status") != "ok"]
        stats = {"verification": error_stats(err)}
        placements = {"title": "Placements: target and where the area's camera measured the part",
                      "columns": ["step", "target x_mm", "target y_mm", "alpha_deg", "measured x_mm", "measured y_mm",
                                  "error µm", "camera 1-σ µm"],
                      "rows": [[int(r["step"]), round(float(r["target_x_mm"]), 4), round(float(r["target_y_mm"]), 4),
                                round(float(r["alpha_deg"]), 2), round(float(r["meas_x_mm"]), 4),
                                round(float(r["meas_y_mm"]), 4), round(float(e) * 1e6, 2),
                                _rounded(r.get("sigma_um"))] for r, e in zip(ok, err)],
                      "note": "error: radial, measured minus target; camera 1-σ: the measuring camera's own "
                              "calibration uncertainty there, per axis"}
        return FitOutcome({"kind": "pick-place"}, stats, rejected,
                          tables=[*radial_error_tables(stats), placements])


def _on_arm(model: dict) -> bool:
    return model.get("kind") == "onboard-camera"


def _rounded(value) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return round(v, 2) if math.isfinite(v) else None


def _within(limits: dict | None, values: dict[str, float], where: str) -> None:
    """Each value inside the arm's workspace box (cell file, mm and degrees), when the box is known."""
    for key, value in values.items():
        box = (limits or {}).get(key)
        if box is not None and not box[0] <= value <= box[1]:
            raise CalibrationInputError(f"{where}{key}: {value:g} is outside the arm's limits; allowed: "
                                        f"{box[0]:g} to {box[1]:g}")
