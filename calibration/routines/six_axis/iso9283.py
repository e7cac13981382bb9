"""iso9283: a six-axis arm's pose accuracy (AP) and pose repeatability (RP) by ISO 9283:1998, measured by its wrist
camera on the table's ChArUco board through the camera's active hand-eye calibration (eye-in-hand).

The poses (§6.8): a cube of `cube_mm` edge centred at `centre_mm` (base frame), its diagonal plane `plane` the
measuring plane, P1 at its centre and P2..P5 on the plane's diagonals 10 % of the diagonal in from its corners
(calibration/models/iso9283.py), every one with the flange at `tool_rotation_deg`. The TCP is the flange (tool0) by
default: the poses are the flange's, as the controller reports it with a zero TCP offset, and what the camera
measures is the flange too. `tcp_mm` puts the TCP elsewhere on the flange (the cube's poses are then the TCP's).

A cycle visits P1 -> P5 in that order; `cycles` of them (ISO 9283: 30). Every visit comes from the same side (each
pose approached the same way at every cycle): from `approach_mm` back along the flange's axis, then a linear move
onto the pose. There the camera takes a frame; the board's ChArUco corners give T_camera_board by planar PnP with
the calibration's intrinsics (its translation scaled by the board's fitted printing scale: PnP on the drawing's
corners finds a board printed s times too large 1/s too near), and the attained flange pose is

    T_flange = Y @ inv(T_camera_board) @ inv(X)

with X = T_flange_camera and Y = T_base_board of the calibration: the flange in the frame the calibration defines (its
Y is where it put the board in the base frame). AP is that pose against the commanded one (§7.2.1); RP the spread of
the visits of one pose (§7.2.2). AP so measured holds the arm's error together with what is left of the hand-eye
calibration's own (X, Y, the lens and the board's scale were fitted with the arm's error in them, and absorb part
of it); RP is the arm's, with the camera's noise.

Why the camera looks at the board obliquely by default (30 deg from the vertical): seen head-on, a board leaves the
camera's tilt and its sideways position nearly interchangeable (turning about the board's centre changes the image
only through perspective), so each frame's corner errors move the measured flange, 0.4 m from the board, sideways by
50-80 µm on the simulated cell; at 30 deg, by 3-8 µm per axis (of which the sensor noise of one frame is 2-5 µm).
The point PnP places best is where the camera's axis meets the board (1-3 µm): a TCP there (`tcp_mm`) measures RP
to within a few µm, while the calibrated lens's own error (0.1 px of principal point is 20 µm at 0.4 m) moves its AP.

Before anything moves, the plan refuses, naming the pose: a pose or its approach out of the arm's reach (nominal
inverse kinematics on its home branch, joint limits, reach), the flange or the camera within 50 mm of the board's
plane, or a pose where the board (projected through the stored calibration) would show fewer than `min_corners`
corners. A visit whose frame shows too few corners, or an ambiguous board pose, is kept as a refused row, with the
reason; AP and RP are then over the visits measured.

Every move goes through the active `arm` calibration when one is in force (`moves: calibrated`), or on the
controller's own kinematics with it left out (`moves: controller`, ChoosesArmCalibration: the run is then made on the
arm as its controller moves it): the arm as it came and as calibrated, measured by the same instrument. The report
names the calibrations used.

`observe: fixed-cameras` measures with the fixed cameras an `arm` calibration made (the IRB 120 cell, its fixture of
four circles): _iso_stereo.py, whose docstring says how. The poses are then the fixture frame's (the controller's TCP
there); the cube, the cycles, the approach and the report are the same.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from geometry import ur
from geometry.charuco import DICTIONARIES, BoardDrawing

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.models import iso9283 as iso
from calibration.models.hand_eye import Intrinsics, pose_from_dict, pose_to_dict
from calibration.routines.base import Area, Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.six_axis import _iso_stereo as stereo_
from calibration.routines.six_axis.hand_eye import flange_matrix, flange_target
from calibration.vision.charuco import Corners, board_pose, find_corners

Triple = tuple[float, float, float]
HOME_DEG = (0.0, -90.0, 90.0, -90.0, -90.0, 0.0)  # the arm works on this configuration's branch (as hand-eye plans)
REACH_M = 0.85  # the UR5e's reach from the shoulder (the plan of hand-eye keeps within it too)
CLEARANCE_M = 0.05  # the flange and the camera stay this far above the board's plane
POSE_KEYS = ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")
CMD = tuple(f"cmd_{k}" for k in POSE_KEYS)
MEAS = tuple(f"meas_{k}" for k in POSE_KEYS)
FLANGE = tuple(f"flange_{k}" for k in POSE_KEYS)


class Iso9283Params(Params):
    observe: Literal["wrist-camera", "fixed-cameras"] = Field("wrist-camera", description="what measures: "
                                                              "wrist-camera, the camera on the wrist through its "
                                                              "hand-eye calibration and the table's board (the UR5e "
                                                              "cell); fixed-cameras, the cameras of the active arm "
                                                              "calibration watching the fixture (the IRB 120 cell)")
    camera: str = Field("wrist", description="wrist-camera: the wrist camera that measures (its active hand-eye "
                        "calibration, eye-in-hand, with the table's board)")
    cameras: tuple[str, ...] = Field(("cam1", "cam2"), min_length=2, description="fixed-cameras: the cameras that "
                                     "measure, calibrated by the active arm calibration")
    moves: Literal["calibrated", "controller"] = Field("calibrated", description="calibrated: every move through "
                                                       "the active arm calibration, when one is in force; "
                                                       "controller: on the controller's own kinematics, the arm "
                                                       "calibration left out (the arm as it came)")
    frames: int = Field(4, ge=1, le=50, description="fixed-cameras: frames each camera takes at every visit, "
                        "their circle centres averaged (the sensor's noise; the arm stands still)")
    view_angle_deg: float = Field(60.0, gt=0, lt=90, description="fixed-cameras: the fixture's plate at most this "
                                  "far from face-on to every camera at every pose")
    margin_px: float = Field(20.0, ge=0, le=1000, description="fixed-cameras: every circle this far inside every "
                             "image at every pose (predicted through the calibration)")
    cycles: int = Field(30, ge=2, le=1000, description="visits of each pose, P1 -> P5 per cycle (ISO 9283: 30)")
    cube_mm: float = Field(100.0, gt=0, le=1000, description="the test cube's edge (ISO 9283 §6.8)")
    centre_mm: Triple = Field((-550.0, -365.0, 406.0), description="the cube's centre, P1 (the TCP, base frame); "
                              "the default suits the UR5e hand-eye cell: where its camera bracket (0, 50, 65) mm puts "
                              "the wrist camera 350 mm above the table board's centre (-500, -130, 0), looking at it "
                              "30 deg from the vertical")
    plane: Literal[tuple(iso.PLANES)] = Field("x+", description="the cube's diagonal plane that holds P1..P5: x+ "
                                              "holds the edges along x and rises toward +y (x-: toward -y; y+, y-, "
                                              "z+, z- alike)")
    tool_rotation_deg: Triple = Field((180.0, -30.0, 90.0), description="the TCP's orientation at every pose "
                                      "(xyz Euler, base frame); the default suits the UR5e hand-eye cell: the "
                                      "flange's axis down, tilted 30 deg toward +y, the camera looking at the board "
                                      "obliquely (a board seen head-on leaves the camera's tilt and its sideways "
                                      "position nearly interchangeable)")
    tcp_mm: Triple = Field((0.0, 0.0, 0.0), description="the TCP on the flange (flange frame; fixed-cameras: "
                           "on the fixture frame): the point P1..P5 place and whose AP and RP are measured; default: "
                           "the flange itself (tool0), or the fixture frame")
    approach_mm: float = Field(20.0, gt=0, le=300, description="each visit comes from this far back along the "
                               "TCP's z axis (the same side every cycle, as ISO 9283 asks)")
    min_corners: int = Field(24, ge=6, le=1000, description="wrist-camera: a pose must show the camera at least "
                             "this many board corners (the plan predicts them through the calibration; a frame with "
                             "fewer is refused)")

    def rotation(self) -> np.ndarray:
        return Rotation.from_euler("xyz", self.tool_rotation_deg, degrees=True).as_matrix()

    def tcp(self) -> np.ndarray:
        """T_flange_tcp: the TCP's offset, no rotation."""
        T = np.eye(4)
        T[:3, 3] = np.asarray(self.tcp_mm) * 1e-3
        return T

    def poses(self) -> dict[str, np.ndarray]:
        """P1..P5, the TCP's poses (base frame, m)."""
        return iso.cube_poses(np.asarray(self.centre_mm) * 1e-3, self.cube_mm * 1e-3, self.plane, self.rotation())

    def flange_poses(self) -> dict[str, np.ndarray]:
        """Where the flange goes for each: T_base_tcp @ inv(T_flange_tcp)."""
        back = np.linalg.inv(self.tcp())
        return {name: T @ back for name, T in self.poses().items()}

    def approach(self, T: np.ndarray) -> np.ndarray:
        """Where a visit of the flange pose T starts: approach_mm back along the flange's axis."""
        A = T.copy()
        A[:3, 3] -= T[:3, 2] * self.approach_mm * 1e-3
        return A


