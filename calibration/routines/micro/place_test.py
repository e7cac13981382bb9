"""place-test: the calibrations used to pick and place (what seed 001 leaves implicit).

For each sphere: the on-board camera finds it at the supply (eq. 5), the arm picks it
there, camera 1 measures its offset on the nozzle (`centring_area`, as area2's virtual
grid does), and the arm places it at a commanded position of area2 with an arbitrary
rotation, the tool offset and the sphere's offset compensated; the calibrated top
camera measures where it landed.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.routines.base import Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.steps import deliver_sphere, new_spheres
from calibration.routines.tables import radial_error_tables
from calibration.stats import error_stats
from calibration.usage import CellCalibration
from calibration.vision.centroid import find_blob, find_blobs


class PlaceTestParams(Params):
    area: str = Field("area2", description="where the spheres are placed (its camera measures them)")
    locate_area: str = Field("board", description="area of the on-board camera's calibration")
    n: int = Field(12, ge=1, le=1000, description="spheres picked, placed and measured")
    margin_mm: float = Field(3.0, ge=0, le=100, description="keep-out from the area's edge")
    plan_seed: int = Field(0, ge=0, description="draws where each sphere goes, and its alpha")
    sphere_diameter_mm: float = Field(1.0, description="nominal sphere diameter")
    sphere_tolerance_mm: float = Field(0.2, description="+/- on the sphere diameter")
    supply_mm: tuple[float, float] | None = Field(None, description="roughly where the feeder presents a sphere")
    view_z_mm: float = Field(20.5, description="gripper height at which the on-board camera sees the floor in focus")
    mount_offset_mm: tuple[float, float] | None = Field(None, description="nominal on-board camera offset")
    park_mm: tuple[float, float, float] | None = Field(None, description="where the arm waits out of the "
                                                       "camera's view while it measures")
    centring_area: str | None = Field(None, description="measure each picked sphere's offset on the nozzle with "
                                      "this area's calibrated camera (area1: camera 1) and place it compensated")


class PlaceTest:
    name: ClassVar[str] = "place-test"
    truth: ClassVar[str | None] = "cellctl.truth.micro:place_test_truth"
    Params: ClassVar[type[PlaceTestParams]] = PlaceTestParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "set", "status", "alpha_deg", "found_x_mm", "found_y_mm", "target_x_mm", "target_y_mm",
        "meas_x_mm", "meas_y_mm", "u_px", "v_px", "centring_x_um", "centring_y_um", "message",
    )
    fit_columns: ClassVar[tuple[str, ...]] = ("target_x_mm", "target_y_mm", "meas_x_mm", "meas_y_mm")

    def inputs(self, params, devices: Devices) -> list[str]:
        centring = [devices.area(params.centring_area).camera] if params.centring_area else []
        return [devices.area(params.area).camera, devices.area(params.locate_area).camera, "nozzle", *centring]

    def output(self, params, devices: Devices) -> str | None:
        return None  # a test, not a calibration

    def plan(self, params: PlaceTestParams, devices: Devices) -> list[Step]:
        for target in self.inputs(params, devices):
            devices.calibration(target, self.name)
        if None in (params.supply_mm, params.mount_offset_mm, params.park_mm):
            raise CalibrationInputError("place-test needs supply_mm, mount_offset_mm and park_mm (cell file)")
        area = devices.area(params.area)
        half = np.array(area.size) / 2 - params.margin_mm * 1e-3
        spacing = 3 * (params.sphere_diameter_mm + params.sphere_tolerance_mm) * 1e-3
        rng = np.random.default_rng(params.plan_seed)
        targets: list[tuple[float, float]] = []
        while len(targets) < params.n:
            x, y = rng.uniform(np.array(area.centre) - half, np.array(area.centre) + half)
            if all(math.hypot(x - a, y - b) >= spacing for a, b in targets):
                targets.append((float(x), float(y)))
        return [Step(i, "pick-place", {"x": x, "y": y, "alpha": float(np.radians(rng.uniform(-180, 180)))})
                for i, (x, y) in enumerate(targets)]

    def execute(self, step: Step, params: PlaceTestParams, devices: Devices, history=()) -> StepResult:
        a = step.args
        cal = CellCalibration(devices.calibrations)
        row = {"step": step.index, "set": "ver", "alpha_deg": math.degrees(a["alpha"]),
               "target_x_mm": a["x"] * 1e3, "target_y_mm": a["y"] * 1e3}
        try:
            found = self._locate_supply(params, devices, cal)
        except VisionError as exc:
            return StepResult(dict(row, status="no-feature", message=f"supply: {exc}"))
        contact = (params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
        camera = devices.area(params.area).camera
        done = deliver_sphere(devices, tuple(found), contact, Pose(a["x"], a["y"], contact, a["alpha"]),
                              devices.area(params.area).alpha_cal, params.centring_area,
                              params.sphere_diameter_mm * 1e-3, tuple(v * 1e-3 for v in params.park_mm), camera, 0.0)
        seen = [(r["u_px"], r["v_px"]) for r in history if r.get("status") == "ok"]
        fresh = new_spheres(find_blobs(done.frames[-1].image), seen)
        if len(fresh) != 1:
            return StepResult(dict(row, status="no-feature", message=f"{len(fresh)} new spheres seen, expected 1"),
                              done.frames)
        measured = cal.locate(camera, [fresh[0].u, fresh[0].v], diameter_px=fresh[0].diameter_px)[0] * 1e3
        return StepResult(dict(row, status="ok", found_x_mm=found[0] * 1e3, found_y_mm=found[1] * 1e3,
                               meas_x_mm=measured[0], meas_y_mm=measured[1], u_px=fresh[0].u, v_px=fresh[0].v,
                               centring_x_um=done.offset[0] * 1e6, centring_y_um=done.offset[1] * 1e6, message=""),
                          done.frames)

    def _locate_supply(self, params, devices: Devices, cal: CellCalibration) -> np.ndarray:
        """The on-board camera over the supply: where exactly is the sphere?"""
        x, y = (v * 1e-3 for v in params.supply_mm)
        mx, my = (v * 1e-3 for v in params.mount_offset_mm)
        devices.arm.move_linear(Pose(x - mx, y - my, params.view_z_mm * 1e-3, 0.0))
        pose = devices.arm.pose()
        camera = devices.area(params.locate_area).camera
        blob = find_blob(devices.camera(camera).capture().image)
        return cal.locate(camera, [blob.u, blob.v], pose, diameter_px=blob.diameter_px)[0]

    def fit(self, samples: list[dict], params, resolutions=None) -> FitOutcome:
        ok = [r for r in samples if r.get("status", "ok") == "ok"]
        err = np.array([math.hypot(r["meas_x_mm"] - r["target_x_mm"], r["meas_y_mm"] - r["target_y_mm"])
                        for r in ok]) * 1e-3
        rejected = [{"step": r.get("step"), "reason": r.get("message")} for r in samples if r.get("status") != "ok"]
        stats = {"verification": error_stats(err)}
        return FitOutcome({"kind": "place-test"}, stats, rejected, tables=radial_error_tables(stats))
