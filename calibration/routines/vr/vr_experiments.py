"""vr-experiments: seed 000 section VII reproduced on the cell, with the seed's figures as report tables.

The reference ("true") alignment is measured as the seed did: the operator aligns
the ORU by hand `standoff_in` in front of the receptacle and the arm's pose is
recorded; the ORU is then moved from there, and the reference alignment at any
stop follows from the arm's reported motion. (On the simulated cell the report's
`truth` section also gives the errors against the hidden truth.)

- Fig. 7: at `fig7_distance_in`, `n_runs` runs of each method from the same coarse
  matching: line-based sequential update with view 1, view 2, both (OBJLOC1, 2, 12)
  and the simultaneous update. Overlays of run 0 (the seed's Figs. 2-5).
- Figs. 8-9: for each inter-camera angle (the overhead camera re-mounted), `n_runs`
  approaches: coarse + fine at the first distance, then the intermittent update at
  each further distance, the ORU moved as the estimate places the receptacle
  (vr-approach). `stats.approach.final`: the worst run at the last stop among the
  angles >= 28 deg.
- Fig. 10: both cameras zoomed to `views` ([view width, ORU distance] pairs, 90 deg
  between the cameras as in the seed), `n_runs` runs each.
- Fig. 11: the 1-sigma ellipses of the simultaneous update at `ellipse_distance_in`.
- Covariance consistency: the alignment errors of every simultaneous update over
  their predicted 1-sigma (RMS of e/sigma per component; 1 when they agree).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from geometry.transforms import inverse, matrix_of

from calibration.models.model_matching import ellipse_summary, error_ellipse
from calibration.routines.base import Devices, FitOutcome, Step, StepResult
from calibration.routines.vr._common import (
    INCH,
    Estimate,
    VrParams,
    fine_methods,
    load_models,
    operator_of,
    overlay_frame,
    pose_of,
    translate,
)
from calibration.routines.vr._samples import (
    ERROR_COLUMNS,
    SAMPLE_COLUMNS,
    SIGMA_COLUMNS,
    covariance_cells,
    error_cells,
    error_vector,
    estimate_from,
    frame_ids,
    has_estimate,
    pose_cells,
    pose_from,
    position_covariances,
    result_row,
    sigma_vector,
)
from calibration.routines.vr.vr_approach import approach_stop, previous_estimate
from calibration.routines.vr.vr_coarse import coarse_at_stop, summary_model

METHODS = ("objloc1", "objloc2", "objloc12", "simultaneous")
SEED_FIG7 = {"objloc1": (1.57, 2.69), "objloc2": (1.64, 4.21), "objloc12": (0.53, 1.19), "simultaneous": (0.21, 0.88)}
FIGURE_OF = {"objloc1": "Fig. 2", "objloc2": "Fig. 3", "objloc12": "Fig. 4", "simultaneous": "Fig. 5"}
REQUIREMENT = (0.25, 3.0)  # in, deg: the ORU insertion's alignment requirement


class VrExperimentsParams(VrParams):
    n_runs: int = Field(5, ge=1, le=100, description="runs per condition of Figs. 8-10 (the seed: 5)")
    fig7_runs: int = Field(10, ge=1, le=100, description="runs of each method for Fig. 7 (the seed: 5; more runs "
                           "make the ratios between methods steadier)")
    fig7_distance_in: float = Field(20.0, gt=0, le=100, description="the approach stop of the Fig. 7 runs")
    distances_in: tuple[float, ...] = Field((20.0, 8.0, 4.0, 2.0), description="approach stops (Fig. 8)")
    angles_deg: tuple[float, ...] = Field((14.0, 28.0, 51.0, 90.0), description="inter-camera angles (Fig. 9)")
    views: tuple[tuple[float, float], ...] = Field(((20.0, 4.0), (28.0, 12.0), (36.0, 20.0)),
                                                   description="(view width in, ORU distance in) pairs (Fig. 10)")
    view_angle_deg: float = Field(90.0, gt=0, le=120, description="inter-camera angle of the Fig. 10 runs")
    ellipse_distance_in: float = Field(10.0, gt=0, le=100, description="where Fig. 11's ellipses are computed")
    standoff_in: float = Field(1.0, ge=0, le=20, description="where the operator aligns the ORU by hand (reference)")
    final_min_angle_deg: float = Field(28.0, ge=0, le=120, description="angles counted in stats.approach.final")


class VrExperiments:
    name: ClassVar[str] = "vr-experiments"
    truth: ClassVar[str | None] = "cellctl.truth.vr:vr_truth"
    Params: ClassVar[type[VrExperimentsParams]] = VrExperimentsParams
    sample_columns: ClassVar[tuple[str, ...]] = SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = ("kind", "condition", "run", "stop", "distance_in", "angle_deg", "view_in",
                                              "method", *ERROR_COLUMNS, *SIGMA_COLUMNS, "pos_err_in", "ori_err_deg",
                                              "status")

    def inputs(self, params, devices: Devices) -> list[str]:
        return []

    def output(self, params, devices: Devices) -> str | None:
        return None

    def plan(self, params: VrExperimentsParams, devices: Devices) -> list[Step]:
        operator_of(devices, self.name)
        todo: list[tuple[str, dict]] = [("reference", {})]
        todo += [("fig7", {"run": r, "distance_in": params.fig7_distance_in}) for r in range(params.fig7_runs)]
        for angle in params.angles_deg:
            todo.append(("mount", {"camera": "top", "angle": angle}))
            for r in range(params.n_runs):
                todo += [("approach", {"condition": f"angle {angle:g}", "angle": angle, "run": r, "stop": k,
                                       "distance_in": d}) for k, d in enumerate(params.distances_in)]
        todo.append(("mount", {"camera": "top", "angle": None}))
        models = load_models(params)
        back = float(models["receptacle"].vertices[:, 1].min() / INCH)
        depth = float(models["oru"].vertices[:, 1].max() / INCH)
        for width, d in params.views:
            look = [params.look_at_in[0], (back + d + depth) / 2, params.look_at_in[2]]  # between the two objects
            todo += [("mount", {"camera": c, "angle": params.view_angle_deg if c == "top" else None, "view": width,
                                "look_at": look}) for c in ("side", "top")]
            todo += [("view", {"condition": f"view {width:g}", "view": width, "angle": params.view_angle_deg, "run": r,
                               "distance_in": d, "look_at": look}) for r in range(params.n_runs)]
        todo += [("mount", {"camera": c, "angle": None, "view": None}) for c in ("side", "top")]
        todo.append(("ellipse", {"distance_in": params.ellipse_distance_in}))
        return [Step(i, kind, args) for i, (kind, args) in enumerate(todo)]

    # ------------------------------------------------------------------ steps
    def execute(self, step: Step, params: VrExperimentsParams, devices: Devices, history=()) -> StepResult:
        a, kind = step.args, step.action
        history = list(history)
        base = {"step": step.index, "kind": kind, "condition": a.get("condition"), "run": a.get("run"),
                "stop": a.get("stop"), "distance_in": a.get("distance_in"), "angle_deg": a.get("angle"),
                "view_in": a.get("view")}
        op = operator_of(devices, self.name)
        if kind == "reference":
            op.align_by_hand(devices.arm, params.standoff_in * INCH)
            return StepResult(dict(base, status="ok", **pose_cells("arm", matrix_of(devices.arm.pose()))))
        if kind == "mount":
            device = getattr(params, a["camera"]).device
            op.mount_camera(device, a.get("angle"), a.get("view"), a.get("look_at"))
            return StepResult(dict(base, status="ok", message=f"{device} mounted: angle {a.get('angle')}, view {a.get('view')}"))
        aligned = _aligned_pose(history)
        reference = _reference(aligned, params.standoff_in)
        setup = {"angle": a.get("angle"), "view": a.get("view"), "look_at": a.get("look_at")}
        for camera in ("side", "top"):  # as the plan says (a no-op unless the run was resumed elsewhere)
            op.mount_camera(getattr(params, camera).device, setup["angle"] if camera == "top" else None, setup["view"],
                            setup["look_at"])
        if kind == "approach":
            previous = None
            if a["stop"] > 0:
                previous = previous_estimate(history, condition=a["condition"], run=a["run"], stop=a["stop"] - 1)
                if previous is None:
                    return StepResult(dict(base, method="simultaneous", status="failed",
                                           message="the previous stop of this run has no estimate"))
            else:
                self._move(devices, aligned, a["distance_in"], params.standoff_in)
            rows, frames, _, _ = approach_stop(params, devices, previous, a["distance_in"], setup, reference)
            return StepResult([dict(base, **r) for r in rows], frames if a["run"] == 0 else [])
        self._move(devices, aligned, a["distance_in"], params.standoff_in)
        models, frames, est, coarse = coarse_at_stop(params, devices, setup)
        methods = METHODS if kind == "fig7" else ("simultaneous",)
        out = fine_methods(params, frames, est, models, methods)
        ref = reference(matrix_of(devices.arm.pose()))
        ids = frame_ids(frames)
        r = coarse["simultaneous"]
        rows = [dict(base, **result_row("point-simultaneous", Estimate(r.cameras, est.oru, r.objects[1].M), r, ref),
                     **ids, status="ok")]
        images = []
        for method, res in out.items():
            if isinstance(res, Exception):
                rows.append(dict(base, method=method, status="failed", message=str(res), **ids))
                continue
            e, result = res
            row = dict(base, **result_row(method, e, result, ref), **ids, status="ok")
            if kind == "ellipse":
                row.update(covariance_cells(result))
            rows.append(row)
            if a.get("run", 0) == 0 and kind in ("fig7", "ellipse"):
                title = f"{method} ({FIGURE_OF[method]})" if kind == "fig7" else f"{method}, {a['distance_in']:g} in"
                images.append(overlay_frame(frames, e, models, title, f"{kind}-{method}"))
        return StepResult(rows, [*frames, *images] if images else [])

    @staticmethod
    def _move(devices: Devices, aligned: np.ndarray, distance_in: float, standoff_in: float) -> None:
        devices.arm.move_linear(pose_of(aligned @ translate((distance_in - standoff_in) * INCH)))

    # ------------------------------------------------------------------ fit
    def fit(self, samples: list[dict], params: VrExperimentsParams, resolutions=None) -> FitOutcome:
        stats, tables, charts = aggregate(samples, params)
        rejected = [{"step": r.get("step"), "reason": f"{r.get('method')}: {r.get('message')}"}
                    for r in samples if r.get("status") == "failed"]
        return FitOutcome(summary_model(samples, "simultaneous"), stats, rejected, {}, tables, charts)


def _aligned_pose(history: list[dict]) -> np.ndarray:
    rows = [r for r in history if r.get("kind") == "reference" and pose_from(r, "arm") is not None]
    if not rows:
        raise RuntimeError("the reference alignment step has not run")
    return pose_from(rows[-1], "arm")


def _reference(aligned: np.ndarray, standoff_in: float):
    """Reference ORU-in-receptacle pose at a stop, from the hand-aligned arm pose and the stop's arm pose."""
    aligned_in_rec = translate(standoff_in * INCH)
    return lambda stop_pose: aligned_in_rec @ inverse(aligned) @ stop_pose


