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

import json
from typing import ClassVar

import numpy as np
from pydantic import Field

from .base import Devices, FitOutcome, Step, StepResult
from .vr_coarse import coarse_at_stop, row_stats, summary_model
from .vr_common import (
    INCH,
    SAMPLE_COLUMNS,
    Estimate,
    MatchFailed,
    VrParams,
    capture_both,
    line_update,
    load_models,
    matrix_of,
    operator_of,
    overlay,
    overlay_frame,
    pose_of,
    result_row,
    translate,
)


class VrApproachParams(VrParams):
    via_in: tuple[float, ...] = Field((8.0, 4.0, 2.0), description="stops: ORU front to receptacle entrance, in")


def approach_stop(params: VrParams, devices: Devices, previous: Estimate | None, distance_in: float | None,
                  setup: dict | None = None, reference=None):
    """One stop of the approach: (rows, frames, estimate). `previous` None: coarse matching here first (stop 0);
    else move to `distance_in` in front of the receptacle as `previous` places it and update from it."""
    models = load_models(params)
    if previous is None:
        models, frames, est, _ = coarse_at_stop(params, devices, setup)
    else:
        target = previous.receptacle @ translate(distance_in * INCH)  # the ORU (= tool frame) there
        devices.arm.move_linear(pose_of(target))
        est = previous.with_oru(matrix_of(devices.arm.pose()))
        frames = capture_both(params, devices)
    try:
        est, result = line_update(params, frames, est, models, (True, True), True)
    except MatchFailed as exc:
        return [{"method": "simultaneous", "status": "failed", "message": str(exc), "estimate": est.to_json(),
                 "side_frame": frames[0].frame_id, "top_frame": frames[1].frame_id}], frames, None
    ref = reference(matrix_of(devices.arm.pose())) if reference else None
    row = dict(result_row("simultaneous", est, result, ref), side_frame=frames[0].frame_id,
               top_frame=frames[1].frame_id, status="ok", arm_pose=json.dumps(matrix_of(devices.arm.pose()).tolist()))
    return [row], frames, est


def previous_estimate(history: list[dict], **match) -> Estimate | None:
    rows = [r for r in history if r.get("status") == "ok" and r.get("method") == "simultaneous"
            and all(r.get(k) == v for k, v in match.items())]
    return Estimate.from_json(rows[-1]["estimate"]) if rows else None


class VrApproach:
    name: ClassVar[str] = "vr-approach"
    Params: ClassVar[type[VrApproachParams]] = VrApproachParams
    sample_columns: ClassVar[tuple[str, ...]] = SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = ("stop", "distance_in", "method", "estimate", "alignment", "sigma")

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
            rows, frames, est = approach_stop(params, devices, previous, a["distance_in"])
            if est is not None:
                d = "start" if a["distance_in"] is None else f"{a['distance_in']:g} in"
                frames = [*frames, overlay_frame(overlay(frames, est, load_models(params), f"stop {a['stop']} ({d})"),
                                                 f"stop{a['stop']}", frames[1].host_timestamp_s)]
        for r in rows:
            r.update(step=step.index, kind="approach", stop=a["stop"], distance_in=a["distance_in"])
        return StepResult(rows, frames)

    def fit(self, samples: list[dict], params, resolutions=None) -> FitOutcome:
        stops = []
        for r in samples:
            if r.get("status") != "ok":
                continue
            R = np.asarray(json.loads(r["alignment"]))
            stops.append(dict(row_stats(r), stop=r["stop"], distance_in=r.get("distance_in"),
                              oru_in_receptacle_in=(R[:3, 3] / INCH).tolist()))
        failed = [{"step": r.get("step"), "reason": r.get("message")} for r in samples if r.get("status") != "ok"]
        stats = {"approach": {"stops": stops, "final": stops[-1] if stops else None}}
        return FitOutcome(summary_model(samples, "simultaneous"), stats, failed)
