"""calibration-check: do the active calibrations still hold? Which one drifted, by how much, and a touch-up.

A few moves against the active calibrations, each a measurement the calibrations predict:

- camera 1 and the nozzle (area1): the nozzle, commanded to a target with the tool compensation on, is read
  by camera 1's map at a grid of positions. At alpha_cal a camera shift and a nozzle change look alike (the
  nozzle simply appears elsewhere); turning the tool tells them apart, because the nozzle's offset turns with
  it and a camera's error does not. So at each position the tool turns through `turns_deg` (0, 90, 0, -90:
  half the readings at alpha_cal, which is the design that estimates both a shift and an offset change best
  for the moves spent). Checking camera 1 without the nozzle reads at alpha_cal only, trusting the nozzle.
- camera 2 (area2): spheres placed as virtual-grid-area2 places them (camera 1 measures each one's offset on
  the nozzle), read by camera 2's map. Camera 1's shift moves them too, and is modelled when area1 is read.
- the on-board camera (board): spheres laid on the free area, seen from views turned about the axis; where each
  sphere rests is unknown, but a mount shift turns with the arm (only the shift is checked: the camera sees the
  same spheres from the same place at every turn, so its rotation or scale would not show).

The verdict is a test of "nothing drifted" (calibration/models/drift.py): each reading's residual against the
noise the calibrations predict (their residual sigma, their map covariance at the pixels seen, the tool
offset's uncertainty), at the false-alarm rate `false_alarm` for the whole check (Bonferroni over its tests).
Each target gets a small drift model with its uncertainty (a camera: shift, rotation and scale about its
area's centre; the nozzle: its offset change at alpha_cal). When a drifted target's readings fit its model,
`update=true` stores a touch-up: the active calibration corrected by the estimate (rotation and scale only if
they are significant), verified by leave-one-out (each reading judged by the correction estimated from all the
others, which never saw it). When they do not fit, the check names the routine to recalibrate with.

A hand-eye calibration (target `hand-eye:<camera>`, six-axis cells) is checked from a few views of its board: was
the camera bumped, or the board moved (`_hand_eye.py`)? Its targets are checked apart from the micro cell's.
"""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
from pydantic import Field, field_validator

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.models.tool_offset import rot
from calibration.routines.base import Devices, FitOutcome, Step, StepResult
from calibration.routines.health import _hand_eye as hand_eye
from calibration.routines.health._judge import AREA1, AREA2, BOARD, BOARD_LAY, judge
from calibration.routines.micro.onboard_camera import OnboardCamera
from calibration.routines.steps import (
    deliver_from_supply,
    new_spheres,
    pick_sphere,
    place_held_sphere,
    visit_and_measure,
)
from calibration.usage import CellCalibration, ToolCompensatedArm
from calibration.vision.centroid import find_blobs


