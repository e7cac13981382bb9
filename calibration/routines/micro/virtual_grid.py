"""Virtual-grid calibration (seed 001 sections 5.2, 6.1.2, appendix B).

The robot itself draws the calibration grid: it moves the nozzle (or a held
sphere) to R x C known positions at constant rotation alpha_cal, the camera
measures each, and the planar B1+B2 model is fitted from pixels to robot
coordinates. Camera calibration and robot registration come out together.
Verification moves to points the fit never saw and compares the commanded
position with the one the calibrated camera measures (section 5.3).
"""

from __future__ import annotations

from dataclasses import replace
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from calibration.baseline import OpenCVPlanarMap, baseline_stats
from calibration.errors import CalibrationInputError
from calibration.models.planar import PlanarModelOptions, fit_planar_map
from calibration.models.sphere_height import SphereHeights, diameter_column
from calibration.routines import targeted
from calibration.routines.base import (
    Devices,
    FitOutcome,
    PlanarFitParams,
    Step,
    StepResult,
    execute_split,
    image_residuals,
)
from calibration.routines.steps import Look, look, measure_look, visit_pose
from calibration.routines.tables import with_seed_table_ii
from calibration.stats import error_stats

CAL, VER = "cal", "ver"
# default target: today's figure + 2 %. The figure is mostly the arm's repeatability, and the map's own error
# carries into everything the camera measures later (the tool offset's check, the spheres' centring): 2 % keeps
# the map's true error within about 1.5x of the whole grid's (5 % would let it double)
EXCESS = 0.02

# Seed 001 Table II, virtual grid: radial error e (µm) as (mean, max, "RMS", n), per area it was run on.
SEED_TABLE_II = {"area1": {"calibration": (3.9, 8.8, 1.7, 56), "verification": (6.3, 19.0, 3.1, 56)}}


class VirtualGridParams(PlanarFitParams):
    area: str = Field("area1", description="working area of the cell file")
    rows: int = Field(8, ge=2, le=100, description="rows of the grid the nozzle draws")
    cols: int = Field(7, ge=2, le=100, description="columns of that grid")
    passes: int = Field(2, ge=1, le=10, description="visits of every grid position (repeatability averages out)")
    n_verify: int = Field(56, ge=0, le=10000, description="random verification points the fit never sees")
    margin_mm: float = Field(1.0, ge=0, le=100, description="keep-out from the edge of the area")
    plan_seed: int = Field(0, ge=0, description="draws the verification points")
    polarity: Literal["bright", "dark"] = Field("bright", description="the nozzle in the image: bright on dark, or dark on bright")
    target_um: float | None = Field(None, gt=0, le=10000, description="predicted RMS error of a located point to "
                                    "reach (95 % upper bound) before the grid stops; none: today's figure (what the "
                                    "whole grid, rows x cols x passes, is predicted to reach) + 2 %. A target below "
                                    "the cell's repeatability spends the whole grid")

    @model_validator(mode="after")
    def _enough_points(self):
        if self.rows * self.cols < 9:
            raise ValueError(f"rows x cols = {self.rows * self.cols}; at least 9 grid points are needed for the model")
        return self



