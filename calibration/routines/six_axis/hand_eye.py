"""Hand-eye calibration of a six-axis arm's camera: on the wrist (eye-in-hand) or over the table (eye-to-hand).

Plan: poses from the region the engineer gives (_poses.py), reachable, showing the board, rotating about
well-spread axes; a region that cannot give them is refused before anything moves. Collect: at each pose the
flange pose the arm reports and the ChArUco corners the camera sees (a frame with too few corners or an ambiguous
pose is kept as a refused row, with the reason). Fit: one simultaneous adjustment of X (flange->camera or
flange->board), Y (base->board or base->camera), the camera's intrinsics and the board's printed scale, over the
reprojection error of every corner in every image (models/hand_eye.py), its covariance honest about the arm's own
error. Verify on held-out poses the fit never saw: their reprojection error, and the board's corners predicted in
the base frame against those each held-out view measures. Eye-in-hand, the touch test follows: corners the
held-out views located (through the fit made from the samples so far) are touched with the tool tip; the rows say
where, and the simulation scores the miss (`truth.touch_mean_mm`; on a real cell, the operator looks). Beside it, on the same samples, OpenCV's closed-form
methods fed the usual chain (intrinsics, then PnP per view, then AX = XB).

`cellctl fit hand-eye --samples F.csv` fits a run's samples again, or pose pairs from elsewhere (one row per
pose: the flange pose and the camera->board pose), robustly and with covariance (models.hand_eye.fit_pose_pairs).
"""

from __future__ import annotations

import json
import math
from typing import ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field, model_validator
from scipy.spatial.transform import Rotation

from geometry.charuco import DICTIONARIES, BoardDrawing
from geometry.orientation import quaternion_wxyz

from drivers.interfaces import JointState, Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.models import hand_eye as he
from calibration.routines.base import Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.six_axis import _samples as samples_
from calibration.routines.six_axis._poses import PosePlan, Region, plan_poses
from calibration.vision.charuco import board_pose, find_corners

Triple = tuple[float, float, float]
DEFAULT_IMAGE = (2448, 2048)  # planning's guess of the image size when the camera does not say (5 MP)