class Iso9283:
    name: ClassVar[str] = "iso9283"
    truth: ClassVar[str | None] = "cellctl.truth.iso9283:iso9283_truth"
    Params: ClassVar[type[Iso9283Params]] = Iso9283Params
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "pose", "cycle", "status", "camera", "frame_id", *CMD, *FLANGE, *MEAS, "corners", "rms_px",
        "calibration", "calibration_id", "arm_calibration", "message")
    fit_columns: ClassVar[tuple[str, ...]] = ("pose", "cycle", *CMD, *MEAS)
    small_params: ClassVar[dict] = {"cycles": 3}

    def through_arm_calibration(self, params: Iso9283Params) -> bool:  # ChoosesArmCalibration
        return params.moves == "calibrated"

    def inputs(self, params: Iso9283Params, devices: Devices) -> list[str]:
        return [stereo_.TARGET] if params.observe == "fixed-cameras" else [_target(params)]

    def output(self, params, devices: Devices) -> str | None:
        return None  # a measurement of the arm, not a calibration

    # -- plan ----------------------------------------------------------------------------------------------------
    def check_targets(self, params: Iso9283Params, areas: dict[str, Area], calibrations: dict[str, dict],
                      arm_limits: dict | None = None) -> None:
        if params.observe == "fixed-cameras":
            stereo_.check_targets(params, calibrations)
            return
        target = _target(params)
        model = calibrations.get(target)
        if model is None:
            raise CalibrationInputError(f"camera: {params.camera!r} has no active hand-eye calibration; run hand-eye "
                                        f"--param camera={params.camera} first")
        if model.get("mount") != "eye-in-hand":
            raise CalibrationInputError(f"camera: {params.camera} is calibrated {model.get('mount')}; iso9283 measures "
                                        "with a camera on the wrist (eye-in-hand) looking at the table's board")
        missing = [k for k in ("hand_eye", "world", "intrinsics", "board") if k not in model]
        if missing:
            raise CalibrationInputError(f"the active calibration of {target} (id {model.get('calibration_id')}) keeps "
                                        f"no {', '.join(missing)} (fitted from pose pairs alone?); iso9283 needs one "
                                        f"made from images: run hand-eye --param camera={params.camera}")
        for name, T in params.flange_poses().items():
            for axis, value in zip(("x_mm", "y_mm", "z_mm"), T[:3, 3] * 1e3):
                box = (arm_limits or {}).get(axis)
                if box is not None and not box[0] <= value <= box[1]:
                    raise CalibrationInputError(f"{name}: the flange's {axis} {value:.1f} is outside the arm's limits "
                                                f"({box[0]:g} to {box[1]:g}); move centre_mm or shrink cube_mm")

    def plan(self, params: Iso9283Params, devices: Devices) -> list[Step]:
        flanges = params.flange_poses()
        if params.observe == "fixed-cameras":
            stereo_.check_plan(params, devices)
        else:
            camera = devices.camera(params.camera)  # an unknown camera, named, before anything else
            self.check_targets(params, devices.areas, devices.calibrations)
            model = devices.calibration(_target(params), self.name)
            reach_joints(flanges, params)
            check_views(flanges, params, model, tuple(getattr(camera, "resolution", None) or ()))
        steps = []
        for cycle in range(1, params.cycles + 1):  # a cycle: P1 -> P5
            for (name, T), F in zip(params.poses().items(), flanges.values()):
                steps.append(Step(len(steps), "visit", {"pose": name, "cycle": cycle, "commanded": _values(T),
                                                        "flange": _values(F), "approach": _values(params.approach(F))}))
        return steps

    def preview(self, params: Iso9283Params, image_size: tuple[int, int] | None) -> list[dict]:
        flanges = params.flange_poses()
        stereo = params.observe == "fixed-cameras"  # its reach and views are the controller's and the calibration's
        joints = {} if stereo else reach_joints(flanges, params)
        rows = []
        for (name, T), F in zip(params.poses().items(), flanges.values()):
            d = pose_to_dict(T)
            a = params.approach(F)[:3, 3] * 1e3
            rows.append([name, *(round(d[k], 3) for k in POSE_KEYS[:3]),
                         *(round(d[k], 6) + 0.0 for k in POSE_KEYS[3:]),  # + 0.0: no "-0" in the table
                         ", ".join(f"{v:.1f}" for v in F[:3, 3] * 1e3), ", ".join(f"{v:.1f}" for v in a),
                         *(round(float(v), 2) for v in np.degrees(joints.get(name, ())))])
        return [{"title": "ISO 9283 test poses (the TCP in the base frame; nothing moves for this)",
                 "columns": ["pose", *POSE_KEYS, "fixture_mm" if stereo else "flange_mm", "approach_mm",
                             *(() if stereo else (f"j{i}_deg" for i in range(1, 7)))],
                 "rows": rows,
                 "note": f"cube of {params.cube_mm:g} mm centred at {tuple(params.centre_mm)} mm, measuring plane "
                         f"{params.plane} (§6.8: P2..P5 10 % of the diagonal in from its corners); {params.cycles} "
                         f"cycles P1 -> P5, {5 * params.cycles} visits, each from {params.approach_mm:g} mm back along "
                         f"the TCP's z axis; the TCP is {_tcp_text(params)}. " + _view_text(params)}]

    # -- collect ----------------------------------------------------------------------------------------------------
    def execute(self, step: Step, params: Iso9283Params, devices: Devices, history=()) -> StepResult:
        a = step.args
        target = self.inputs(params, devices)[0]
        model = devices.calibration(target, self.name)
        devices.arm.move_linear(_pose(a["approach"]))
        devices.arm.move_linear(_pose(a["flange"]))
        reported = pose_to_dict(flange_matrix(devices.arm.pose()))
        row = {"step": step.index, "pose": a["pose"], "cycle": a["cycle"], **dict(zip(CMD, a["commanded"])),
               **{f"flange_{k}": v for k, v in reported.items()}, "calibration": target,
               "calibration_id": model.get("calibration_id"), "arm_calibration": getattr(devices.arm, "calibration_id", None)}
        if params.observe == "fixed-cameras":
            seen, frames = stereo_.measure(params, devices)
            T = seen.pop("pose", None)
            row.update({"camera": "+".join(params.cameras), "message": "", **seen})
            if T is not None:
                row.update({f"meas_{k}": v for k, v in pose_to_dict(T @ params.tcp()).items()})
            return StepResult(row, frames)
        frame = devices.camera(params.camera).capture()
        row.update(camera=params.camera, frame_id=frame.frame_id)
        try:
            seen, corners, rms = measure_flange(frame.image, model, params.min_corners)
        except VisionError as exc:
            return StepResult(dict(row, status="refused", message=str(exc)), [frame])
        return StepResult(dict(row, status="ok", corners=corners, rms_px=rms, message="",
                               **{f"meas_{k}": v for k, v in pose_to_dict(seen @ params.tcp()).items()}), [frame])

    # -- the report -------------------------------------------------------------------------------------------------
    def fit(self, samples: list[dict], params: Iso9283Params | None = None, resolutions=None) -> FitOutcome:
        return fit_iso9283(samples, params)