class VirtualGrid:
    name: ClassVar[str] = "virtual-grid"
    truth: ClassVar[str | None] = "cellctl.truth.micro:virtual_grid_truth"
    Params: ClassVar[type[VirtualGridParams]] = VirtualGridParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "set", "status", "camera", "frame_id",
        "cmd_x_mm", "cmd_y_mm", "z_mm", "alpha_abs_deg", "x_mm", "y_mm",
        "u_px", "v_px", "diameter_px", "snr", "message",
    )

    fit_columns: ClassVar[tuple[str, ...]] = ("x_mm", "y_mm", "u_px", "v_px", "set")

    # -- plan ----------------------------------------------------------------
    def plan(self, params: VirtualGridParams, devices: Devices) -> list[Step]:
        area = devices.area(params.area)
        half = np.array(area.size) / 2 - params.margin_mm * 1e-3
        if np.any(half <= 0):
            raise CalibrationInputError(
                f"margin_mm={params.margin_mm} leaves no room in area {area.name} of size "
                f"{area.size[0] * 1e3:.3f} x {area.size[1] * 1e3:.3f} mm"
            )
        cx, cy = area.centre
        xs = np.linspace(cx - half[0], cx + half[0], params.cols)
        ys = np.linspace(cy - half[1], cy + half[1], params.rows)
        # the budget, information first: the grid as two interleaved checkerboards (each alone covers the whole
        # area, so the first half already supports the full model), each in serpentine order (short moves)
        grid = []
        for colour in (0, 1):
            for r, y in enumerate(ys):
                row = [(CAL, x, y) for c, x in enumerate(xs) if (r + c) % 2 == colour]
                grid += row if r % 2 == 0 else row[::-1]
        targets = []
        for p in range(params.passes):  # every other pass runs backwards: each point approached both ways
            targets += grid if p % 2 == 0 else grid[::-1]
        rng = np.random.default_rng(params.plan_seed)
        checks = np.column_stack([rng.uniform(cx - half[0], cx + half[0], params.n_verify),
                                  rng.uniform(cy - half[1], cy + half[1], params.n_verify)])
        start = np.array(targets[-1][1:] if targets else (cx, cy))
        for k in targeted.nearest_neighbour_order(checks, start, _distance):  # a short tour of the checks
            targets.append((VER, *checks[k]))
        return [
            Step(i, "visit", {"set": s, "x": float(x), "y": float(y), "z": area.z, "alpha": area.alpha_cal,
                              "camera": area.camera})
            for i, (s, x, y) in enumerate(targets)
        ]

    def inputs(self, params: VirtualGridParams, devices: Devices) -> list[str]:
        return []

    def output(self, params: VirtualGridParams, devices: Devices) -> str | None:
        return devices.area(params.area).camera

    # -- collect -------------------------------------------------------------
    def execute(self, step: Step, params: VirtualGridParams, devices: Devices, history=()) -> StepResult:
        return execute_split(self, step, params, devices, history)

    # the step in parts (Pipelines): a visit's blob is found while the arm makes the next visit's move
    def approach(self, step: Step, params: VirtualGridParams, devices: Devices, history=()) -> None:
        devices.arm.move_linear(visit_pose(step))

    def capture(self, step: Step, params: VirtualGridParams, devices: Devices, history=()) -> Look:
        return look(devices, visit_pose(step), step.args["camera"])

    def measure(self, step: Step, captured: Look, params: VirtualGridParams, history=()) -> StepResult:
        row, frame = measure_look(captured, params.polarity)
        return StepResult({"step": step.index, "set": step.args["set"], **row}, [frame])

    def overlaps(self, step: Step) -> bool:
        return True  # every visit's target is planned: none depends on a measurement

    # -- accuracy target (calibration/routines/targeted.py) -----------------
    def budget(self, step: Step) -> bool:
        return step.args.get("set") == CAL

    def enough(self, samples: list[dict], params: VirtualGridParams) -> bool:
        p = predict_map([r for r in samples if r.get("set") == CAL], params.model_options())
        return p is not None and p.meets(params.target_um, params.rows * params.cols * params.passes, EXCESS)

    # -- fit + verify --------------------------------------------------------
    def fit(self, samples: list[dict], params: VirtualGridParams, resolutions=None) -> FitOutcome:
        outcome = with_seed_table_ii(self.fit_with(samples, params.model_options(), resolutions), SEED_TABLE_II,
                                     params.area)
        return with_stopping(outcome, samples, params, params.rows * params.cols * params.passes, EXCESS)

    @staticmethod
    def fit_with(samples: list[dict], options: PlanarModelOptions, resolutions=None,
                 working_distance: float | None = None) -> FitOutcome:
        """The fit with the image size of the samples' camera, when known ("*": any camera's)."""
        resolutions = resolutions or {}
        cameras = {r.get("camera") for r in samples} - {None, ""}
        image_size = resolutions.get(cameras.pop()) if len(cameras) == 1 else None
        return fit_virtual_grid(samples, options, image_size or resolutions.get("*"), working_distance)


