"""vr-fine: automated fine matching, the line-based simultaneous update (seed 000 sections III-V).

Starts from the active `vr` calibration (vr-coarse's or a previous vr-fine's:
cameras and receptacle in the robot frame), with the ORU where the arm now
reports it. Without a stored calibration it runs the coarse matching first, in
the same step. Lines are detected next to the projected models, the 20 variables
solved, and detection repeated from the new estimate (`rounds`).
"""

from __future__ import annotations

from typing import ClassVar

from ..errors import CalibrationInputError
from .base import Devices, FitOutcome, Step, StepResult
from .vr_coarse import coarse_at_stop, row_stats, summary_model
from .vr_common import (
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
    result_row,
)


class VrFineParams(VrParams):
    pass


class VrFine:
    name: ClassVar[str] = "vr-fine"
    Params: ClassVar[type[VrFineParams]] = VrFineParams
    sample_columns: ClassVar[tuple[str, ...]] = SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = ("method", "estimate", "alignment", "rms_px")

    def inputs(self, params, devices: Devices) -> list[str]:
        return ["vr"]

    def output(self, params, devices: Devices) -> str | None:
        return "vr"

    def plan(self, params, devices: Devices) -> list[Step]:
        if "vr" not in devices.calibrations:
            operator_of(devices, f"{self.name} without a stored vr calibration (coarse matching first)")
        return [Step(0, "fine", {})]

    def execute(self, step: Step, params, devices: Devices, history=()) -> StepResult:
        stored = devices.calibrations.get("vr")
        models = load_models(params)
        if stored and stored.get("model", stored).get("estimate"):
            import json

            est = Estimate.from_json(json.dumps(stored.get("model", stored)["estimate"]))
            est = est.with_oru(matrix_of(devices.arm.pose()))
            frames = capture_both(params, devices)
        else:
            models, frames, est, _ = coarse_at_stop(params, devices)
        try:
            est, result = line_update(params, frames, est, models, (True, True), True)
        except MatchFailed as exc:
            raise CalibrationInputError(f"{self.name}: {exc}; run vr-coarse again") from None
        row = dict(result_row("simultaneous", est, result, None), step=step.index, kind="fine",
                   side_frame=frames[0].frame_id, top_frame=frames[1].frame_id, status="ok")
        view = overlay_frame(overlay(frames, est, models, "line-based simultaneous"), "fine", frames[1].host_timestamp_s)
        return StepResult([row], [*frames, view])

    def fit(self, samples: list[dict], params, resolutions=None) -> FitOutcome:
        stats = {r["method"]: row_stats(r) for r in samples if r.get("method")}
        return FitOutcome(summary_model(samples, "simultaneous"), stats)