# ------------------------------------------------------------------ statistics, tables, charts

def _rms(values) -> float | None:
    v = np.asarray([x for x in values if x is not None], float)
    return float(np.sqrt(np.mean(v**2))) if v.size else None


def _ok(rows, **match):
    return [r for r in rows if r.get("status") == "ok" and error_vector(r) is not None
            and all(r.get(k) == v for k, v in match.items())]


def _spread(rows, part: slice, unit: float) -> float | None:
    """Standard deviation over runs of the alignment error vector (the seed's Fig. 7 measure, its precision):
    the root of the summed per-component variances, in `unit`."""
    if len(rows) < 2:  # no spread from one run, or none (every run of the method failed)
        return None
    e = np.array([error_vector(r)[part] for r in rows], float)
    return float(np.sqrt(np.sum(np.var(e, axis=0, ddof=1))) / unit)


def _summary(rows) -> dict:
    """`position_in`, `orientation_deg`: standard deviation over runs (precision); `rms_*`: RMS of the error
    magnitude from the reference (accuracy, bias included)."""
    return {"position_in": _spread(rows, slice(0, 3), INCH), "orientation_deg": _spread(rows, slice(3, 6), math.pi / 180),
            "rms_position_in": _rms(r["pos_err_in"] for r in rows), "rms_orientation_deg": _rms(r["ori_err_deg"] for r in rows),
            "predicted_position_in": _rms(r["sigma_pos_in"] for r in rows),
            "predicted_orientation_deg": _rms(r["sigma_ori_deg"] for r in rows), "n": len(rows)}