# -- the pieces, usable alone ---------------------------------------------------------------------------------------
def measure_flange(image: np.ndarray, model: dict, min_corners: int) -> tuple[np.ndarray, int, float]:
    """The flange pose (cell frame: the calibration's base) a frame of the wrist camera shows, the corners it used
    and PnP's RMS reprojection error (px); VisionError when the board cannot give it."""
    corners = find_corners(image, _drawing(model), min_corners)
    T, rms = flange_from_corners(corners, model)
    return T, len(corners), rms


def flange_from_corners(corners: Corners, model: dict) -> tuple[np.ndarray, float]:
    """T_flange in the calibration's frame from the board's corners in one image: Y @ inv(T_camera_board) @ inv(X),
    T_camera_board by planar PnP with the calibration's lens; and PnP's RMS reprojection error (px)."""
    X, Y = pose_from_dict(model["hand_eye"]), pose_from_dict(model["world"])
    lens = Intrinsics.from_dict(model["intrinsics"])
    T_camera_board, rms = board_pose(corners, _drawing(model), lens.K(), lens.dist)
    T_camera_board[:3, 3] *= float(model.get("board_scale", 1.0))  # the print's true size, as the fit found it
    return Y @ np.linalg.inv(T_camera_board) @ np.linalg.inv(X), rms