class HandEyeParams(Params):
    mount: Literal["eye-in-hand", "eye-to-hand"] = Field("eye-in-hand", description="eye-in-hand: the camera rides "
                                                         "the flange, the board lies on the table; eye-to-hand: the "
                                                         "camera is fixed, the board rides the flange")
    camera: str = Field("wrist", description="the camera calibrated")
    poses: int = Field(15, ge=4, le=200, description="calibration poses")
    verify_poses: int = Field(5, ge=0, le=100, description="held-out poses the fit never sees")
    intrinsics: Literal["fit", "stored"] = Field("fit", description="fit: the camera's intrinsics are adjusted with "
                                                 "the hand-eye; stored: those of its active hand-eye calibration")
    # the board's drawing
    squares: tuple[int, int] = Field((12, 9), description="board: chessboard squares (x, y)")
    square_mm: float = Field(20.0, gt=0, le=500, description="board: square size as drawn")
    marker_mm: float = Field(15.0, gt=0, le=500, description="board: marker size as drawn")
    dictionary: Literal[DICTIONARIES] = Field("DICT_5X5_250", description="board: ArUco dictionary")
    first_marker: int = Field(0, ge=0, le=249, description="board: id of its first marker")
    # the region, and what the engineer knows roughly
    target_mm: Triple = Field((-500.0, -130.0, 0.0), description="eye-in-hand: the board's rough centre; "
                              "eye-to-hand: where to show the flange's board (base frame)")
    standoff_mm: float = Field(350.0, gt=50, le=2000, description="eye-in-hand: camera to board distance")
    depth_mm: float = Field(80.0, ge=0, le=1000, description="the distance varies by up to +/- this (one distance "
                            "alone cannot tell the camera's offset along its axis from its focal length)")
    radius_mm: float = Field(40.0, ge=0, le=500, description="spread of the aim point (eye-in-hand) or of the board "
                             "(eye-to-hand) about target_mm")
    tilt_deg: float = Field(30.0, ge=0, le=75, description="views tilted up to this from facing the board")
    roll_deg: float = Field(45.0, ge=0, le=180, description="views turned up to +/- this about the line of sight")
    mount_mm: Triple = Field((0.0, 50.0, 65.0), description="eye-in-hand: the camera on the flange; eye-to-hand: "
                             "the board's centre on the flange (flange frame, roughly)")
    mount_rotation_deg: Triple | None = Field(None, description="its rough orientation on the flange (xyz Euler); "
                                              "default: looking (eye-in-hand) or facing (eye-to-hand) along the "
                                              "flange axis")
    camera_mm: Triple | None = Field(None, description="eye-to-hand: the fixed camera's rough position (base frame)")
    focal_mm: float = Field(8.0, gt=0, le=500, description="the lens (planning and the first guess)")
    pixel_um: float = Field(3.45, gt=0, le=50, description="the sensor's pixel pitch")
    home_deg: tuple[float, float, float, float, float, float] = Field(
        (0.0, -90.0, 90.0, -90.0, -90.0, 0.0), description="the plan keeps this configuration's IK branch")
    min_corners: int = Field(12, ge=6, le=1000, description="frames with fewer corners are refused")
    plan_seed: int = Field(0, ge=0, description="draws the poses within the region")
    order_seed: int = Field(0, ge=0, description="0: the poses in the planned tour; else visited in an order shuffled "
                            "by this seed (the result must not depend on it)")
    arm_accuracy_mm: float = Field(0.1, ge=0, le=50, description="the arm's accuracy at the flange, 1-sigma per axis "
                                   "(a factory-calibrated UR: 0.1); the floor of the result's uncertainty")
    arm_accuracy_deg: float = Field(0.01, ge=0, le=5, description="the same for its orientation")
    loss: Literal["linear", "soft_l1", "huber"] = Field("soft_l1", description="robust loss of the fit")
    # the touch test (eye-in-hand)
    touches: int = Field(4, ge=0, le=50, description="eye-in-hand: board corners the held-out views locate, each "
                         "then touched with the tool tip (0: no touch test)")
    tip_mm: Triple = Field((0.0, 0.0, 150.0), description="the touch pointer's tip (flange frame); it must reach "
                           "past the camera")
    approach_mm: float = Field(30.0, gt=0, le=300, description="the tip comes down onto each corner from this high")

    @model_validator(mode="after")
    def _board(self):
        if not self.marker_mm < self.square_mm:
            raise ValueError(f"marker_mm {self.marker_mm} must be smaller than square_mm {self.square_mm}")
        if self.mount == "eye-to-hand" and self.camera_mm is None:
            raise ValueError("camera_mm: eye-to-hand needs the fixed camera's rough position (base frame, mm)")
        return self

    def drawing(self) -> BoardDrawing:
        return BoardDrawing(tuple(self.squares), self.square_mm * 1e-3, self.marker_mm * 1e-3, self.dictionary,
                            self.first_marker)

    def mount_guess(self) -> np.ndarray:
        T = np.eye(4)
        rotation = self.mount_rotation_deg or ((0.0, 0.0, 0.0) if self.mount == "eye-in-hand" else (180.0, 0.0, 0.0))
        T[:3, :3] = Rotation.from_euler("xyz", rotation, degrees=True).as_matrix()
        T[:3, 3] = np.asarray(self.mount_mm) * 1e-3
        return T

    def arm_accuracy(self) -> tuple[float, float]:
        return self.arm_accuracy_mm * 1e-3, math.radians(self.arm_accuracy_deg)

    def focal_px(self) -> float:
        return self.focal_mm / (self.pixel_um * 1e-3)