class CheckParams(hand_eye.HandEyeCheckParams):
    targets: str | None = Field(None, description="comma-separated targets to check (default: every one this "
                                "check knows with an active calibration; hand-eye:<camera> for a hand-eye "
                                "calibration)")
    update: bool = Field(False, description="store a touch-up of each drifted target whose drift fits the model")
    false_alarm: float = Field(0.01, gt=0, lt=0.5, description="chance of a drift verdict when nothing drifted")
    area: str = Field("area1", description="camera 1's area, where the nozzle is read")
    grid: tuple[int, int] = Field((3, 4), description="rows, cols of the positions read in that area, each with "
                                  "every turn of turns_deg (the nozzle checked)")
    grid_at_alpha_cal: tuple[int, int] = Field((4, 4), description="the same when camera 1 is checked without the "
                                               "nozzle: read at alpha_cal only")
    extent: float = Field(0.6, gt=0, le=1, description="share of the area the positions span")
    turns_deg: tuple[float, ...] = Field((0.0, 90.0, 0.0, -90.0), description="tool rotations at each position "
                                         "(relative to alpha_cal) when the nozzle is checked")
    tool: str = Field("nozzle", description="the tool calibration's target")
    place_area: str = Field("area2", description="where spheres are placed for camera 2")
    spheres: int = Field(16, ge=2, le=100, description="spheres placed for camera 2")
    supply_mm: tuple[float, float] | None = Field(None, description="where the feeder presents a sphere")
    supply_z_mm: float = Field(0.0, description="the feeder's surface height")
    park_mm: tuple[float, float, float] | None = Field(None, description="out of camera 2's view")
    sphere_diameter_mm: float = Field(1.0, gt=0, le=10, description="nominal sphere diameter")
    sphere_tolerance_mm: float = Field(0.2, ge=0, le=5, description="+/- on the sphere diameter")
    margin_mm: float = Field(3.0, ge=0, le=100, description="keep-out from area2's edge")
    plan_seed: int = Field(0, ge=0, description="draws where the spheres go")
    board_area: str = Field("board", description="free area where spheres are laid for the on-board camera")
    board_grid: tuple[int, int] = Field((2, 2), description="rows, cols of the spheres laid there")
    board_pitch_mm: tuple[float, float] = Field((3.0, 2.5), description="their pitch (x, y)")
    board_alphas_deg: tuple[float, ...] | None = Field(None, description="rotation of each view of them (turns "
                                                       "about the axis tell a mount shift from where the spheres "
                                                       "lie); default: the on-board calibration's own poses")
    board_repeats: int = Field(2, ge=1, le=10, description="how many times the views are taken")
    view_z_mm: float = Field(20.5, description="gripper height at which the on-board camera sees them in focus")
    mount_offset_mm: tuple[float, float] | None = Field(None, description="nominal: where the on-board camera "
                                                        "looks, from the gripper")
    pixel_um: float | None = Field(None, gt=0, description="the on-board camera's nominal resolution (to tell the "
                                   "spheres apart)")

    @field_validator("targets")
    @classmethod
    def _names(cls, value):
        if value is not None and not [t for t in value.split(",") if t.strip()]:
            raise ValueError("targets: give at least one name, e.g. cam1,nozzle")
        return value

    @field_validator("turns_deg")
    @classmethod
    def _turns(cls, value):
        if len(value) < 2 or np.ptp(value) < 30:
            raise ValueError(f"turns_deg {list(value)}: at least two rotations spanning 30 degrees or more")
        return value