def reach_joints(poses: dict[str, np.ndarray], params: Iso9283Params) -> dict[str, np.ndarray]:
    """The joints of each pose (its approach reachable too), on the home branch; CalibrationInputError naming the
    first pose out of reach."""
    home = np.radians(HOME_DEG)
    branch = ur.branch_of(home)
    shoulder = np.array([0.0, 0.0, ur.UR5E_DH[0][1]])
    joints = {}
    for name, T in poses.items():
        for what, F in ((name, T), (f"{name}'s approach", params.approach(T))):
            where = ", ".join(f"{v * 1e3:.1f}" for v in F[:3, 3])
            try:
                q = ur.inverse(F, branch, near=home)
            except ur.Unreachable as exc:
                raise CalibrationInputError(f"{what}: the flange would have to be at ({where}) mm, out of the arm's "
                                            f"reach ({exc}); move centre_mm nearer the arm or shrink cube_mm; nothing "
                                            "moved") from None
            distance = float(np.linalg.norm(F[:3, 3] - shoulder))
            if distance > REACH_M:
                raise CalibrationInputError(f"{what}: the flange would have to be at ({where}) mm, {distance * 1e3:.0f} "
                                            f"mm from the shoulder, beyond the arm's reach of {REACH_M * 1e3:.0f} mm; "
                                            "move centre_mm nearer the arm or shrink cube_mm; nothing moved")
            if np.any(np.abs(q) > 2 * math.pi):
                raise CalibrationInputError(f"{what}: the flange at ({where}) mm needs joints outside +/-360 deg; "
                                            "change tool_rotation_deg; nothing moved")
            joints.setdefault(name, q)
    return joints