class HandEye:
    name: ClassVar[str] = "hand-eye"
    truth: ClassVar[str | None] = "cellctl.truth.six_axis:hand_eye_truth"
    Params: ClassVar[type[HandEyeParams]] = HandEyeParams
    sample_columns: ClassVar[tuple[str, ...]] = samples_.SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = samples_.FIT_COLUMNS
    small_params: ClassVar[dict] = {"poses": 6, "verify_poses": 1}

    def inputs(self, params: HandEyeParams, devices: Devices) -> list[str]:
        return [self.output(params, devices)] if params.intrinsics == "stored" else []

    def output(self, params: HandEyeParams, devices: Devices) -> str | None:
        return f"hand-eye:{params.camera}"

    # -- plan ------------------------------------------------------------------
    def pose_plan(self, params: HandEyeParams, image_size: tuple[int, int]) -> PosePlan:
        """The poses, checked (reach, joint limits, the board in view, spread rotation axes), or the reason not."""
        drawing = params.drawing()
        region = Region(params.mount, np.asarray(params.target_mm) * 1e-3, params.standoff_mm * 1e-3,
                        params.depth_mm * 1e-3, params.radius_mm * 1e-3, math.radians(params.tilt_deg), math.radians(params.roll_deg),
                        params.mount_guess(),
                        None if params.camera_mm is None else np.asarray(params.camera_mm) * 1e-3,
                        params.focal_px(), image_size, min(drawing.size_m) / 2, np.radians(params.home_deg))
        return plan_poses(region, params.poses, params.verify_poses, params.plan_seed)

    def preview(self, params: HandEyeParams, image_size: tuple[int, int] | None) -> list[dict]:
        table = self.pose_plan(params, image_size or DEFAULT_IMAGE).table()
        if params.mount == "eye-in-hand" and params.verify_poses and params.touches:
            table["note"] += (f"; then {params.touches} touches: the tip at {tuple(params.tip_mm)} mm on the flange "
                              f"comes down {params.approach_mm:g} mm onto corners the held-out views locate")
        return [table]

    def plan(self, params: HandEyeParams, devices: Devices) -> list[Step]:
        camera = devices.camera(params.camera)  # an unknown camera fails before any motion
        if params.intrinsics == "stored":
            devices.calibration(self.output(params, devices), self.name)
        size = tuple(getattr(camera, "resolution", None) or DEFAULT_IMAGE)
        poses = self.pose_plan(params, size).poses
        if params.order_seed:
            poses = [poses[i] for i in np.random.default_rng(params.order_seed).permutation(len(poses))]
        steps = [Step(i, "pose", {"pose": p.name, "set": p.set, "joints": [float(v) for v in p.joints]})
                 for i, p in enumerate(poses)]
        if params.mount == "eye-in-hand" and params.verify_poses > 0:
            steps += [Step(len(steps) + k, "touch", {"touch": k + 1}) for k in range(params.touches)]
        return steps

    # -- collect ---------------------------------------------------------------
    def execute(self, step: Step, params: HandEyeParams, devices: Devices, history=()) -> StepResult:
        if step.action == "touch":
            return self._touch(step, params, devices, list(history))
        row, frame = visit(step, params.camera, devices)
        h, w = frame.image.shape[:2]
        K, dist, stored = self._lens(params, devices, (w, h))
        row.update(stored)
        drawing = params.drawing()
        try:
            corners = find_corners(frame.image, drawing, params.min_corners)
            board_pose(corners, drawing, K, dist)  # refuses an ambiguous view
        except VisionError as exc:
            return StepResult(dict(row, status="refused", message=str(exc)), [frame])
        rows = [dict(row, status="ok", corner_id=int(i), u_px=float(u), v_px=float(v), message="")
                for i, (u, v) in zip(corners.ids, corners.uv)]
        return StepResult(rows, [frame])

    def _lens(self, params, devices, size) -> tuple[np.ndarray, np.ndarray, dict]:
        """K and distortion for the checks at collection, and the stored intrinsics' columns (none when fitted)."""
        if params.intrinsics == "stored":
            lens = he.Intrinsics.from_dict(devices.calibration(self.output(params, devices), self.name)["intrinsics"])
            values = [lens.fx, lens.fy, lens.cx, lens.cy, *lens.dist]
            return lens.K(), np.asarray(lens.dist), dict(zip(samples_.INTRINSIC_COLUMNS, values))
        w, h = size
        f = params.focal_px()
        return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]]), np.zeros(5), {}

    # -- touch -------------------------------------------------------------------
    def _touch(self, step: Step, params: HandEyeParams, devices: Devices, history: list[dict]) -> StepResult:
        """Fit the samples so far, locate one board corner in a held-out view, and bring the tool tip down onto
        it. A fit or a location that fails refuses the touch (the row says why); nothing moves then."""
        k = int(step.args["touch"])
        row = {"step": step.index, "pose": f"touch{k}", "set": "touch", "camera": params.camera}
        try:
            corner_id, located, view = self._locate_for_touch(k, params, history)
        except (CalibrationInputError, VisionError) as exc:
            return StepResult(dict(row, status="refused", message=f"no corner to touch: {exc}"))
        tip = np.asarray(params.tip_mm) * 1e-3
        R = TOOL_DOWN
        at = flange_target(R, located - R @ tip)
        above = flange_target(R, located + np.array([0, 0, params.approach_mm * 1e-3]) - R @ tip)
        devices.arm.move_linear(above)
        devices.arm.move_linear(at)
        reported = he.pose_to_dict(flange_matrix(devices.arm.pose()))
        joints = np.degrees(devices.arm.joints().positions)
        devices.arm.move_linear(above)  # off the board again before anything else moves
        return StepResult(dict(row, status="ok", corner_id=corner_id,
                               **{c: float(v) for c, v in zip(samples_.JOINT_COLUMNS, joints)},
                               **{f"flange_{f}": v for f, v in reported.items()},
                               **{c: float(v * 1e3) for c, v in zip(samples_.TOUCH_COLUMNS, located)},
                               message=f"located by {view}"))

    def _locate_for_touch(self, k: int, params: HandEyeParams, history: list[dict]) -> tuple[int, np.ndarray, str]:
        """Touch k's corner (cycling through the held-out views and the board's quadrants) in the base frame, as
        its held-out view measures it through the fit of the calibration views."""
        views = [r for r in history if not samples_.is_touch(r)]
        key = json.dumps([views, params.model_dump()], sort_keys=True, default=str)
        if getattr(self, "_touch_fit", (None,))[0] != key:  # one fit serves every touch of a run
            self._touch_fit = (key, *self._fit_core(views, params))
        _, result, data, board, _ = self._touch_fit
        ver = data.views["ver"]
        if not ver:
            raise CalibrationInputError("no held-out view saw the board")
        view = ver[(k - 1) % len(ver)]
        lo, hi = board.corners[:, :2].min(axis=0), board.corners[:, :2].max(axis=0)
        quadrant = np.array([(1, 1), (3, 1), (3, 3), (1, 3)][(k - 1) % 4]) / 4
        wanted = lo + quadrant * (hi - lo)
        seen = board.corners[view.ids, :2]
        i = int(np.argmin(np.linalg.norm(seen - wanted, axis=1)))
        points = board.corners[view.ids] * result.board_scale
        T_camera_board = chain_pairs([he.View(view.pose, view.T_base_flange, np.arange(len(view.ids)), view.uv)],
                                     he.Board(points), result.intrinsics)[0]
        T = view.T_base_flange @ result.X @ T_camera_board
        return int(view.ids[i]), T[:3, :3] @ points[i] + T[:3, 3], view.pose

    # -- fit ---------------------------------------------------------------------
    def fit(self, samples: list[dict], params: HandEyeParams, resolutions=None) -> FitOutcome:
        if samples_.has_corners(samples):
            return self._fit_images(samples, params)
        return self._fit_pairs(samples, params)

    def _fit_core(self, rows: list[dict], params: HandEyeParams):
        """The simultaneous adjustment of the calibration views: (result, samples, board, first intrinsics)."""
        data = samples_.image_samples(rows)
        board = he.Board(params.drawing().corners())
        cal = data.views["cal"]
        if data.stored is not None:
            s = data.stored
            lens0 = he.Intrinsics(*data.size, s["fx_px"], s["fy_px"], s["cx_px"], s["cy_px"],
                                  (s["k1"], s["k2"], s["p1"], s["p2"], s["k3"]))
        else:
            lens0 = first_intrinsics(cal, board, data.size)
        he.check_motion([v.T_base_flange for v in cal])
        result = he.fit_views(cal, board, params.mount, lens0, fit_intrinsics=data.stored is None, loss=params.loss,
                              arm_accuracy=params.arm_accuracy())
        return result, data, board, lens0

    def _fit_images(self, rows: list[dict], params: HandEyeParams) -> FitOutcome:
        result, data, board, lens0 = self._fit_core(rows, params)
        cal, ver = data.views["cal"], data.views["ver"]
        pairs = chain_pairs(cal, board, lens0)
        baselines = he.opencv_baselines([v.T_base_flange for v in cal], [p for p in pairs], params.mount)
        verification = verify_views(result, ver, board, params.mount)
        compared = {name: verify_pairs_of(b, ver, board, lens0, params.mount) for name, b in baselines.items()}
        model = self._model(result, params)
        model["board_scale"] = result.board_scale
        stats = {"calibration": {"n_poses": len(cal), "n_corners": int(sum(len(v.ids) for v in cal)),
                                 "rms_px": result.rms_px},
                 "verification": verification["stats"],
                 "opencv": {name: {"hand_eye": None if b["X"] is None else he.pose_to_dict(b["X"]),
                                   "world": None if b["Y"] is None else he.pose_to_dict(b["Y"]),
                                   "error": b["error"], "verification": compared[name]}
                            for name, b in baselines.items()}}
        tables = [self._result_table(result), per_pose_table(result, verification),
                  opencv_table(baselines, compared, verification["stats"])]
        if data.touches:
            stats["touch"] = {"n_touches": len(data.touches)}
            tables.append(touch_table(data.touches))
        rejected = data.refused + result.rejected
        fitted = verify_views(result, cal, board, params.mount)["plot"]  # the calibration views' own residuals
        plot = {"image_size": list(data.size), **verification["plot"]}
        if fitted:
            plot.update(cal_uv=fitted["ver_uv"], cal_err=fitted["ver_err"])
        return FitOutcome(model, stats, rejected, plot, tables, summary=self._summary(result, verification["stats"]))

    def _fit_pairs(self, rows: list[dict], params: HandEyeParams) -> FitOutcome:
        pairs = samples_.pose_pairs(rows)
        result = he.fit_pose_pairs(pairs.flange["cal"], pairs.target["cal"], params.mount, loss=params.loss,
                                   arm_accuracy=params.arm_accuracy())
        baselines = he.opencv_baselines(pairs.flange["cal"], pairs.target["cal"], params.mount)
        ver = {"n_poses": len(pairs.flange["ver"])}
        errors = [pair_error(result.X, result.Y, F, C, params.mount, result.board_scale)
                  for F, C in zip(pairs.flange["ver"], pairs.target["ver"])]
        if errors:
            t, r = np.array(errors).T
            ver.update(translation_mean_mm=float(np.mean(t) * 1e3), translation_max_mm=float(np.max(t) * 1e3),
                       rotation_mean_deg=float(np.degrees(np.mean(r))), rotation_max_deg=float(np.degrees(np.max(r))))
        stats = {"calibration": {"n_poses": len(pairs.flange["cal"])}, "verification": ver,
                 "opencv": {name: {"hand_eye": None if b["X"] is None else he.pose_to_dict(b["X"]),
                                   "world": None if b["Y"] is None else he.pose_to_dict(b["Y"]), "error": b["error"]}
                            for name, b in baselines.items()}}
        model = dict(self._model(result, params), board_scale=result.board_scale)
        return FitOutcome(model, stats, result.rejected, {}, [self._result_table(result)],
                          summary=self._summary(result, ver))

    def _model(self, result: he.HandEyeResult, params: HandEyeParams) -> dict:
        model = {"kind": "hand-eye", "mount": params.mount, "camera": params.camera,
                 "hand_eye": he.pose_to_dict(result.X), "world": he.pose_to_dict(result.Y),
                 "hand_eye_sigma": {"translation_mm": [float(v * 1e3) for v in result.sigma_X_translation_m],
                                    "rotation_deg": [float(math.degrees(v)) for v in result.sigma_X_rotation_rad]},
                 "world_sigma": {"translation_mm": [float(v * 1e3) for v in result.sigma_Y_translation_m],
                                 "rotation_deg": [float(math.degrees(v)) for v in result.sigma_Y_rotation_rad]},
                 "hand_eye_bound95": {"translation_mm": float(result.bound95_X_translation_m * 1e3),
                                      "rotation_deg": float(math.degrees(result.bound95_X_rotation_rad))},
                 "board": {"squares": list(params.squares), "square_mm": params.square_mm,
                           "marker_mm": params.marker_mm, "dictionary": params.dictionary,
                           "first_marker": params.first_marker}}
        # for locating with it: the covariance of X, Y, [intrinsics, board scale] (the fit's parameters, rad and m),
        # and the arm's accuracy that the fit's sigmas add to X and Y
        model["covariance"] = {"names": list(result.parameter_names), "matrix": np.asarray(result.covariance).tolist()}
        model["arm_accuracy"] = {"mm": params.arm_accuracy_mm, "deg": params.arm_accuracy_deg}
        # the same as matrices (m), which the OpenCV YAML export writes as FileStorage matrices
        model["matrices"] = {"hand_eye_4x4_m": result.X.tolist(), "world_4x4_m": result.Y.tolist()}
        if result.intrinsics is not None:
            model["intrinsics"] = result.intrinsics.to_dict()
            model["matrices"].update(camera_matrix=result.intrinsics.K().tolist(),
                                     distortion_coefficients=list(result.intrinsics.dist))
        return model

    @staticmethod
    def _summary(result: he.HandEyeResult, verification: dict) -> dict:
        return {"hand_eye_sigma_mm": float(np.linalg.norm(result.sigma_X_translation_m) * 1e3),
                "hand_eye_bound95_mm": float(result.bound95_X_translation_m * 1e3),
                **{k: v for k, v in verification.items() if k.endswith(("_mm", "_px"))}}

    def _result_table(self, result: he.HandEyeResult) -> dict:
        names = (("X", "flange->camera", "base->board") if result.mount == "eye-in-hand"
                 else ("X", "flange->board", "base->camera"))
        rows = []
        for label, T, st, sr in ((f"X ({names[1]})", result.X, result.sigma_X_translation_m, result.sigma_X_rotation_rad),
                                 (f"Y ({names[2]})", result.Y, result.sigma_Y_translation_m, result.sigma_Y_rotation_rad)):
            d = he.pose_to_dict(T)
            rows.append([label, *(round(d[k], 4) for k in ("x_mm", "y_mm", "z_mm")),
                         *(round(d[k], 6) for k in ("qw", "qx", "qy", "qz")),
                         ", ".join(f"{v * 1e3:.3f}" for v in st), ", ".join(f"{math.degrees(v):.4f}" for v in sr)])
        return {"title": "Hand-eye result (1-sigma from the covariance scaled by the residuals)",
                "columns": ["transform", "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz", "sigma_xyz_mm",
                            "sigma_rot_deg"],
                "rows": rows,
                "note": f"95 % bound of X: {result.bound95_X_translation_m * 1e3:.3f} mm, "
                        f"{math.degrees(result.bound95_X_rotation_rad):.4f} deg"
                        f"; board printed at {result.board_scale:.5f} of its drawing"}