class CalibrationCheck:
    name: ClassVar[str] = "calibration-check"
    truth: ClassVar[str | None] = "cellctl.truth.micro:check_truth"
    Params: ClassVar[type[CheckParams]] = CheckParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "set", "status", "camera", "frame_id", "pos", "turn_deg", "centre_x_mm", "centre_y_mm",
        "target_x_mm", "target_y_mm",
        "cmd_x_mm", "cmd_y_mm", "z_mm", "alpha_abs_deg", "x_mm", "y_mm", "meas_x_mm", "meas_y_mm",
        "u_px", "v_px", "diameter_px", "snr", "centring_x_um", "centring_y_um", "sphere", "message",
        *hand_eye.COLUMNS,
    )
    fit_columns: ClassVar[tuple[str, ...]] = ("set", "target_x_mm", "target_y_mm", "meas_x_mm", "meas_y_mm")
    small_params: ClassVar[dict] = {"grid": (2, 2), "grid_at_alpha_cal": (2, 2), "spheres": 2, "board_grid": (1, 2),
                                    "board_repeats": 1, "hand_eye_poses": 4}

    # -- what is checked ------------------------------------------------------
    def roles(self, params: CheckParams, devices: Devices) -> dict[str, str]:
        """target -> its role (cam1, nozzle, cam2, cam3: which measurement reads it), for the areas the cell has."""
        roles = {}
        if params.area in devices.areas:
            roles.update({devices.area(params.area).camera: "cam1", params.tool: "nozzle"})
        if params.place_area in devices.areas:
            roles[devices.area(params.place_area).camera] = "cam2"
        if params.board_area in devices.areas:
            roles[devices.area(params.board_area).camera] = "cam3"
        return roles

    def targets(self, params: CheckParams, devices: Devices) -> list[str]:
        roles = self.roles(params, devices)
        if params.targets is None:
            chosen = [t for t in roles if t in devices.calibrations] or hand_eye.active(devices)
            if not chosen:
                raise CalibrationInputError(f"calibration-check: none of {', '.join([*roles, 'hand-eye:<camera>'])} "
                                            "has an active calibration; calibrate first (calibrate-cell, hand-eye)")
            return chosen
        chosen = list(dict.fromkeys(t.strip() for t in params.targets.split(",") if t.strip()))
        unknown = [t for t in chosen if t not in roles and not hand_eye.is_target(t)]
        if unknown:
            raise CalibrationInputError(f"calibration-check: cannot check {', '.join(unknown)}; this cell's check knows "
                                        f"{', '.join([*roles, 'hand-eye:<camera>'])}")
        mixed = [t for t in chosen if not hand_eye.is_target(t)]
        if mixed and len(mixed) < len(chosen):
            raise CalibrationInputError(f"calibration-check: check the hand-eye targets apart from {', '.join(mixed)} "
                                        "(one check per kind of cell)")
        return chosen

    @staticmethod
    def _hand_eye(targets: list[str]) -> bool:
        return all(hand_eye.is_target(t) for t in targets)

    def _reads(self, params, devices) -> tuple[list[str], bool, bool, bool]:
        """(targets, area1 read, area2 read, board read): the micro cell's."""
        targets = self.targets(params, devices)
        role = self.roles(params, devices)
        kinds = {role[t] for t in targets}
        return targets, bool(kinds & {"cam1", "nozzle"}), "cam2" in kinds, "cam3" in kinds

    def inputs(self, params: CheckParams, devices: Devices) -> list[str]:
        targets = self.targets(params, devices)
        if self._hand_eye(targets):
            return targets
        targets, area1, area2, board = self._reads(params, devices)
        needed = list(targets)
        if area1 or area2:  # camera 1 reads the nozzle (area1) and centres the spheres (area2)
            needed.append(devices.area(params.area).camera)
        if params.tool in devices.calibrations:  # the tool compensation places every sphere and turns the nozzle
            needed.append(params.tool)
        return list(dict.fromkeys(needed))

    def output(self, params, devices: Devices) -> str | None:
        return None  # a check; its touch-ups are proposed as new versions (FitOutcome.calibrations)

    # -- plan -------------------------------------------------------------------
    def plan(self, params: CheckParams, devices: Devices) -> list[Step]:
        targets = self.targets(params, devices)
        if self._hand_eye(targets):
            hand_eye.validate(params, devices, targets)
            return [Step(i, action, args) for i, (action, args) in enumerate(hand_eye.plan(params, devices, targets))]
        targets, area1, area2, board = self._reads(params, devices)
        for target in self.inputs(params, devices):
            devices.calibration(target, self.name)  # refused before anything moves
            if target != params.tool and "uncertainty" not in devices.calibrations[target]:
                raise CalibrationInputError(
                    f"calibration-check: the active calibration of {target} (id "
                    f"{devices.calibrations[target].get('calibration_id')}) keeps no map uncertainty, which the "
                    f"check's verdict needs; it predates the check: recalibrate {target} once")
        steps: list[tuple[str, dict]] = []
        if area1:
            steps += self._area1_plan(params, devices, turn=params.tool in targets)
        if area2:
            steps += self._area2_plan(params, devices)
        if board:
            steps += self._board_plan(params, devices)
        return [Step(i, action, args) for i, (action, args) in enumerate(steps)]

    def _area1_plan(self, params: CheckParams, devices: Devices, turn: bool) -> list[tuple[str, dict]]:
        area = devices.area(params.area)
        rows, cols = params.grid if turn else params.grid_at_alpha_cal
        half = np.array(area.size) / 2 * params.extent
        xs = np.linspace(-half[0], half[0], cols) if cols > 1 else np.zeros(1)
        ys = np.linspace(-half[1], half[1], rows) if rows > 1 else np.zeros(1)
        turns = params.turns_deg if turn else (0.0,)
        out, pos = [], 0
        for r, y in enumerate(ys):
            for x in (xs if r % 2 == 0 else xs[::-1]):  # serpentine: short moves
                for t in turns:
                    out.append(("visit", {"set": AREA1, "pos": pos, "centre": list(area.centre),
                                          "x": float(area.centre[0] + x),
                                          "y": float(area.centre[1] + y), "z": area.z, "alpha_cal": area.alpha_cal,
                                          "turn": math.radians(t), "camera": area.camera}))
                pos += 1
        return out

    def _area2_plan(self, params: CheckParams, devices: Devices) -> list[tuple[str, dict]]:
        if params.supply_mm is None or params.park_mm is None or devices.gripper is None:
            raise CalibrationInputError("check of camera 2 needs a gripper, supply_mm and park_mm (cell file, "
                                        "routines.check)")
        area = devices.area(params.place_area)
        half = np.array(area.size) / 2 - params.margin_mm * 1e-3
        if np.any(half <= 0):
            raise CalibrationInputError(f"margin_mm={params.margin_mm} leaves no room in area {area.name}")
        spacing = 3 * (params.sphere_diameter_mm + params.sphere_tolerance_mm) * 1e-3
        rng = np.random.default_rng(params.plan_seed)
        targets: list[tuple[float, float]] = []
        for _ in range(params.spheres):
            for _attempt in range(1000):
                x, y = rng.uniform(np.array(area.centre) - half, np.array(area.centre) + half)
                if all(math.hypot(x - a, y - b) >= spacing for a, b in targets):
                    break
            else:
                raise CalibrationInputError(f"no room for {params.spheres} spheres {spacing * 1e3:.1f} mm apart")
            targets.append((float(x), float(y)))
        contact = (params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
        return [("place", {"set": AREA2, "pos": k, "centre": list(area.centre), "x": x, "y": y, "z": area.z + contact, "alpha": area.alpha_cal,
                           "camera": area.camera}) for k, (x, y) in enumerate(targets)]

    def _board_plan(self, params: CheckParams, devices: Devices) -> list[tuple[str, dict]]:
        if None in (params.supply_mm, params.mount_offset_mm, params.pixel_um) or devices.gripper is None:
            raise CalibrationInputError("check of the on-board camera needs a gripper, supply_mm, mount_offset_mm and "
                                        "pixel_um (cell file, routines.check)")
        area = devices.area(params.board_area)
        rows, cols = params.board_grid
        contact = (params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
        out, k = [], 0
        for r in range(rows):
            for c in range(cols):
                x = area.centre[0] + (c - (cols - 1) / 2) * params.board_pitch_mm[0] * 1e-3
                y = area.centre[1] + (r - (rows - 1) / 2) * params.board_pitch_mm[1] * 1e-3
                out.append(("lay", {"set": BOARD_LAY, "pos": k, "x": float(x), "y": float(y), "z": area.z + contact,
                                    "camera": area.camera}))
                k += 1
        mount = np.array(params.mount_offset_mm) * 1e-3
        # by default from the poses it was calibrated from: where the arm's own systematic errors are what the
        # calibration saw (elsewhere its axis sits off by a few µm that no single D describes)
        alphas = params.board_alphas_deg or devices.calibrations[area.camera].get("alphas_deg")
        if not alphas:
            raise CalibrationInputError(f"calibration-check: the calibration of {area.camera} does not say its poses; recalibrate "
                                        "it with onboard-camera, or give board_alphas_deg")
        for v, alpha in enumerate(list(alphas) * params.board_repeats):  # the camera over the spheres' centre
            a = math.radians(alpha)
            x, y = np.array(area.centre) - rot(a) @ mount
            out.append(("view", {"set": BOARD, "pos": v, "x": float(x), "y": float(y), "z": params.view_z_mm * 1e-3,
                                 "alpha": a, "camera": area.camera}))
        return out

    # -- collect ------------------------------------------------------------------
    def execute(self, step: Step, params: CheckParams, devices: Devices, history=()) -> StepResult:
        if step.action == hand_eye.ACTION:
            return hand_eye.execute(step, params, devices)
        action = {"visit": self._visit, "place": self._place, "lay": self._lay, "view": self._view}[step.action]
        return action(step, params, devices, history)

    def _visit(self, step: Step, params: CheckParams, devices: Devices, history) -> StepResult:
        """The nozzle to the target with the tool compensated, read by camera 1's map."""
        a = step.args
        cal = CellCalibration(devices.calibrations, params.tool)
        arm = ToolCompensatedArm(devices.arm, cal, a["alpha_cal"])
        pose = Pose(a["x"], a["y"], a["z"], a["alpha_cal"] + a["turn"])
        row, frame = visit_and_measure(replace(devices, arm=arm), pose, a["camera"])
        measured = cal.locate(a["camera"], [row["u_px"], row["v_px"]])[0] * 1e3  # NaN when not measured
        row.update(step=step.index, set=a["set"], pos=a["pos"], turn_deg=math.degrees(a["turn"]),
                   centre_x_mm=a["centre"][0] * 1e3, centre_y_mm=a["centre"][1] * 1e3,
                   target_x_mm=a["x"] * 1e3, target_y_mm=a["y"] * 1e3, meas_x_mm=measured[0], meas_y_mm=measured[1])
        return StepResult(row, [frame])

    def _place(self, step: Step, params: CheckParams, devices: Devices, history) -> StepResult:
        """A sphere placed as virtual-grid-area2 places one (centred by camera 1), read by camera 2's map."""
        a = step.args
        done = deliver_from_supply(devices, params, Pose(a["x"], a["y"], a["z"], a["alpha"]), params.area, a["camera"])
        offset, landed, reported, frame = done.offset, done.landed, done.reported, done.frames[-1]
        row = {"step": step.index, "set": a["set"], "pos": a["pos"], "camera": a["camera"], "frame_id": frame.frame_id,
               "centre_x_mm": a["centre"][0] * 1e3, "centre_y_mm": a["centre"][1] * 1e3, "turn_deg": 0.0,
               "target_x_mm": a["x"] * 1e3, "target_y_mm": a["y"] * 1e3, "x_mm": landed[0] * 1e3,
               "y_mm": landed[1] * 1e3, "z_mm": reported.z * 1e3, "centring_x_um": offset[0] * 1e6, "centring_y_um": offset[1] * 1e6}
        seen = [(r["u_px"], r["v_px"]) for r in history if r.get("set") == AREA2 and r.get("status") == "ok"]
        fresh = new_spheres(find_blobs_or_none(frame.image), seen)
        if len(fresh) != 1:
            row.update(status="no-feature", message=f"{len(fresh)} new spheres seen, expected 1")
            return StepResult(row, done.frames)
        blob = fresh[0]
        measured = CellCalibration(devices.calibrations).locate(a["camera"], [blob.u, blob.v],
                                                                diameter_px=blob.diameter_px)[0] * 1e3
        row.update(status="ok", u_px=blob.u, v_px=blob.v, diameter_px=blob.diameter_px, snr=blob.snr,
                   meas_x_mm=measured[0], meas_y_mm=measured[1], message="")
        return StepResult(row, done.frames)

    def _lay(self, step: Step, params: CheckParams, devices: Devices, history) -> StepResult:
        """A sphere laid on the free area, as onboard-camera lays its grid."""
        a = step.args
        contact = (params.supply_z_mm + params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
        pick_sphere(devices, tuple(v * 1e-3 for v in params.supply_mm), contact, 0.0)
        landed, reported = place_held_sphere(devices, Pose(a["x"], a["y"], a["z"], 0.0), np.zeros(2), 0.0)
        return StepResult({"step": step.index, "set": a["set"], "status": "ok", "pos": a["pos"], "turn_deg": 0.0,
                           "target_x_mm": a["x"] * 1e3, "target_y_mm": a["y"] * 1e3, "x_mm": landed[0] * 1e3,
                           "y_mm": landed[1] * 1e3, "z_mm": reported.z * 1e3, "message": ""})

    def _view(self, step: Step, params: CheckParams, devices: Devices, history) -> StepResult:
        """The laid spheres seen by the on-board camera from one pose, each located by its calibration (eq. 5)."""
        a = step.args
        devices.arm.move_linear(Pose(a["x"], a["y"], a["z"], a["alpha"]))
        reported = devices.arm.pose()
        camera = devices.camera(a["camera"])
        frame = camera.capture()
        common = {"step": step.index, "set": a["set"], "pos": a["pos"], "camera": a["camera"],
                  "frame_id": frame.frame_id, "turn_deg": math.degrees(reported.alpha), "x_mm": reported.x * 1e3,
                  "y_mm": reported.y * 1e3, "z_mm": reported.z * 1e3}
        laid = {int(r["pos"]): (r["target_x_mm"] * 1e-3, r["target_y_mm"] * 1e-3)
                for r in history if r.get("set") == BOARD_LAY}
        nominal = SimpleNamespace(mount_offset_mm=params.mount_offset_mm, pixel_um=params.pixel_um,
                                  pitch_mm=params.board_pitch_mm)
        found = OnboardCamera.identify(find_blobs_or_none(frame.image), laid, reported, nominal, camera.resolution)
        if not found:
            return StepResult(dict(common, status="no-feature", message="no laid sphere recognised"), [frame])
        cal = CellCalibration(devices.calibrations)
        rows = []
        for k, blob in found:
            where = cal.locate(a["camera"], [blob.u, blob.v], reported, diameter_px=blob.diameter_px)[0] * 1e3
            rows.append(dict(common, status="ok", sphere=k, target_x_mm=laid[k][0] * 1e3, target_y_mm=laid[k][1] * 1e3,
                             meas_x_mm=where[0], meas_y_mm=where[1], u_px=blob.u, v_px=blob.v,
                             diameter_px=blob.diameter_px, snr=blob.snr, message=""))
        return StepResult(rows, [frame])

    # -- judge --------------------------------------------------------------------
    def fit(self, samples: list[dict], params: CheckParams, resolutions=None) -> FitOutcome:
        raise CalibrationInputError("calibration-check judges the calibrations it checked: its samples alone cannot be fitted "
                                    "(run it on the cell, or give it the calibrations: CalibrationCheck().judge)")

    def judge(self, samples: list[dict], params: CheckParams, calibrations: dict[str, dict],
              resolutions=None) -> FitOutcome:
        if hand_eye.read(samples):
            return hand_eye.judge(samples, params, calibrations)
        return judge(samples, params, calibrations)

    def alarm(self, result: dict) -> dict | None:
        """Drift: which targets, what to do about each, by how much, and the touch-ups stored."""
        if result.get("verdict") != "drift":
            return None
        return {"verdict": "drift", "drifted": result["drifted"], "actions": result["actions"],
                "drift": result["stats"]["drift"], "updated": result.get("updated", {})}


def find_blobs_or_none(image) -> list:
    try:
        return find_blobs(image)
    except VisionError:
        return []
