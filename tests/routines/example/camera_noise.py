"""camera-noise: how still a still nozzle looks, an example of a routine added as one file.

The nozzle stands at an area's centre while its camera takes `frames` pictures; the fit is the scatter of the
nozzle's centroid in pixels. The test copies this file into a family's folder (test_routine_registry.py) and runs
it through the CLI: nothing else names it.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError
from calibration.routines.base import Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.steps import visit_and_measure


class CameraNoiseParams(Params):
    area: str = Field("area1", description="the area whose camera watches the nozzle, at its centre")
    frames: int = Field(8, ge=2, le=1000, description="pictures taken of the still nozzle")


class CameraNoise:
    name: ClassVar[str] = "camera-noise"
    truth: ClassVar[str | None] = None  # nothing hidden to judge it against: the scatter is the camera's own
    Params: ClassVar[type[CameraNoiseParams]] = CameraNoiseParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "status", "camera", "frame_id", "cmd_x_mm", "cmd_y_mm", "z_mm", "x_mm", "y_mm", "alpha_abs_deg",
        "u_px", "v_px", "diameter_px", "snr", "message")
    fit_columns: ClassVar[tuple[str, ...]] = ("u_px", "v_px")

    def inputs(self, params: CameraNoiseParams, devices: Devices) -> list[str]:
        return []

    def output(self, params: CameraNoiseParams, devices: Devices) -> str | None:
        return None  # a measurement, not a calibration

    def plan(self, params: CameraNoiseParams, devices: Devices) -> list[Step]:
        area = devices.area(params.area)
        at = {"x": area.centre[0], "y": area.centre[1], "z": area.z, "alpha": area.alpha_cal, "camera": area.camera}
        return [Step(i, "look", at) for i in range(params.frames)]

    def execute(self, step: Step, params: CameraNoiseParams, devices: Devices, history=()) -> StepResult:
        a = step.args
        row, frame = visit_and_measure(devices, Pose(a["x"], a["y"], a["z"], a["alpha"]), a["camera"])
        return StepResult(dict(row, step=step.index), [frame])

    def fit(self, samples: list[dict], params: CameraNoiseParams, resolutions=None) -> FitOutcome:
        uv = np.array([[float(r["u_px"]), float(r["v_px"])] for r in samples if r.get("status", "ok") == "ok"])
        if len(uv) < 2:
            raise CalibrationInputError(f"camera-noise: {len(uv)} frame(s) with the nozzle seen; the scatter needs 2")
        sd = uv.std(axis=0, ddof=1)
        stats = {"noise": {"n": len(uv), "sd_u_px": float(sd[0]), "sd_v_px": float(sd[1])}}
        table = {"title": "The still nozzle's centroid scatter", "columns": ["frames", "SD u (px)", "SD v (px)"],
                 "rows": [[len(uv), round(float(sd[0]), 4), round(float(sd[1]), 4)]]}
        rejected = [{"step": r.get("step"), "reason": r.get("message") or r.get("status")}
                    for r in samples if r.get("status", "ok") != "ok"]
        return FitOutcome({"kind": "camera-noise"}, stats, rejected, tables=[table])