TOOL_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # the flange's axis down, as at home


def visit(step: Step, camera: str, devices: Devices):
    """A pose step's move (to its joints) and frame: (its row so far: the joints and the flange pose the arm reports,
    the frame's id and size; the frame)."""
    a = step.args
    devices.arm.move_joints(JointState(tuple(float(v) for v in a["joints"])))
    reported = he.pose_to_dict(flange_matrix(devices.arm.pose()))
    joints = np.degrees(devices.arm.joints().positions)
    frame = devices.camera(camera).capture()
    h, w = frame.image.shape[:2]
    row = {"step": step.index, "pose": a["pose"], "set": a["set"], "camera": camera, "frame_id": frame.frame_id,
           "width_px": w, "height_px": h, **{c: float(v) for c, v in zip(samples_.JOINT_COLUMNS, joints)},
           **{f"flange_{k}": v for k, v in reported.items()}}
    return row, frame


def flange_target(R: np.ndarray, position) -> Pose:
    return Pose(*(float(v) for v in position), orientation=quaternion_wxyz(Rotation.from_matrix(R)))


def flange_matrix(pose) -> np.ndarray:
    T = np.eye(4)
    w, x, y, z = pose.orientation
    T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    T[:3, 3] = (pose.x, pose.y, pose.z)
    return T