def check_views(poses: dict[str, np.ndarray], params: Iso9283Params, model: dict, image_size: tuple) -> None:
    """Each pose keeps the flange and the camera clear of the board and shows it at least min_corners corners, the
    board's corners projected through the stored calibration (X, Y, the intrinsics, the printing scale);
    CalibrationInputError naming the first pose that does not."""
    X, Y = pose_from_dict(model["hand_eye"]), pose_from_dict(model["world"])
    lens = Intrinsics.from_dict(model["intrinsics"])
    w, h = image_size or (lens.width, lens.height)
    points = _drawing(model).corners() * float(model.get("board_scale", 1.0))
    normal, origin = Y[:3, 2], Y[:3, 3]
    centre = Y[:3, :3] @ points.mean(axis=0) + origin
    for name, T in poses.items():
        T_base_camera = T @ X
        for part, p in (("flange", T[:3, 3]), ("camera", T_base_camera[:3, 3])):
            height = -normal @ (p - origin)  # the camera sees the print looking along its +z: in front is -z
            if height < CLEARANCE_M:
                raise CalibrationInputError(f"{name}: the {part} would be {height * 1e3:.0f} mm above the board's plane "
                                            f"(at least {CLEARANCE_M * 1e3:.0f} mm); raise centre_mm or shrink "
                                            "cube_mm; nothing moved")
        T_camera_board = np.linalg.inv(T_base_camera) @ Y
        pc = points @ T_camera_board[:3, :3].T + T_camera_board[:3, 3]
        front = pc[:, 2] > 0
        shown = 0
        if front.any():
            uv = cv2.projectPoints(pc[front], np.zeros(3), np.zeros(3), lens.K(), np.asarray(lens.dist))[0].reshape(-1, 2)
            shown = int(np.sum((uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)))
        if shown < params.min_corners:
            where = ", ".join(f"{v * 1e3:.0f}" for v in centre)
            raise CalibrationInputError(
                f"{name}: the {params.camera} camera would see {shown} of the board's {len(points)} corners there "
                f"(min_corners={params.min_corners}), predicted through {_target(params)} (id "
                f"{model.get('calibration_id')}); put centre_mm over the board (its centre is at ({where}) mm) or "
                "shrink cube_mm; nothing moved")


