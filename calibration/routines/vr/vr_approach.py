"""vr-approach: the operational procedure of seed 000 section VI.

Stop 0: coarse matching from the operator's clicks, then the line-based
simultaneous update (steps 1-6). Then the arm moves the ORU to via points
`via_in` in front of the receptacle as the current estimate places it, and at
each stop the line-based simultaneous update runs again from the previous
estimate, with no operator input (steps 7-9), ending aligned for insertion at the
last via point. Each stop records the receptacle's pose relative to the ORU, its
predicted 1-sigma and an overlay image.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from geometry.transforms import matrix_of

from calibration.routines.base import Devices, FitOutcome, Step, StepResult, Table
from calibration.routines.vr._common import (
    INCH,
    Estimate,
    MatchFailed,
    VrParams,
    line_update,
    operator_of,
    overlay_frame,
    pose_of,
    translate,
)
from calibration.routines.vr._samples import (
    ESTIMATE_FIT_COLUMNS,
    SAMPLE_COLUMNS,
    SIGMA_COLUMNS,
    estimate_cells,
    estimate_from,
    frame_ids,
    pose_cells,
    result_row,
)
from calibration.routines.vr.vr_coarse import SIGMA_TEXT, row_stats, scene_table, start_at_stop, summary_model


class VrApproachParams(VrParams):
    via_in: tuple[float, ...] = Field((8.0, 4.0, 2.0), description="stops: ORU front to receptacle entrance, in")


def approach_stop(params: VrParams, devices: Devices, previous: Estimate | None, distance_in: float | None,
                  setup: dict | None = None, reference=None):
    """One stop of the approach: (rows, frames, models, estimate). `previous` None: coarse matching here first (stop 0);
    else move to `distance_in` in front of the receptacle as `previous` places it and update from it."""
    if previous is not None:
        target = previous.receptacle @ translate(distance_in * INCH)  # the ORU (= tool frame) there
        devices.arm.move_linear(pose_of(target))
    models, frames, est = start_at_stop(params, devices, previous, setup)
    try:
        est, result = line_update(params, frames, est, models, (True, True), True)
    except MatchFailed as exc:
        return [{"method": "simultaneous", "status": "failed", "message": str(exc), **estimate_cells(est),
                 **frame_ids(frames)}], frames, models, None
    ref = reference(matrix_of(devices.arm.pose())) if reference else None
    row = dict(result_row("simultaneous", est, result, ref), **frame_ids(frames), status="ok",
               **pose_cells("arm", matrix_of(devices.arm.pose())))
    return [row], frames, models, est


def previous_estimate(history: list[dict], **match) -> Estimate | None:
    rows = [r for r in history if r.get("status") == "ok" and r.get("method") == "simultaneous"
            and all(r.get(k) == v for k, v in match.items())]
    return estimate_from(rows[-1]) if rows else None


class VrApproach:
    name: ClassVar[str] = "vr-approach"
    truth: ClassVar[str | None] = "cellctl.truth.vr:vr_truth"
    Params: ClassVar[type[VrApproachParams]] = VrApproachParams
    sample_columns: ClassVar[tuple[str, ...]] = SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = ("stop", "distance_in", "method", *ESTIMATE_FIT_COLUMNS, *SIGMA_COLUMNS)

    def inputs(self, params, devices: Devices) -> list[str]:
        return []

    def output(self, params, devices: Devices) -> str | None:
        return "vr"

    def plan(self, params: VrApproachParams, devices: Devices) -> list[Step]:
        operator_of(devices, self.name)
        return [Step(0, "start", {"stop": 0, "distance_in": None})] + [
            Step(k, "via", {"stop": k, "distance_in": float(d)}) for k, d in enumerate(params.via_in, start=1)]

    def execute(self, step: Step, params: VrApproachParams, devices: Devices, history=()) -> StepResult:
        a = step.args
        previous = previous_estimate(list(history)) if a["stop"] else None
        if a["stop"] and previous is None:
            rows, frames = [{"method": "simultaneous", "status": "failed", "message": "no estimate from earlier stops"}], []
        else:
            rows, frames, models, est = approach_stop(params, devices, previous, a["distance_in"])
            if est is not None:
                d = "start" if a["distance_in"] is None else f"{a['distance_in']:g} in"
                frames = [*frames, overlay_frame(frames, est, models, f"stop {a['stop']} ({d})", f"stop{a['stop']}")]
        for r in rows:
            r.update(step=step.index, kind="approach", stop=a["stop"], distance_in=a["distance_in"])
        return StepResult(rows, frames)

    def fit(self, samples: list[dict], params, resolutions=None) -> FitOutcome:
        stops = []
        for r in samples:
            if r.get("status") != "ok":
                continue
            R = estimate_from(r).alignment()
            stops.append(dict(row_stats(r), stop=r["stop"], distance_in=r.get("distance_in"),
                              oru_in_receptacle_in=(R[:3, 3] / INCH).tolist()))
        failed = [{"step": r.get("step"), "reason": r.get("message")} for r in samples if r.get("status") != "ok"]
        stats = {"approach": {"stops": stops, "final": stops[-1] if stops else None}}
        model = summary_model(samples, "simultaneous")
        tables = [stops_table(stops)]
        if "estimate" in model:
            tables.append(scene_table(Estimate.from_dict(model["estimate"])))
        return FitOutcome(model, stats, failed, tables=tables)


def stops_table(stops: list[dict]) -> Table:
    """The approach stop by stop: where the ORU stood against the receptacle, the fit's residuals, the predicted
    accuracy."""
    rows = []
    for s in stops:
        distance = "start" if s.get("distance_in") is None else s["distance_in"]
        rows.append([s["stop"], distance, s.get("n_lines"), round(s["rms_px"], 3), s.get("iterations"),
                     *(round(v, 3) for v in s["oru_in_receptacle_in"]), round(s["sigma_pos_in"], 3),
                     round(s["sigma_ori_deg"], 2)])
    return {"title": "Approach: the ORU in the receptacle frame at each stop (line-based simultaneous update)",
            "columns": ["stop", "via (in)", "lines", "RMS (px)", "iterations", "x (in)", "y (in)", "z (in)",
                        "σ position (in)", "σ rotation (deg)"],
            "rows": rows,
            "note": "via: the stop's distance from the receptacle entrance as the previous estimate placed it "
                    "(start: where the arm stood for the coarse matching). RMS: the image residual of the fit. "
                    f"{SIGMA_TEXT}"}