def first_intrinsics(views: list[he.View], board: he.Board, size) -> he.Intrinsics:
    """The usual first estimate: OpenCV's calibrateCamera on the calibration views' corners."""
    objects = [board.corners[v.ids].astype(np.float32) for v in views]
    images = [v.uv.astype(np.float32) for v in views]
    _, K, dist, _, _ = cv2.calibrateCamera(objects, images, tuple(size), None, None)
    d = np.zeros(5)
    d[:min(5, dist.size)] = dist.ravel()[:5]
    return he.Intrinsics(*size, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), tuple(float(v) for v in d))


def chain_pairs(views: list[he.View], board: he.Board, lens: he.Intrinsics) -> list[np.ndarray]:
    """T_camera_board of each view by PnP with the first intrinsics: the usual chain's second link."""
    out = []
    for v in views:
        ok, rvec, tvec = cv2.solvePnP(board.corners[v.ids], v.uv, lens.K(), np.asarray(lens.dist))
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        out.append(T)
    return out


def camera_from_board(X, Y, T_base_flange, mount: str) -> np.ndarray:
    """T_camera_board the model predicts at a flange pose."""
    if mount == "eye-in-hand":
        return np.linalg.inv(T_base_flange @ X) @ Y
    return np.linalg.inv(Y) @ T_base_flange @ X