def fit_iso9283(samples: list[dict], params: Iso9283Params | None = None) -> FitOutcome:
    """AP (§7.2.1) and RP (§7.2.2) per pose from the measured visits (the rows' cmd_* and meas_* columns), their
    tables and statistics; a pose with fewer than 2 measured visits is left out, with the reason."""
    ok = [r for r in samples if r.get("status", "ok") == "ok"]
    rejected = [{"step": r.get("step"), "pose": r.get("pose"), "reason": r.get("message") or r.get("status")}
                for r in samples if r.get("status", "ok") != "ok"]
    names = sorted({str(r["pose"]) for r in ok})
    results = {}
    for name in names:
        rows = sorted((r for r in ok if str(r["pose"]) == name), key=lambda r: int(r["cycle"]))
        if len(rows) < 2:
            rejected.append({"pose": name, "reason": f"{len(rows)} measured visit: RP needs at least 2"})
            continue
        commanded = np.array([_matrix(r, "cmd_") for r in rows])
        attained = np.array([_matrix(r, "meas_") for r in rows])
        results[name] = (iso.pose_accuracy(commanded, attained), iso.pose_repeatability(attained), commanded[0])
    if not results:
        raise CalibrationInputError("no pose with 2 or more measured visits: nothing to evaluate (the rows need "
                                    "status ok and their cmd_* and meas_* columns)")
    ap = {k: float(a.ap_p * 1e3) for k, (a, _, _) in results.items()}
    rp = {k: float(r.rp_l * 1e3) for k, (_, r, _) in results.items()}
    per_pose = {k: {"n": a.n, "APp_mm": a.ap_p * 1e3, **{f"AP{c}_mm": float(v * 1e3) for c, v in zip("xyz", a.ap_xyz)},
                    **{f"AP{c}_deg": float(math.degrees(v)) for c, v in zip("abc", a.ap_abc)},
                    "RPl_mm": r.rp_l * 1e3, "l_mean_mm": r.l_mean * 1e3, "S_l_mm": r.s_l * 1e3,
                    **{f"RP{c}_deg": float(math.degrees(v)) for c, v in zip("abc", r.rp_abc)},
                    "barycentre_mm": [float(v * 1e3) for v in a.barycentre]}
                for k, (a, r, _) in results.items()}
    used = sorted({(str(r.get("calibration")), r.get("calibration_id")) for r in ok if r.get("calibration")}, key=str)
    stats = {"ap_mm": {**ap, "worst": max(ap.values())}, "rp_mm": {**rp, "worst": max(rp.values())},
             "per_pose": per_pose, "cycles": max(int(r["cycle"]) for r in ok), "n_visits": len(samples),
             "n_measured": len(ok), "calibrations": {t: i for t, i in used}}
    tables = [_standard_table(results, params), _barycentre_table(results), _visits_table(samples, used, params)]
    summary = {"ap_worst_mm": stats["ap_mm"]["worst"], "rp_worst_mm": stats["rp_mm"]["worst"]}
    return FitOutcome({"kind": "iso9283"}, stats, rejected, tables=tables, summary=summary)