def fit_virtual_grid(samples: list[dict], options: PlanarModelOptions, image_size=None,
                     working_distance: float | None = None) -> FitOutcome:
    """Fit on the `cal` rows, measure the error on the `ver` rows (the fit never sees them).

    `working_distance` (m, the lens's nominal), for spheres: correct each for its height from its
    apparent diameter (`models.sphere_height`; rows need `diameter_px`)."""
    rows = [dict(r) for r in samples]
    for i, r in enumerate(rows):
        if r.get("set") not in (CAL, VER):
            raise CalibrationInputError(f"sample {i}: set={r.get('set')!r}; allowed: 'cal' or 'ver'")
    measured = [r for r in rows if r.get("status", "ok") == "ok"]
    skipped = [{"step": r.get("step"), "reason": r.get("message") or r.get("status")}
               for r in rows if r.get("status", "ok") != "ok"]
    cal = [r for r in measured if r["set"] == CAL]
    ver = [r for r in measured if r["set"] == VER]
    if not cal:
        raise CalibrationInputError("no 'cal' samples with a measured feature: nothing to fit")

    uv_cal, xy_cal = _arrays(cal)
    if image_size is None:  # offline files carry no image size: centre the model on the pixels seen
        image_size = _pixel_extent(uv_cal)
    fit = fit_planar_map(uv_cal, xy_cal, image_size, options)
    heights = None
    if working_distance is not None:
        d_cal = diameter_column(cal)
        for _ in range(2):  # the heights need the map's scale, the map the heights: twice is converged
            heights = SphereHeights.for_map(fit.map, uv_cal, d_cal, working_distance)
            xy_plane = heights.to_map_plane(xy_cal, heights.dz(fit.map, uv_cal, d_cal))
            fit = fit_planar_map(uv_cal, xy_plane, image_size, options)
        xy_cal = heights.to_map_plane(xy_cal, heights.dz(fit.map, uv_cal, d_cal))  # what the map is judged on

    err_cal = np.linalg.norm(fit.map.pixel_to_plane(uv_cal) - xy_cal, axis=1)
    inliers = np.asarray(fit.inliers, dtype=bool)
    stats = {"calibration": error_stats(err_cal[inliers])}
    plot = {"cal_uv": uv_cal[inliers], "cal_err": image_residuals(fit.map, uv_cal, xy_cal)[inliers],
            "image_size": image_size}
    if ver:
        uv_ver, xy_ver = _arrays(ver)
        if heights is not None:  # the verification spheres are measured as a user measures one
            xy_ver = heights.to_map_plane(xy_ver, heights.dz(fit.map, uv_ver, diameter_column(ver)))
        res_ver = fit.map.pixel_to_plane(uv_ver) - xy_ver
        stats["verification"] = error_stats(np.linalg.norm(res_ver, axis=1))
        stats["baseline_opencv"] = baseline_stats(
            lambda: OpenCVPlanarMap(uv_cal[inliers], xy_cal[inliers], image_size).pixel_to_plane, uv_ver, xy_ver)
        predicted = fit.map_std(uv_ver)
        plot.update(ver_uv=uv_ver, ver_err=image_residuals(fit.map, uv_ver, xy_ver))
    else:
        stats["verification"] = error_stats(np.empty(0))
        predicted = fit.map_std(uv_cal)
    stats["predicted"] = {
        "residual_sigma_um": float(np.mean(np.atleast_1d(fit.sigma)) * 1e6),
        "map_rms_um": float(np.sqrt(np.mean(np.square(predicted))) * 1e6),
        "condition_number": float(fit.condition_number),
    }
    rejected = [{"step": cal[int(r["index"])].get("step", int(r["index"])), "set": CAL,
                 "residual_um": float(np.linalg.norm(r["residual"]) * 1e6), "reason": r["reason"]}
                for r in fit.rejected]
    model = {"kind": "virtual-grid", "plane_unit": "m", "map": fit.map.to_dict(),
             **({"sphere_heights": heights.to_dict()} if heights is not None else {}),
             "parameter_std": dict(zip(fit.param_names, np.sqrt(np.clip(np.diag(fit.covariance), 0, None)).tolist())),
             "uncertainty": fit.uncertainty().to_dict()}  # what a check needs to tell drift from noise
    return FitOutcome(model, stats, rejected + [dict(r, set="?") for r in skipped], plot)


def predict_map(cal_rows: list[dict], options: PlanarModelOptions, image_size=None,
                working_distance: float | None = None, budget: int | None = None) -> targeted.Prediction | None:
    """The predicted RMS error of a point the map locates, from the calibration rows so far: the fit's residual
    sigma (repeatability and measurement) and the map's own uncertainty, its covariance carried to a grid of
    pixels over the calibrated region's bounding box (where verification points fall). `working_distance`: the
    spheres corrected for their heights first, as `fit_virtual_grid` does. `budget`: the calibration samples of
    the whole plan, for a small one (targeted.prediction's budget_dof)."""
    ok = [r for r in cal_rows if r.get("status", "ok") == "ok"]
    if len(ok) < 9:
        return None
    uv, xy = _arrays(ok)
    try:
        size = image_size or _pixel_extent(uv)
        fit = fit_planar_map(uv, xy, size, options)
        if working_distance is not None:
            d = diameter_column(ok)
            for _ in range(2):  # as fit_virtual_grid
                heights = SphereHeights.for_map(fit.map, uv, d, working_distance)
                fit = fit_planar_map(uv, heights.to_map_plane(xy, heights.dz(fit.map, uv, d)), size, options)
    except (CalibrationInputError, np.linalg.LinAlgError, ValueError):
        return None
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    grid = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 7), np.linspace(lo[1], hi[1], 7)), -1).reshape(-1, 2)
    model_var = float(np.mean(np.square(fit.map_std(grid))))
    dof = 2 * int(np.sum(fit.inliers)) - len(fit.param_names)
    budget_dof = None if budget is None else dof + 2 * max(budget - len(cal_rows), 0)
    return targeted.prediction(len(cal_rows), float(fit.sigma), dof, model_var, budget_dof)


def with_stopping(outcome: FitOutcome, samples: list[dict], params, budget: int,
                  excess: float = targeted.EXCESS) -> FitOutcome:
    """The outcome with where its collection stopped and why (table, chart, stats["target"])."""
    options = params.model_options()
    points = targeted.curve([r for r in samples if r.get("set") == CAL], lambda rows: predict_map(rows, options))
    stats, table, chart = targeted.stopping_report(params.area, points, params.target_um, budget, excess)
    outcome.stats["target"] = stats
    return replace(outcome, tables=[*outcome.tables, table], charts=[*outcome.charts, chart])


def _distance(here: np.ndarray, there: np.ndarray) -> np.ndarray:
    return np.hypot(*(there - here).T)


def _arrays(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    uv = np.array([[float(r["u_px"]), float(r["v_px"])] for r in rows])
    xy = np.array([[float(r["x_mm"]), float(r["y_mm"])] for r in rows]) * 1e-3
    return uv, xy


def _pixel_extent(uv: np.ndarray) -> tuple[int, int]:
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    return int(round(lo[0] + hi[0] + 1)), int(round(lo[1] + hi[1] + 1))