def pair_error(X, Y, T_base_flange, T_camera_board, mount: str, board_scale: float = 1.0) -> tuple[float, float]:
    """How far a measured camera->board pose (with the board's drawing: its distance 1/board_scale short) is from
    the model's."""
    measured = T_camera_board.copy()
    measured[:3, 3] *= board_scale
    return he.transform_error(camera_from_board(X, Y, T_base_flange, mount), measured)


def project(lens: he.Intrinsics, T_camera_board, points) -> np.ndarray:
    rvec = cv2.Rodrigues(T_camera_board[:3, :3])[0]
    return cv2.projectPoints(points, rvec, T_camera_board[:3, 3], lens.K(), np.asarray(lens.dist))[0].reshape(-1, 2)


def verify_views(result: he.HandEyeResult, views: list[he.View], board: he.Board, mount: str) -> dict:
    """Held-out views: the reprojection error of their corners, and each corner in the base frame as the model
    predicts it against where the view measures it (PnP with the fitted lens, through the reported flange)."""
    lens, s = result.intrinsics, result.board_scale
    px, mm, per_pose, ver_uv, ver_err = [], [], [], [], []
    for v in views:
        points = board.corners[v.ids] * s
        T_cb = camera_from_board(result.X, result.Y, v.T_base_flange, mount)
        predicted = project(lens, T_cb, points)
        err = v.uv - predicted
        ok, rvec, tvec = cv2.solvePnP(points, v.uv, lens.K(), np.asarray(lens.dist))
        T_measured = np.eye(4)
        T_measured[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_measured[:3, 3] = tvec.ravel()
        if mount == "eye-in-hand":
            seen = (v.T_base_flange @ result.X @ T_measured)
            model = result.Y
        else:
            seen = result.Y @ T_measured
            model = v.T_base_flange @ result.X
        dist = np.linalg.norm((points @ seen[:3, :3].T + seen[:3, 3]) - (points @ model[:3, :3].T + model[:3, 3]), axis=1)
        px.append(np.linalg.norm(err, axis=1))
        mm.append(dist * 1e3)
        per_pose.append({"pose": v.pose, "n": len(v.ids), "rms_px": float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))),
                         "corner_mean_mm": float(np.mean(dist) * 1e3)})
        ver_uv.append(v.uv)
        ver_err.append(err)
    if not views:
        return {"stats": {"n_poses": 0}, "per_pose": [], "plot": {}}
    px_all, mm_all = np.concatenate(px), np.concatenate(mm)
    stats = {"n_poses": len(views), "n_corners": int(px_all.size),
             "rms_px": float(np.sqrt(np.mean(px_all ** 2))), "max_px": float(px_all.max()),
             "corner_mean_mm": float(mm_all.mean()), "corner_max_mm": float(mm_all.max())}
    return {"stats": stats, "per_pose": per_pose,
            "plot": {"ver_uv": np.concatenate(ver_uv).tolist(), "ver_err": np.concatenate(ver_err).tolist()}}


