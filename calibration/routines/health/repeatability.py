"""Pose repeatability of the robot as a calibrated camera sees it (ISO 9283 section 7.2.2, in the area's plane).

Seed 001's error budget rests on it (section 4: the robot's x-y repeatability is +/- 5 µm). The nozzle
visits P1 (the area's centre) and P2..P5 (near its corners, 10 % of the diagonal in, as ISO 9283 puts
them on its test plane) in cycles P1 -> P5, each position always approached from the same side, the
positions from different sides. The area's camera measures the nozzle at every visit through its active
calibration. Per position, with l_j the distance of cycle j's attained position from their barycentre:

    RP = l_mean + 3 S_l        (S_l the sample standard deviation of the l_j)

(calibration/models/iso9283.py's pose_repeatability, as the six-axis iso9283 routine's), and the drift, the
distance between the mean attained positions of the first and the last cycles.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError
from calibration.models.iso9283 import pose_repeatability
from calibration.routines.base import Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.steps import visit_and_measure
from calibration.usage import CellCalibration

COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")
SEED_RP_UM = 5.0  # seed 001 section 4: the robot's x-y repeatability, +/- 5 µm


class RepeatabilityParams(Params):
    area: str = Field("area1", description="area whose calibrated camera watches the nozzle")
    positions: int = Field(5, ge=1, le=5, description="P1 (the centre), then P2..P5 near the corners")
    cycles: int = Field(30, ge=2, le=1000, description="visits of each position (ISO 9283: 30)")
    inset: float = Field(0.1, ge=0.0, le=0.45, description="P2..P5 this fraction of the diagonal in from the "
                                                            "corners (ISO 9283: 0.1)")
    approach_mm: float = Field(1.0, ge=0.0, le=20, description="each visit starts this far out, on the "
                                                               "position's own side")
    drift_cycles: int = Field(3, ge=1, le=100, description="cycles averaged at each end for the drift")
    polarity: Literal["bright", "dark"] = Field("bright", description="the nozzle in the image: bright on dark, or dark on bright")

    @model_validator(mode="after")
    def _enough_cycles(self):
        if 2 * self.drift_cycles > self.cycles:
            raise ValueError(f"drift_cycles={self.drift_cycles} needs at least {2 * self.drift_cycles} cycles "
                             f"(got {self.cycles})")
        return self


class Repeatability:
    name: ClassVar[str] = "repeatability"
    truth: ClassVar[str | None] = "cellctl.truth.micro:repeatability_truth"
    Params: ClassVar[type[RepeatabilityParams]] = RepeatabilityParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "position", "cycle", "status", "camera", "frame_id", "cmd_x_mm", "cmd_y_mm", "z_mm",
        "alpha_abs_deg", "x_mm", "y_mm", "u_px", "v_px", "diameter_px", "snr", "meas_x_mm", "meas_y_mm", "message",
    )
    fit_columns: ClassVar[tuple[str, ...]] = ("position", "cycle", "meas_x_mm", "meas_y_mm")
    small_params: ClassVar[dict] = {"positions": 2, "cycles": 2, "drift_cycles": 1}

    def inputs(self, params: RepeatabilityParams, devices: Devices) -> list[str]:
        return [devices.area(params.area).camera]

    def output(self, params: RepeatabilityParams, devices: Devices) -> str | None:
        return None  # a measurement of the robot, not a calibration

    def plan(self, params: RepeatabilityParams, devices: Devices) -> list[Step]:
        area = devices.area(params.area)
        devices.calibration(area.camera, self.name)  # refused before anything moves
        centre = np.array(area.centre)
        half = np.array(area.size) / 2 * (1 - 2 * params.inset)
        corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        targets = [centre] + [centre + half * c for c in corners]
        sides = [np.array([1.0, 0.0])] + [np.array(c) / math.sqrt(2) for c in corners]  # where each comes from
        steps = []
        for cycle in range(1, params.cycles + 1):
            for k in range(params.positions):
                start = targets[k] + sides[k] * params.approach_mm * 1e-3
                steps.append({"position": f"P{k + 1}", "cycle": cycle, "x": float(targets[k][0]),
                              "y": float(targets[k][1]), "from_x": float(start[0]), "from_y": float(start[1]),
                              "z": area.z, "alpha": area.alpha_cal, "camera": area.camera})
        return [Step(i, "visit", args) for i, args in enumerate(steps)]

    def execute(self, step: Step, params: RepeatabilityParams, devices: Devices, history=()) -> StepResult:
        a = step.args
        devices.arm.move_linear(Pose(a["from_x"], a["from_y"], a["z"], a["alpha"]))
        row, frame = visit_and_measure(devices, Pose(a["x"], a["y"], a["z"], a["alpha"]), a["camera"], params.polarity)
        seen = CellCalibration(devices.calibrations).locate(a["camera"], [[row["u_px"], row["v_px"]]])[0] * 1e3
        row.update(step=step.index, position=a["position"], cycle=a["cycle"], meas_x_mm=seen[0], meas_y_mm=seen[1])
        return StepResult(row, [frame])  # NaN where the nozzle was not seen

    def fit(self, samples: list[dict], params: RepeatabilityParams, resolutions=None) -> FitOutcome:
        return fit_repeatability(samples, params.drift_cycles)


def fit_repeatability(samples: list[dict], drift_cycles: int = 3) -> FitOutcome:
    """RP and drift per position from the measured positions (meas_x_mm, meas_y_mm) of each cycle."""
    ok = [r for r in samples if r.get("status", "ok") == "ok"]
    labels = sorted({str(r["position"]) for r in ok})
    if not labels:
        raise CalibrationInputError("no visit with a measured nozzle: nothing to evaluate")
    positions, series = {}, []
    for i, label in enumerate(labels):
        rows = sorted((r for r in ok if str(r["position"]) == label), key=lambda r: int(r["cycle"]))
        xy = np.array([[float(r["meas_x_mm"]), float(r["meas_y_mm"])] for r in rows]) * 1e-3
        if len(xy) < 2:
            raise CalibrationInputError(f"{label}: {len(xy)} measured visit(s); RP needs at least 2")
        repeat = pose_repeatability(xy)  # in the area's plane: x and y
        centre = repeat.barycentre
        ends = min(drift_cycles, len(xy) // 2)
        drift = np.linalg.norm(xy[-ends:].mean(axis=0) - xy[:ends].mean(axis=0))
        positions[label] = {"n": len(xy), "x_mm": centre[0] * 1e3, "y_mm": centre[1] * 1e3,
                            "l_mean_um": repeat.l_mean * 1e6, "s_l_um": repeat.s_l * 1e6, "rp_um": repeat.rp_l * 1e6,
                            "drift_um": float(drift * 1e6)}
        series.append({"label": f"{label} ({len(xy)})", "xy_mm": np.tile(centre * 1e3, (len(xy), 1)),
                       "err": xy - centre, "colour": COLOURS[i % len(COLOURS)]})
    rp = {k: p["rp_um"] for k, p in positions.items()}
    stats = {"repeatability": {
        "rp_um": rp, "rp_max_um": max(rp.values()), "rp_mean_um": float(np.mean(list(rp.values()))),
        "drift_mean_um": float(np.mean([p["drift_um"] for p in positions.values()])), "positions": positions}}
    table = {"title": "Pose repeatability RP = mean l + 3 S_l (µm), ISO 9283, seen by the calibrated camera",
             "columns": ["position", "x (mm)", "y (mm)", "n", "mean l", "S_l", "RP", "drift"],
             "rows": [[k, round(p["x_mm"], 3), round(p["y_mm"], 3), p["n"], round(p["l_mean_um"], 2),
                       round(p["s_l_um"], 2), round(p["rp_um"], 2), round(p["drift_um"], 2)]
                      for k, p in positions.items()]
                     + [["seed 001 section 4 (their robot)", None, None, None, None, None, SEED_RP_UM, None]],
             "note": f"l: distance of a cycle's attained position from the position's barycentre; drift: between "
                     f"the mean positions of the first and the last {drift_cycles} cycles. The camera's own noise "
                     f"and its map's scale error add to what it sees of the robot."}
    chart = {"name": "repeatability", "title": "pose repeatability per position", "x_label": "position k of P_k",
             "y_label": "µm", "series": {"RP": [[i + 1, v] for i, v in enumerate(rp.values())],
                                         "mean l": [[i + 1, p["l_mean_um"]] for i, p in enumerate(positions.values())],
                                         "seed 001: ±5 µm": [[1, SEED_RP_UM], [len(rp), SEED_RP_UM]]}}
    rejected = [{"step": r.get("step"), "reason": r.get("message") or r.get("status")}
                for r in samples if r.get("status", "ok") != "ok"]
    plot = {"series": series, "title": "attained positions about their barycentre, per position"}
    return FitOutcome({"kind": "repeatability"}, stats, rejected, plot, tables=[table], charts=[chart])