def _standard_table(results: dict, params: Iso9283Params | None) -> dict:
    rows = []
    for name, (a, r, _) in results.items():
        rows.append([name, a.n, round(a.ap_p * 1e3, 4), *(round(float(v * 1e3), 4) for v in a.ap_xyz),
                     *(round(math.degrees(v), 5) for v in a.ap_abc), round(r.rp_l * 1e3, 4),
                     *(round(math.degrees(v), 5) for v in r.rp_abc)])
    return {"title": "ISO 9283 pose accuracy (§7.2.1) and pose repeatability (§7.2.2)",
            "columns": ["pose", "n", "APp_mm", "APx_mm", "APy_mm", "APz_mm", "APa_deg", "APb_deg", "APc_deg",
                        "RPl_mm", "RPa_deg", "RPb_deg", "RPc_deg"],
            "rows": rows,
            "note": "AP: the barycentre of the attained poses against the commanded pose (angles: the mean small "
                    "rotation about x, y, z); RPl = mean l + 3 S_l, RPa/b/c = +/- 3 S. " + _attained_text(params)}


def _attained_text(params: Iso9283Params | None) -> str:
    if params is not None and params.observe == "fixed-cameras":
        return ("Attained: the fixture as the fixed cameras of the arm calibration measured it (its circles in "
                "every camera at once), in the frame that calibration defines; so AP holds what is left of the "
                "cameras' calibration beside the arm's error, and RP the cameras' noise beside the arm's")
    return ("Attained: the flange as the wrist camera measured it, in the frame its hand-eye calibration defines "
            "(its Y); so AP holds the calibration's own error beside the arm's, and RP the camera's noise beside "
            "the arm's")


def _barycentre_table(results: dict) -> dict:
    rows = []
    for name, (a, r, cmd) in results.items():  # positions as text: a table cell shows 4 significant digits of a float
        rows.append([name, _xyz(cmd[:3, 3]), _xyz(a.barycentre), round(r.l_mean * 1e3, 4), round(r.s_l * 1e3, 4)])
    return {"title": "Barycentre of the attained positions, per pose",
            "columns": ["pose", "commanded_mm", "barycentre_mm", "l_mean_mm", "S_l_mm"],
            "rows": rows, "note": "x, y, z (base frame as the calibration defines it); l: each visit's distance from "
                                  "the barycentre; S_l its sample standard deviation"}