def verify_pairs_of(baseline: dict, views: list[he.View], board: he.Board, lens: he.Intrinsics, mount: str) -> dict:
    """A closed-form method's X, Y judged like the fit's, on the held-out views (corners in the base frame, with
    the chain's own first intrinsics and the nominal board)."""
    if baseline["X"] is None or not views:
        return {}
    result = he.HandEyeResult.__new__(he.HandEyeResult)
    result.X, result.Y, result.intrinsics, result.board_scale = baseline["X"], baseline["Y"], lens, 1.0
    return verify_views(result, views, board, mount)["stats"]


def per_pose_table(result: he.HandEyeResult, verification: dict) -> dict:
    rows = [[p["pose"], "cal", p.get("n"), round(p["rms_px"], 3) if p.get("rms_px") is not None else None, None,
             "yes" if p.get("inlier", True) else "no"] for p in result.per_view]
    rows += [[p["pose"], "ver", p["n"], round(p["rms_px"], 3), round(p["corner_mean_mm"], 3), "held out"]
             for p in verification["per_pose"]]
    return {"title": "Per pose", "columns": ["pose", "set", "corners", "rms_px", "corner_mean_mm", "used"],
            "rows": rows, "note": "corner_mean_mm: the board's corners in the base frame, predicted by the model "
                                  "against measured by that held-out view"}


