"""vr-coarse: operator-interactive coarse matching (seed 000 section VI, steps 1-5).

One stop: both cameras grab a frame, the operator clicks at least `min_clicks`
model points and their image points per object and view (Fig. 6), then the
point-based sequential update (camera calibrations on the ORU, receptacle
localisation from both views) and the point-based simultaneous update (20
variables). The result, cameras and receptacle in the robot frame, becomes the
active `vr` calibration that vr-fine and vr-approach start from.
"""

from __future__ import annotations

import math
from typing import ClassVar

from scipy.spatial.transform import Rotation

from geometry.transforms import matrix_of

from calibration.routines.base import Devices, FitOutcome, Step, StepResult, Table
from calibration.routines.vr._common import (
    CAM,
    INCH,
    Estimate,
    VrParams,
    capture_both,
    click_observations,
    initial_estimate,
    load_models,
    operator_of,
    overlay_frame,
    point_coarse,
)
from calibration.routines.vr._samples import (
    ESTIMATE_FIT_COLUMNS,
    SAMPLE_COLUMNS,
    estimate_from,
    frame_ids,
    has_estimate,
    result_row,
)


class VrCoarseParams(VrParams):
    pass


def coarse_at_stop(params: VrParams, devices: Devices, setup: dict | None = None):
    """Frames, the coarse estimate and the point-based results at the arm's current pose."""
    models = load_models(params)
    est0 = initial_estimate(params, devices, matrix_of(devices.arm.pose()), setup)
    frames = capture_both(params, devices)
    obs = click_observations(params, devices, frames, models, est0)
    est, results = point_coarse(params, est0, obs)
    return models, frames, est, results


def start_at_stop(params: VrParams, devices: Devices, start: Estimate | None, setup: dict | None = None):
    """Models, frames and the estimate to update at the arm's current pose: `start` with the ORU where the arm
    now reports it, or (`start` None) the coarse matching here."""
    if start is None:
        models, frames, est, _ = coarse_at_stop(params, devices, setup)
        return models, frames, est
    est = start.with_oru(matrix_of(devices.arm.pose()))
    return load_models(params), capture_both(params, devices), est


def summary_model(rows: list[dict], method: str) -> dict:
    """The `vr` calibration: the last estimate of `method` (cameras, ORU, receptacle; 4x4 matrices, m, px)."""
    chosen = [r for r in rows if r.get("method") == method and has_estimate(r)]
    if not chosen:
        return {"kind": "vr-scene"}
    est = estimate_from(chosen[-1])
    return {"kind": "vr-scene", "estimate": est.to_dict(), "alignment": est.alignment().tolist(),
            "focal_px": [c.f for c in est.cameras]}


METHOD_TEXT = {
    "point-objloc12": "each camera calibrated on the ORU, then the receptacle located from both views (point-based "
                      "sequential update, the operator's clicks)",
    "point-simultaneous": "cameras and receptacle solved together from the operator's clicks (20 variables)",
    "simultaneous": "cameras and receptacle solved together from the image lines detected beside the projected "
                    "models (line-based simultaneous update)",
}
SIGMA_TEXT = ("σ: the predicted 1σ of the ORU's alignment with the receptacle (position: vector sum over x, y, z; "
              "rotation: over the three rotations).")


def matching_table(rows: list[dict]) -> Table:
    """Each matching the run solved: its image residuals, solver iterations and the predicted accuracy."""
    ok = [r for r in rows if r.get("method") and r.get("status", "ok") == "ok" and r.get("rms_px") is not None]
    methods = "; ".join(f"{m}: {METHOD_TEXT[m]}" for m in dict.fromkeys(r["method"] for r in ok) if m in METHOD_TEXT)
    return {"title": "Matching: image residuals and predicted alignment accuracy",
            "columns": ["method", "points", "lines", "RMS (px)", "max (px)", "iterations", "converged",
                        "σ position (in)", "σ rotation (deg)"],
            "rows": [[r["method"], r.get("n_points"), r.get("n_lines"), _round(r["rms_px"], 3),
                      _round(r.get("max_px"), 3), r.get("iterations"), "yes" if r.get("converged") else "no",
                      _round(r.get("sigma_pos_in"), 3), _round(r.get("sigma_ori_deg"), 2)] for r in ok],
            "note": f"{methods}. RMS, max: the image residuals of the fit. {SIGMA_TEXT}"}


def scene_table(est: Estimate) -> Table:
    """The fitted scene: the receptacle and the cameras in the robot frame, and what the cell needs of them,
    the ORU's pose in the receptacle frame."""
    rows = []
    for label, T in (("receptacle, robot frame", est.receptacle), ("ORU, receptacle frame", est.alignment())):
        rows.append([label, *(_round(v / INCH, 3) for v in T[:3, 3]), "in",
                     _round(math.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()), 2), None])
    for name, cam in zip(CAM, est.cameras):
        centre = -cam.V[:3, :3].T @ cam.V[:3, 3]
        rows.append([f"{name} camera centre, robot frame", *(_round(v, 3) for v in centre), "m", None,
                     _round(cam.f, 1)])
    return {"title": "Fitted scene", "columns": ["object", "x", "y", "z", "unit", "rotation (deg)", "f (px)"],
            "rows": rows, "note": "rotation: the angle of the object's rotation from the frame's axes; f: the "
                                  "camera's fitted focal length."}


def _round(value, digits: int):
    return None if value is None else round(float(value), digits)


def row_stats(r: dict) -> dict:
    keys = ("rms_px", "max_px", "n_lines", "n_points", "iterations", "converged", "sigma_pos_in", "sigma_ori_deg",
            "pos_err_in", "ori_err_deg")
    return {k: r[k] for k in keys if r.get(k) is not None}


class SceneRoutine:
    """What vr-coarse and vr-fine share: one stop, whose last `model_method` estimate is the `vr` calibration."""

    sample_columns: ClassVar[tuple[str, ...]] = SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = ("method", *ESTIMATE_FIT_COLUMNS, "rms_px")
    model_method: ClassVar[str]

    def output(self, params, devices: Devices) -> str | None:
        return "vr"

    def fit(self, samples: list[dict], params, resolutions=None) -> FitOutcome:
        stats = {r["method"]: row_stats(r) for r in samples if r.get("method")}
        model = summary_model(samples, self.model_method)
        tables = [matching_table(samples)]
        if "estimate" in model:
            tables.append(scene_table(Estimate.from_dict(model["estimate"])))
        return FitOutcome(model, stats, tables=tables)


class VrCoarse(SceneRoutine):
    name: ClassVar[str] = "vr-coarse"
    truth: ClassVar[str | None] = "cellctl.truth.vr:vr_truth"
    Params: ClassVar[type[VrCoarseParams]] = VrCoarseParams
    model_method: ClassVar[str] = "point-simultaneous"

    def inputs(self, params, devices: Devices) -> list[str]:
        return []

    def plan(self, params, devices: Devices) -> list[Step]:
        operator_of(devices, self.name)  # refuse before anything moves
        return [Step(0, "coarse", {})]

    def execute(self, step: Step, params, devices: Devices, history=()) -> StepResult:
        models, frames, est, results = coarse_at_stop(params, devices)
        rows = []
        for name in ("objloc12", "simultaneous"):
            r = results[name]
            stage = Estimate(r.cameras, est.oru, r.objects[1].M)
            rows.append(dict(result_row(f"point-{name}", stage, r, None), step=step.index, kind="coarse",
                             **frame_ids(frames), status="ok"))
        view = overlay_frame(frames, est, models, "point-based simultaneous", "coarse")
        return StepResult(rows, [*frames, view])
