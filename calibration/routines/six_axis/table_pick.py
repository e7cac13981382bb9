"""table-pick: a six-axis cell's production job. The wrist camera finds a part on the table and the arm picks it
up and puts it down where it is asked to.

Look: the flange goes where the camera, through its active hand-eye calibration, looks straight down at
`look_mm` from `standoff_mm`; the frame's bright discs of the part's size are located on the plane of the part's
top face (calibration/models/hand_eye_locate.py), each with its 1-sigma. Pick: the one nearest `pick_near_mm`; the
vacuum cup (`tip_mm` on the flange) comes down onto its centre from `approach_mm` above, grips, and rises. Place:
the cup carries it over `place_mm` and comes down until the part's underside meets the table, releases, rises.

(pick-place is the micro cell's job, with its areas and tool compensation; routine names are one namespace.)
A place target or a look point outside the arm's limits, a camera without an active hand-eye calibration, or a
cell without a gripper is refused at submit and again by the plan, before anything moves. Nothing seen, or a part
the cup does not hold, ends the job with the reason in its rows; nothing is placed then.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from pydantic import Field

from geometry import ur

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.models.hand_eye_locate import HandEyeCamera
from calibration.routines.base import Area, Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.six_axis.hand_eye import TOOL_DOWN, flange_matrix, flange_target
from calibration.vision.centroid import find_blobs

HOME_BRANCH = ur.branch_of(np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0]))  # the branch the arm works on
Pair = tuple[float, float]
Triple = tuple[float, float, float]


class TablePickParams(Params):
    camera: str = Field("wrist", description="the wrist camera that finds the part (its hand-eye calibration)")
    look_mm: Pair = Field((-450.0, 150.0), description="where the camera looks straight down (base frame x, y)")
    standoff_mm: float = Field(350.0, gt=50, le=2000, description="the camera's height over the part's top face")
    pick_near_mm: Pair | None = Field(None, description="pick the part nearest this (default: look_mm)")
    place_mm: Pair = Field(..., description="where to put the part down (base frame x, y of its centre)")
    table_z_mm: float = Field(0.0, ge=-1000, le=1000, description="height of the table's surface (base frame)")
    part_diameter_mm: float = Field(30.0, gt=0, le=300, description="nominal; discs within +/-25 % are parts")
    part_height_mm: float = Field(6.0, gt=0, le=300)
    tip_mm: Triple = Field((0.0, 0.0, 150.0), description="the vacuum cup's centre on the flange (flange frame)")
    approach_mm: float = Field(40.0, gt=0, le=300, description="the cup comes down onto the part from this high")


class TablePick:
    name: ClassVar[str] = "table-pick"
    truth: ClassVar[str | None] = "cellctl.truth.six_axis:table_pick_truth"
    Params: ClassVar[type[TablePickParams]] = TablePickParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "action", "status", "u_px", "v_px", "diameter_px", "x_mm", "y_mm", "z_mm", "sigma_um", "held",
        "j1_deg", "j2_deg", "j3_deg", "j4_deg", "j5_deg", "j6_deg", "message")
    fit_columns: ClassVar[tuple[str, ...]] = ("action", "status")
    small_params: ClassVar[dict] = {"place_mm": (-450.0, 250.0)}

    def inputs(self, params: TablePickParams, devices: Devices) -> list[str]:
        return [f"hand-eye:{params.camera}"]

    def output(self, params, devices: Devices) -> str | None:
        return None  # production, not a calibration

    def check_targets(self, params: TablePickParams, areas: dict[str, Area], calibrations: dict[str, dict],
                      arm_limits: dict | None = None) -> None:
        target = f"hand-eye:{params.camera}"
        if target not in calibrations:
            raise CalibrationInputError(f"camera: {params.camera!r} has no active hand-eye calibration; run "
                                        f"hand-eye --param camera={params.camera} first")
        if calibrations[target].get("mount") != "eye-in-hand":
            raise CalibrationInputError(f"camera: {params.camera} is calibrated eye-to-hand; table-pick looks with "
                                        "a camera on the wrist")
        for where, (x, y) in (("look_mm", params.look_mm), ("place_mm", params.place_mm)):
            for axis, value in (("x_mm", x), ("y_mm", y)):
                box = (arm_limits or {}).get(axis)
                if box is not None and not box[0] <= value <= box[1]:
                    raise CalibrationInputError(f"{where}: {axis} {value:g} is outside the arm's limits; allowed: "
                                                f"{box[0]:g} to {box[1]:g}")

    def plan(self, params: TablePickParams, devices: Devices) -> list[Step]:
        self.check_targets(params, devices.areas, devices.calibrations)
        devices.camera(params.camera)
        if devices.gripper is None:
            raise CalibrationInputError("table-pick needs a gripper (the cell file's gripper: section)")
        # the look and the place within the arm's reach before anything moves (the pick is where the look finds it)
        camera = HandEyeCamera(devices.calibration(f"hand-eye:{params.camera}", self.name))
        top_z = (params.table_z_mm + params.part_height_mm) * 1e-3
        tip = np.asarray(params.tip_mm) * 1e-3
        place = np.array([*np.asarray(params.place_mm) * 1e-3, top_z])
        for what, flange in (("look_mm", _look_flange(camera, params, top_z)),
                             ("place_mm", _flange_for(place, tip)),
                             ("place_mm", _flange_for(place + [0, 0, params.approach_mm * 1e-3], tip))):
            try:
                ur.inverse(flange, HOME_BRANCH)
            except ur.Unreachable as exc:
                where = ", ".join(f"{v * 1e3:.0f}" for v in flange[:3, 3])
                raise CalibrationInputError(f"{what}: the flange would have to be at ({where}) mm, out of the arm's "
                                            f"reach ({exc}); nothing moved") from None
        return [Step(0, "look", {}), Step(1, "pick", {}), Step(2, "place", {})]

    # -- the three steps ---------------------------------------------------------------------------------------
    def execute(self, step: Step, params: TablePickParams, devices: Devices, history=()) -> StepResult:
        camera = HandEyeCamera(devices.calibration(f"hand-eye:{params.camera}", self.name))
        top_z = (params.table_z_mm + params.part_height_mm) * 1e-3
        if step.action == "look":
            return self._look(step, params, devices, camera, top_z)
        found = [r for r in history if r.get("action") == "look" and r.get("status") == "ok"]
        if step.action == "pick":
            return self._pick(step, params, devices, found, top_z)
        held = [r for r in history if r.get("action") == "pick" and str(r.get("held")) == "True"]
        return self._place(step, params, devices, bool(held), top_z)

    def _look(self, step, params, devices, camera: HandEyeCamera, top_z: float) -> StepResult:
        devices.arm.move_linear(_pose(_look_flange(camera, params, top_z)))
        reported = flange_matrix(devices.arm.pose())
        frame = devices.camera(params.camera).capture()
        row = {"step": step.index, "action": "look", **_joints(devices)}
        size_px = camera.lens.fx * params.part_diameter_mm / params.standoff_mm
        try:
            blobs = find_blobs(frame.image, "bright", min_diameter_px=0.75 * size_px, max_diameter_px=1.25 * size_px)
        except VisionError as exc:
            blobs, why = [], str(exc)
        else:
            why = f"no bright disc of {0.75 * size_px:.0f}-{1.25 * size_px:.0f} px (a {params.part_diameter_mm:g} mm part)"
        if not blobs:
            return StepResult(dict(row, status="nothing", message=f"no part in view: {why}"), [frame])
        xyz, sigma = camera.locate([(b.u, b.v) for b in blobs], reported, top_z)
        return StepResult([dict(row, status="ok", u_px=b.u, v_px=b.v, diameter_px=b.diameter_px,
                                x_mm=float(p[0] * 1e3), y_mm=float(p[1] * 1e3), z_mm=float(p[2] * 1e3),
                                sigma_um=float(s * 1e6), message="")
                           for b, p, s in zip(blobs, xyz, sigma)], [frame])

    def _pick(self, step, params, devices, found: list[dict], top_z: float) -> StepResult:
        row = {"step": step.index, "action": "pick"}
        if not found:
            return StepResult(dict(row, status="refused", held=False, message="the look found no part: nothing "
                                   "moved to pick"))
        near = np.asarray(params.pick_near_mm or params.look_mm)
        chosen = min(found, key=lambda r: math.hypot(float(r["x_mm"]) - near[0], float(r["y_mm"]) - near[1]))
        at = np.array([float(chosen["x_mm"]), float(chosen["y_mm"]), top_z * 1e3]) * 1e-3
        joints = self._down_and_up(params, devices, at, devices.gripper.grip)
        status = devices.gripper.status()
        held = bool(status.object_detected)
        return StepResult(dict(row, status="ok" if held else "missed", held=held,
                               x_mm=float(at[0] * 1e3), y_mm=float(at[1] * 1e3), z_mm=float(at[2] * 1e3),
                               sigma_um=chosen.get("sigma_um"), **joints,
                               message="" if held else "the cup did not seal: the part was not where the camera "
                                                       "located it"))

    def _place(self, step, params, devices, held: bool, top_z: float) -> StepResult:
        row = {"step": step.index, "action": "place"}
        if not held:
            return StepResult(dict(row, status="refused", message="nothing held: nothing placed"))
        at = np.array([*np.asarray(params.place_mm) * 1e-3, top_z])  # the part's top, its underside on the table
        joints = self._down_and_up(params, devices, at, devices.gripper.release)
        return StepResult(dict(row, status="ok", x_mm=float(at[0] * 1e3), y_mm=float(at[1] * 1e3),
                               z_mm=float(at[2] * 1e3), **joints, message=""))

    def _down_and_up(self, params, devices, at: np.ndarray, act) -> dict:
        """The cup straight down onto `at` from approach_mm above, `act` there (grip or release), and up again;
        the joints it acted at."""
        tip = np.asarray(params.tip_mm) * 1e-3
        above = at + np.array([0.0, 0.0, params.approach_mm * 1e-3])
        devices.arm.move_linear(_pose(_flange_for(above, tip)))
        devices.arm.move_linear(_pose(_flange_for(at, tip)))
        joints = _joints(devices)
        act()
        devices.arm.move_linear(_pose(_flange_for(above, tip)))
        return joints

    # -- the report ----------------------------------------------------------------------------------------------
    def fit(self, samples: list[dict], params, resolutions=None) -> FitOutcome:
        seen = [r for r in samples if r.get("action") == "look" and r.get("status") == "ok"]
        pick = next((r for r in samples if r.get("action") == "pick"), None)
        place = next((r for r in samples if r.get("action") == "place"), None)
        rejected = [{"step": r.get("step"), "reason": r.get("message")} for r in samples
                    if r.get("status") not in ("ok", None, "")]
        stats = {"parts_seen": len(seen), "picked": bool(pick and str(pick.get("held")) == "True"),
                 "placed": bool(place and place.get("status") == "ok")}
        if pick is not None and pick.get("sigma_um") not in (None, ""):
            stats["pick_sigma_um"] = float(pick["sigma_um"])
        rows = [[r.get("action"), r.get("status"), *(_round(r.get(k)) for k in ("x_mm", "y_mm", "z_mm", "sigma_um")),
                 r.get("message") or ""] for r in samples]
        table = {"title": "Look, pick, place", "columns": ["action", "status", "x_mm", "y_mm", "z_mm", "sigma_um",
                                                             "note"], "rows": rows,
                 "note": "look: each part the camera located (its top face's centre, base frame); pick and place: "
                         "where the cup was sent"}
        return FitOutcome({"kind": "table-pick"}, stats, rejected, tables=[table], summary=stats)


def _look_flange(camera: HandEyeCamera, params: TablePickParams, top_z: float) -> np.ndarray:
    """The flange where X puts the camera straight over look_mm, standoff_mm above the parts, its axis down."""
    T_camera = np.eye(4)
    T_camera[:3, :3] = TOOL_DOWN
    T_camera[:3, 3] = (*np.asarray(params.look_mm) * 1e-3, top_z + params.standoff_mm * 1e-3)
    return T_camera @ np.linalg.inv(camera.X)


def _flange_for(cup: np.ndarray, tip: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = TOOL_DOWN
    T[:3, 3] = cup - TOOL_DOWN @ tip
    return T


def _pose(T: np.ndarray) -> Pose:
    return flange_target(T[:3, :3], T[:3, 3])


def _joints(devices) -> dict:
    return {f"j{i}_deg": float(math.degrees(v)) for i, v in enumerate(devices.arm.joints().positions, start=1)}


def _round(value):
    try:
        return round(float(value), 3)
    except (TypeError, ValueError):
        return None