def touch_table(touches: list[dict]) -> dict:
    rows = [[t["pose"], t["corner_id"], *(round(t[c], 3) for c in samples_.TOUCH_COLUMNS), t["message"]]
            for t in touches]
    return {"title": "Touch test: the tool tip brought onto corners that held-out views located",
            "columns": ["touch", "corner", *samples_.TOUCH_COLUMNS, "note"], "rows": rows,
            "note": "where the tip was sent (base frame); how far it landed from the corner is seen at the cell "
                    "(in simulation: truth.touch_mean_mm)"}


def opencv_table(baselines: dict, compared: dict, ours: dict) -> dict:
    rows = [["cellctl (simultaneous)", ours.get("corner_mean_mm"), ours.get("corner_max_mm"), ours.get("rms_px"), ""]]
    for name, b in baselines.items():
        c = compared.get(name) or {}
        rows.append([f"OpenCV {name}", c.get("corner_mean_mm"), c.get("corner_max_mm"), c.get("rms_px"),
                     b["error"] or ""])
    return {"title": "Against OpenCV's closed-form methods on the same samples (held-out poses)",
            "columns": ["method", "corner_mean_mm", "corner_max_mm", "rms_px", "error"],
            "rows": [[r[0], *(None if v is None else round(float(v), 4) for v in r[1:4]), r[4]] for r in rows],
            "note": "OpenCV's methods are fed the usual chain: calibrateCamera, then PnP per view, then AX = XB"}