def aggregate(samples: list[dict], params: VrExperimentsParams) -> tuple[dict, list, list]:
    """Stats, report tables and charts from rows whose `error` (ORU-in-receptacle alignment error, m and rad,
    receptacle frame) is against a reference; the truth section calls it with errors against the truth."""
    stats: dict = {}
    tables: list = []
    charts: list = []
    fig7 = [r for r in samples if r.get("kind") == "fig7"]
    stats["alignment"] = {}
    for m in (*METHODS, "point-simultaneous"):
        s = _summary(_ok(fig7, method=m))
        s["n_failed"] = sum(1 for r in fig7 if r.get("method") == m and r.get("status") == "failed")
        stats["alignment"][m] = s
    al = stats["alignment"]
    if al["simultaneous"]["position_in"] and al["objloc12"]["position_in"]:
        stats["alignment"]["gain_over_objloc12"] = {
            "position": al["objloc12"]["position_in"] / al["simultaneous"]["position_in"],
            "orientation": al["objloc12"]["orientation_deg"] / al["simultaneous"]["orientation_deg"]}
    tables.append({"title": f"Fig. 7: alignment error at {params.fig7_distance_in:g} in: standard deviation over runs, "
                            "and RMS from the reference alignment",
                   "columns": ["method", "SD pos (in)", "SD ori (deg)", "RMS pos (in)", "RMS ori (deg)",
                               "pred. 1σ (in)", "runs", "failed", "seed pos (in)", "seed ori (deg)"],
                   "rows": [[m, al[m]["position_in"], al[m]["orientation_deg"], al[m]["rms_position_in"],
                             al[m]["rms_orientation_deg"], al[m]["predicted_position_in"], al[m]["n"],
                             al[m]["n_failed"], *SEED_FIG7.get(m, ("-", "-"))] for m in (*METHODS, "point-simultaneous")],
                   "note": "pos: position, ori: orientation (vector sums over the three axes); SD: standard "
                           "deviation over runs (precision); RMS: of the error from the reference (accuracy); pred. "
                           "1σ: the predicted position 1σ, RMS over runs. "
                           "Seed: simultaneous 2.5x more precise in position than OBJLOC12, 1.4x in orientation. "
                           "Point-simultaneous: the coarse matching all methods start from. The predicted 1σ "
                           "includes the systematic term of eqs. 10-11, which is the same in every run of one "
                           "cell: compare it with the RMS (stats.covariance_consistency does, per component)."})
    charts.append({"name": "fig7_alignment", "title": "Fig. 7: position alignment error per run", "x_label": "run",
                   "y_label": "position error (in)", "series": {
                       m: [[r["run"], r["pos_err_in"]] for r in _ok(fig7, method=m)] for m in METHODS}})

    # Figs. 8 and 9: the approaches
    appr = [r for r in samples if r.get("kind") == "approach"]
    by = {}
    for angle in params.angles_deg:
        for k, d in enumerate(params.distances_in):
            by[(angle, d)] = _summary(_ok(appr, angle_deg=angle, stop=k))
    stats["approach"] = {"by_angle": {f"{a:g}": {f"{d:g}": by[(a, d)] for d in params.distances_in}
                                      for a in params.angles_deg}}
    last = len(params.distances_in) - 1
    finals = [r for r in _ok(appr, stop=last) if r["angle_deg"] >= params.final_min_angle_deg]
    runs = {(r["angle_deg"], r["run"]) for r in appr}
    counted = {k for k in runs if k[0] >= params.final_min_angle_deg}
    stats["approach"]["final"] = {
        "distance_in": params.distances_in[-1], "min_angle_deg": params.final_min_angle_deg,
        "position_in": max((r["pos_err_in"] for r in finals), default=None),
        "orientation_deg": max((r["ori_err_deg"] for r in finals), default=None),
        "runs": len(counted), "runs_reached": len(finals),
        "within_requirement": bool(finals) and len(finals) == len(counted) and all(
            r["pos_err_in"] <= REQUIREMENT[0] and r["ori_err_deg"] <= REQUIREMENT[1] for r in finals)}
    stats["approach"]["final_by_angle"] = {
        f"{a:g}": {"position_in": max((r["pos_err_in"] for r in _ok(appr, angle_deg=a, stop=last)), default=None),
                   "orientation_deg": max((r["ori_err_deg"] for r in _ok(appr, angle_deg=a, stop=last)), default=None)}
        for a in params.angles_deg}
    cols = ["distance (in)"] + [f"{a:g}° pos (in)" for a in params.angles_deg] + [f"{a:g}° ori (deg)" for a in params.angles_deg]
    tables.append({"title": "Figs. 8-9: alignment error (RMS over runs) by ORU distance and inter-camera angle",
                   "columns": cols, "rows": [[d] + [by[(a, d)]["rms_position_in"] for a in params.angles_deg]
                                             + [by[(a, d)]["rms_orientation_deg"] for a in params.angles_deg]
                                             for d in params.distances_in],
                   "note": "Seed: the error falls as the ORU nears the receptacle and as the angle grows toward 90°; "
                           "at 28°, 51° and 90° all runs were within ±1/4 in and ±3° at 2 in, not at 14°."})
    charts.append({"name": "fig8_distance", "title": "Fig. 8: position error against ORU distance", "x_label":
                   "ORU distance from receptacle (in)", "y_label": "position error, RMS (in)", "log_y": True,
                   "series": {f"{a:g}°": [[d, by[(a, d)]["rms_position_in"]] for d in params.distances_in
                                          if by[(a, d)]["rms_position_in"]] for a in params.angles_deg}})
    charts.append({"name": "fig9_angle", "title": "Fig. 9: position error against inter-camera angle", "x_label":
                   "inter-camera angle (deg)", "y_label": "position error, RMS (in)", "log_y": True,
                   "series": {f"{d:g} in": [[a, by[(a, d)]["rms_position_in"]] for a in params.angles_deg
                                            if by[(a, d)]["rms_position_in"]] for d in params.distances_in}})

    # Fig. 10: view size
    view = [r for r in samples if r.get("kind") == "view"]
    vs = {w: _summary(_ok(view, view_in=w, method="simultaneous")) for w, _ in params.views}
    stats["view_size"] = {f"{w:g}": dict(vs[w], distance_in=d) for w, d in params.views}
    tables.append({"title": f"Fig. 10: alignment error by view width ({params.view_angle_deg:g}° between the cameras)",
                   "columns": ["view width (in)", "ORU distance (in)", "position (in)", "orientation (deg)", "runs"],
                   "rows": [[w, d, vs[w]["rms_position_in"], vs[w]["rms_orientation_deg"], vs[w]["n"]] for w, d in params.views],
                   "note": "Seed: the error grows as the objects' image gets smaller (wider views)."})
    charts.append({"name": "fig10_view", "title": "Fig. 10: position error against view width", "x_label":
                   "view width (in)", "y_label": "position error, RMS (in)",
                   "series": {"simultaneous": [[w, vs[w]["rms_position_in"]] for w, _ in params.views if vs[w]["rms_position_in"]]}})

    # Fig. 11: ellipses
    ell = [r for r in samples if r.get("kind") == "ellipse" and r.get("method") == "simultaneous"
           and "rec" in position_covariances(r)]
    if ell:
        blocks = position_covariances(ell[-1])  # each block's tx, ty, tz
        rows, series = [], {}
        for block, label in (("side", "side camera"), ("top", "overhead camera"), ("rec", "receptacle")):
            if block not in blocks:
                continue
            for i, j in ((0, 1), (0, 2), (1, 2)):
                pair = f"t{'xyz'[i]}-t{'xyz'[j]}"
                s = ellipse_summary(blocks[block], i, j)
                rows.append([label, pair, s["sigma_i"] / INCH, s["sigma_j"] / INCH, s["rho"]])
                if block == "rec":
                    series[pair] = (error_ellipse(blocks[block], i, j) / INCH).tolist()
        stats["ellipses"] = {"distance_in": params.ellipse_distance_in, "receptacle_sigma_in": [
            float(np.sqrt(blocks["rec"][i, i]) / INCH) for i in range(3)]}
        tables.append({"title": f"Fig. 11: 1σ of the simultaneous update at {params.ellipse_distance_in:g} in (camera poses "
                                "in their own frames, receptacle in its frame)",
                       "columns": ["block", "pair", "σ first (in)", "σ second (in)", "ρ"], "rows": rows,
                       "note": "Seed: the cameras' σ along their optical axes (tz) are very large (correlated with the "
                               "focal length); the receptacle's within 0.14 in on every axis."})
        charts.append({"name": "fig11_receptacle", "title": "Fig. 11: 1σ ellipses of the receptacle position",
                       "x_label": "first axis (in)", "y_label": "second axis (in)", "series": series})

    # covariance consistency: spread of the simultaneous updates' errors over their predicted 1-sigma
    z = []
    for r in samples:
        e, s = error_vector(r), sigma_vector(r)
        if r.get("status") == "ok" and r.get("method") == "simultaneous" and e is not None and s is not None:
            z.append(e / np.maximum(s, 1e-12))
    if z:
        z = np.asarray(z)
        stats["covariance_consistency"] = {
            "ratio": float(np.sqrt(np.mean(z**2))), "position": float(np.sqrt(np.mean(z[:, :3] ** 2))),
            "orientation": float(np.sqrt(np.mean(z[:, 3:] ** 2))), "n": len(z),
            "note": "RMS of (alignment error / predicted 1-sigma) per component over every simultaneous update; "
                    "1 = agreement"}
    return stats, tables, charts


def rows_with_errors(samples: list[dict], error_of) -> list[dict]:
    """Copies of the rows with the error columns recomputed by `error_of(row, alignment) -> 6-vector | None`
    (`alignment`: the row's estimated ORU-in-receptacle pose)."""
    out = []
    for r in samples:
        r = dict(r)
        e = error_of(r, estimate_from(r).alignment()) if r.get("status") == "ok" and has_estimate(r) else None
        if e is not None:
            r.update(error_cells(e))
        out.append(r)
    return out


__all__ = ["Estimate", "VrExperiments", "aggregate", "load_models", "rows_with_errors"]
