"""vr-fine: automated fine matching, the line-based simultaneous update (seed 000 sections III-V).

Starts from the active `vr` calibration (vr-coarse's or a previous vr-fine's:
cameras and receptacle in the robot frame), with the ORU where the arm now
reports it. Without a stored calibration it runs the coarse matching first, in
the same step. Lines are detected next to the projected models, the 20 variables
solved, and detection repeated from the new estimate (`rounds`).
"""

from __future__ import annotations

from typing import ClassVar

from calibration.errors import CalibrationInputError
from calibration.routines.base import Devices, Step, StepResult
from calibration.routines.vr._common import Estimate, MatchFailed, VrParams, line_update, operator_of, overlay_frame
from calibration.routines.vr._samples import frame_ids, result_row
from calibration.routines.vr.vr_coarse import SceneRoutine, start_at_stop


class VrFineParams(VrParams):
    pass


class VrFine(SceneRoutine):
    name: ClassVar[str] = "vr-fine"
    truth: ClassVar[str | None] = "cellctl.truth.vr:vr_truth"
    Params: ClassVar[type[VrFineParams]] = VrFineParams
    model_method: ClassVar[str] = "simultaneous"

    def inputs(self, params, devices: Devices) -> list[str]:
        return ["vr"]

    def plan(self, params, devices: Devices) -> list[Step]:
        if "vr" not in devices.calibrations:
            operator_of(devices, f"{self.name} without a stored vr calibration (coarse matching first)")
        return [Step(0, "fine", {})]

    def execute(self, step: Step, params, devices: Devices, history=()) -> StepResult:
        stored = devices.calibrations.get("vr") or {}
        model = stored.get("model", stored)
        start = Estimate.from_dict(model["estimate"]) if model.get("estimate") else None
        models, frames, est = start_at_stop(params, devices, start)
        try:
            est, result = line_update(params, frames, est, models, (True, True), True)
        except MatchFailed as exc:
            raise CalibrationInputError(f"{self.name}: {exc}; run vr-coarse again") from None
        row = dict(result_row("simultaneous", est, result, None), step=step.index, kind="fine", **frame_ids(frames),
                   status="ok")
        return StepResult([row], [*frames, overlay_frame(frames, est, models, "line-based simultaneous", "fine")])