def _xyz(p_m: np.ndarray) -> str:
    return ", ".join(f"{v * 1e3:.4f}" for v in p_m)


def _visits_table(samples: list[dict], used, params: Iso9283Params | None = None) -> dict:
    names = sorted({str(r["pose"]) for r in samples if r.get("pose")})
    rows = []
    for name in names:
        mine = [r for r in samples if str(r.get("pose")) == name]
        ok = [r for r in mine if r.get("status", "ok") == "ok"]
        rows.append([name, len(mine), len(ok),
                     round(float(np.mean([float(r["corners"]) for r in ok])), 1) if ok else None,
                     round(float(np.mean([float(r["rms_px"]) for r in ok])), 4) if ok else None])
    cals = ", ".join(f"{t} (id {i})" for t, i in used) or "none recorded"
    stereo = params is not None and params.observe == "fixed-cameras"
    arms = sorted({str(r["arm_calibration"]) for r in samples if r.get("arm_calibration") not in (None, "")})
    if params is not None and params.moves == "controller":
        moved = "the arm moved on its controller's own kinematics (moves=controller: the arm calibration left out)"
    elif arms:
        moved = f"every move through the arm calibration (id {', '.join(arms)})"
    else:
        moved = "the arm moved on its controller's own kinematics (no arm calibration in force)"
    return {"title": "Visits and what measured them",
            "columns": ["pose", "visits", "measured", "circles_mean" if stereo else "corners_mean",
                        "reprojection_rms_px" if stereo else "pnp_rms_px"],
            "rows": rows, "note": f"calibrations used: {cals}; {moved}"}


def _view_text(params: Iso9283Params) -> str:
    if params.observe == "fixed-cameras":
        return (f"Every camera ({', '.join(params.cameras)}) must see every circle at every pose and the controller "
                "reach it: checked through the arm calibration when the run is planned")
    return (f"The board must show {params.min_corners} corners at every pose: checked through the calibration when "
            "the run is planned")


def _tcp_text(params: Iso9283Params) -> str:
    if not any(params.tcp_mm):
        return "the fixture frame" if params.observe == "fixed-cameras" else "the flange (tool0)"
    return f"({', '.join(f'{v:g}' for v in params.tcp_mm)}) mm on the flange"


def _target(params: Iso9283Params) -> str:
    return f"hand-eye:{params.camera}"


def _drawing(model: dict) -> BoardDrawing:
    b = model["board"]
    if b.get("dictionary") not in DICTIONARIES:
        raise CalibrationInputError(f"the calibration's board dictionary {b.get('dictionary')!r}; allowed: "
                                    f"{', '.join(DICTIONARIES)}")
    return BoardDrawing(tuple(b["squares"]), b["square_mm"] * 1e-3, b["marker_mm"] * 1e-3, b["dictionary"],
                        int(b.get("first_marker", 0)))


def _values(T: np.ndarray) -> list[float]:
    d = pose_to_dict(T)
    return [float(d[k]) for k in POSE_KEYS]


def _pose(values) -> Pose:
    T = pose_from_dict(dict(zip(POSE_KEYS, values)))
    return flange_target(T[:3, :3], T[:3, 3])


def _matrix(row: dict, prefix: str) -> np.ndarray:
    try:
        return pose_from_dict({k: row[prefix + k] for k in POSE_KEYS})
    except KeyError as exc:
        raise CalibrationInputError(f"step {row.get('step')}: column {exc.args[0]!r} is missing; the rows need "
                                    f"{', '.join(prefix + k for k in POSE_KEYS)}") from None
    except CalibrationInputError as exc:
        raise CalibrationInputError(f"step {row.get('step')}, {prefix}*: {exc}") from None
