"""The arm's own geometry, calibrated by its wrist camera: kinematic identification (issue 28).

Plan: many arm configurations that show the wrist camera the table board (_arm_poses.py), chosen greedily to
identify the arm's deviations from its published table (D-optimal over the deviations the views can identify),
reachable, clear of the table, checked before anything moves; held-out verification poses are the candidates
farthest in joint space from those. Collect: at each pose the joints the arm reports and the ChArUco corners (as
`hand-eye` collects them). Fit (models/arm_kinematics.py): a hand-eye fit with the nominal table first (the "before"
model: what a hand-eye calibration alone gives), then the simultaneous adjustment of the identifiable deviations
with X, Y and the lens; the deviations the views cannot identify are fixed at nominal and named. Beside it, the usual
chain (cameras first, then the arm) on the same samples. Verify on the held-out views: the camera pose each image
measures against what each model predicts.

The board's print is the length reference (a camera sees angles only): give its measured scale (`board_scale`, the
measured length over the drawn one) when it was measured, else the drawing's, with `board_scale_sigma_pct`.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from geometry.charuco import DICTIONARIES, BoardDrawing
from geometry.kinematic_table import KinematicTable, nominal_table

from calibration.errors import CalibrationInputError, VisionError
from calibration.models import arm_kinematics as ak
from calibration.models import hand_eye as he
from calibration.routines.base import Devices, FitOutcome, NewVersion, Step, StepResult
from calibration.routines.six_axis import _arm_poses as poses_
from calibration.routines.six_axis import _arm_stereo as stereo_
from calibration.routines.six_axis import _samples as samples_
from calibration.routines.six_axis.hand_eye import (
    DEFAULT_IMAGE,
    HandEye,
    HandEyeParams,
    first_intrinsics,
    visit,
)
from calibration.vision.charuco import board_pose, find_corners

Triple = tuple[float, float, float]


class ArmKinematicsParams(stereo_.StereoParams):
    observe: Literal["wrist-board", "fixed-cameras"] = Field("wrist-board", description="wrist-board: the wrist "
                                                             "camera watches a board on the table; fixed-cameras: "
                                                             "fixed cameras watch the fixture's circles on the flange "
                                                             "(_arm_stereo.py, its parameters from StereoParams)")
    camera: str = Field("wrist", description="the wrist camera that watches the board")
    arm_model: str = Field("ur5e", description="the arm's published table (geometry/kinematic_table.py): ur5e")
    poses: int = Field(40, ge=8, le=300, description="calibration poses")
    verify_poses: int = Field(8, ge=0, le=100, description="held-out poses the fit never sees")
    candidates: int = Field(400, ge=20, le=5000, description="reachable poses showing the board, planned from")
    # the board's drawing and where it lies, roughly
    squares: tuple[int, int] = Field((12, 9), description="board: chessboard squares (x, y)")
    square_mm: float = Field(20.0, gt=0, le=500, description="board: square size as drawn")
    marker_mm: float = Field(15.0, gt=0, le=500, description="board: marker size as drawn")
    dictionary: Literal[DICTIONARIES] = Field("DICT_5X5_250", description="board: ArUco dictionary")
    first_marker: int = Field(0, ge=0, le=249, description="board: id of its first marker")
    board_scale: float = Field(1.0, gt=0.9, lt=1.1, description="the print's measured size over its drawing (the "
                               "length reference of the whole calibration: measure it if you can)")
    board_scale_sigma_pct: float = Field(0.03, gt=0, le=5, description="1-sigma of board_scale, %")
    board_mm: Triple = Field((-620.0, -40.0, 0.0), description="the board's origin corner, roughly (base frame)")
    board_rotation_deg: Triple = Field((180.0, 0.0, 0.0), description="its orientation, roughly (xyz Euler; "
                                       "180, 0, 0: the print faces up)")
    # the region of views
    target_mm: Triple = Field((-500.0, -130.0, 0.0), description="the board's rough centre (base frame)")
    standoff_mm: tuple[float, float] = Field((280.0, 550.0), description="camera to board distance, min and max")
    radius_mm: float = Field(60.0, ge=0, le=500, description="spread of the aim point about target_mm")
    tilt_deg: float = Field(40.0, ge=0, le=70, description="views tilted up to this from the board's normal")
    mount_mm: Triple = Field((0.0, 50.0, 65.0), description="the camera on the flange, roughly (flange frame)")
    focal_mm: float = Field(8.0, gt=0, le=500, description="the lens (planning and the first guess)")
    pixel_um: float = Field(3.45, gt=0, le=50, description="the sensor's pixel pitch")
    home_deg: tuple[float, float, float, float, float, float] = Field((0.0, -90.0, 90.0, -90.0, -90.0, 0.0))
    reach_mm: float = Field(850.0, gt=0, le=3000, description="the wrist stays within this of the shoulder")
    min_corners: int = Field(12, ge=6, le=1000, description="frames with fewer corners are refused")
    plan_seed: int = Field(0, ge=0, description="draws the candidate poses")
    loss: Literal["linear", "soft_l1", "huber"] = Field("soft_l1", description="robust loss of the fit")

    def drawing(self) -> BoardDrawing:
        return BoardDrawing(tuple(self.squares), self.square_mm * 1e-3, self.marker_mm * 1e-3, self.dictionary,
                            self.first_marker)


class ArmKinematics:
    name: ClassVar[str] = "arm-kinematics"
    truth: ClassVar[str | None] = "cellctl.truth.arm_stereo:arm_kinematics_truth"  # either observation
    Params: ClassVar[type[ArmKinematicsParams]] = ArmKinematicsParams
    sample_columns: ClassVar[tuple[str, ...]] = samples_.SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = samples_.SAMPLE_COLUMNS
    small_params: ClassVar[dict] = {"poses": 24, "verify_poses": 3, "candidates": 200}

    def inputs(self, params, devices: Devices) -> list[str]:
        return []

    def output(self, params, devices: Devices) -> str | None:
        return "arm"

    # -- plan ------------------------------------------------------------------
    def _region(self, params: ArmKinematicsParams, image_size) -> poses_.ArmRegion:
        X = np.eye(4)
        X[:3, 3] = np.asarray(params.mount_mm) * 1e-3
        Y = np.eye(4)
        Y[:3, :3] = Rotation.from_euler("xyz", params.board_rotation_deg, degrees=True).as_matrix()
        Y[:3, 3] = np.asarray(params.board_mm) * 1e-3
        lo, hi = sorted(params.standoff_mm)
        return poses_.ArmRegion(np.asarray(params.target_mm) * 1e-3, (lo * 1e-3, hi * 1e-3), params.radius_mm * 1e-3,
                                math.radians(params.tilt_deg), X, Y, params.focal_mm / (params.pixel_um * 1e-3),
                                tuple(image_size), params.drawing().corners(), np.radians(params.home_deg))

    def pose_plan(self, params: ArmKinematicsParams, image_size) -> dict:
        """The chosen poses (joints), the held-out ones, and what the plan can identify; or the reason not."""
        table = _table(params)
        region = self._region(params, image_size)
        cands = poses_.candidates(region, table, params.candidates, params.plan_seed, params.reach_mm * 1e-3)
        poses_.check_enough(cands, params.poses + params.verify_poses)
        # chosen for the deviations a camera can identify at all: the others' near-null directions would only
        # attract the choice
        structural = self._structural(params, image_size)
        names = table.parameter_names()
        free = np.array([n not in structural for n in names])
        J = poses_.pose_jacobians(cands, table, region, free)
        chosen = poses_.choose(J, params.poses)
        seen = _plan_observability(J[chosen], table, free=free)
        seen["fixed"] = sorted(set(seen["fixed"]) | structural, key=names.index)
        Q = np.array([cands[i].joints for i in chosen])
        # refused only when a deviation is far from identifiable (the fit decides again from the corners themselves)
        _refuse_unidentifiable(_plan_observability(J[chosen], table, ak.OBSERVABLE_RATIO / 10, free), structural, Q,
                               table)
        held = poses_.farthest(cands, chosen, params.verify_poses)
        order = poses_.tour(cands, chosen, region.home)
        ver_order = poses_.tour(cands, held, cands[order[-1]].joints) if held else []
        return {"cal": [cands[i].joints for i in order], "ver": [cands[i].joints for i in ver_order],
                "identified": seen["identified"], "fixed": seen["fixed"], "o1": seen["o1"],
                "joint_spread_deg": np.degrees(Q.max(axis=0) - Q.min(axis=0)).tolist(), "table": table}

    def _structural(self, params: ArmKinematicsParams, image_size) -> frozenset[str]:
        """The deviations no camera view of the board can identify on this arm (what a wide default region
        leaves fixed): the plan may leave these, and no others."""
        wide = ArmKinematicsParams(arm_model=params.arm_model, camera=params.camera)
        key = (params.arm_model, tuple(image_size))
        if key not in _STRUCTURAL:
            table = _table(wide)
            region = self._region(wide, image_size)
            cands = poses_.candidates(region, table, wide.candidates, 0, wide.reach_mm * 1e-3)
            J = poses_.pose_jacobians(cands, table, region, np.ones(len(table.vector()), dtype=bool))
            _STRUCTURAL[key] = frozenset(_plan_observability(J, table)["fixed"])
        return _STRUCTURAL[key]

    def preview(self, params: ArmKinematicsParams, image_size) -> list[dict]:
        if params.observe == "fixed-cameras":
            return stereo_.preview(params, image_size)
        plan = self.pose_plan(params, image_size or DEFAULT_IMAGE)
        rows = [[f"cal{i + 1}", *[round(float(v), 2) for v in np.degrees(q)]] for i, q in enumerate(plan["cal"])]
        rows += [[f"ver{i + 1}", *[round(float(v), 2) for v in np.degrees(q)]] for i, q in enumerate(plan["ver"])]
        spread = ", ".join(f"{v:.0f}" for v in plan["joint_spread_deg"])
        return [{"title": "Planned arm configurations", "columns": ["pose", *samples_.JOINT_COLUMNS], "rows": rows,
                 "note": (f"{len(plan['cal'])} calibration and {len(plan['ver'])} held-out poses; joint spread "
                          f"(deg) {spread}; identifies {len(plan['identified'])} deviations "
                          f"(observability O1 {plan['o1']:.3g}); fixed at nominal: {', '.join(plan['fixed'])}")}]

    def plan(self, params: ArmKinematicsParams, devices: Devices) -> list[Step]:
        if params.observe == "fixed-cameras":
            return stereo_.plan(params, devices)
        camera = devices.camera(params.camera)
        size = tuple(getattr(camera, "resolution", None) or DEFAULT_IMAGE)
        plan = self.pose_plan(params, size)
        steps = [(f"cal{i + 1}", "cal", q) for i, q in enumerate(plan["cal"])]
        steps += [(f"ver{i + 1}", "ver", q) for i, q in enumerate(plan["ver"])]
        return [Step(i, "pose", {"pose": name, "set": s, "joints": [float(v) for v in q]})
                for i, (name, s, q) in enumerate(steps)]

    # -- collect ---------------------------------------------------------------
    def execute(self, step: Step, params: ArmKinematicsParams, devices: Devices, history=()) -> StepResult:
        if params.observe == "fixed-cameras":
            return stereo_.execute(step, params, devices)
        row, frame = visit(step, params.camera, devices)
        h, w = frame.image.shape[:2]
        f = params.focal_mm / (params.pixel_um * 1e-3)
        K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
        drawing = params.drawing()
        try:
            corners = find_corners(frame.image, drawing, params.min_corners)
            board_pose(corners, drawing, K, np.zeros(5))  # refuses an ambiguous view
        except VisionError as exc:
            return StepResult(dict(row, status="refused", message=str(exc)), [frame])
        return StepResult([dict(row, status="ok", corner_id=int(i), u_px=float(u), v_px=float(v), message="")
                           for i, (u, v) in zip(corners.ids, corners.uv)], [frame])

    # -- fit ---------------------------------------------------------------------
    def fit(self, samples: list[dict], params: ArmKinematicsParams, resolutions=None) -> FitOutcome:
        if params.observe == "fixed-cameras":
            return stereo_.fit(samples, params, resolutions)
        views, size, refused = _views(samples)
        cal, ver = views["cal"], views["ver"]
        nominal = _table(params)
        board = he.Board(params.drawing().corners() * params.board_scale)
        hand_eye_views = ak.views_of(cal, nominal)
        lens0 = first_intrinsics(hand_eye_views, board, size)
        before = he.fit_views(hand_eye_views, board, "eye-in-hand", lens0, loss=params.loss)
        result = ak.fit(cal, board, before.intrinsics, nominal, before.X, before.Y, loss=params.loss,
                        scale_sigma=params.board_scale_sigma_pct / 100)
        # two usual chains, the arm fitted after the camera: the camera calibrated on its own (OpenCV's
        # calibrateCamera on the same views), or with the nominal arm (the hand-eye fit, as a cell would do it)
        free = result.observability["free_mask"]
        seq_table, seq_X, seq_Y = ak.sequential(cal, board, lens0, nominal, before.X, before.Y, free)
        he_table, he_X, he_Y = ak.sequential(cal, board, before.intrinsics, nominal, before.X, before.Y, free)
        models = {"before": (before.intrinsics, nominal, before.X, before.Y, before.board_scale),
                  "after": (result.intrinsics, result.table, result.X, result.Y, result.board_scale),
                  "sequential": (lens0, seq_table, seq_X, seq_Y, 1.0),
                  "sequential_hand_eye": (before.intrinsics, he_table, he_X, he_Y, 1.0)}
        verification, series = {}, {}
        centre = board.corners.mean(axis=0)
        distance = [float(np.linalg.norm((he._inv(result.Y) @ result.table.forward(v.joints) @ result.X)[:3, 3]
                                         - centre) * 1e3) for v in ver]
        for name, (lens, table, X, Y, scale) in models.items():
            errors = ak.camera_errors(ver, board, lens, table, X, Y, scale) if ver else np.zeros((0, 2))
            verification[name] = _error_stats(errors)
            series[name] = sorted([d, float(e * 1e3)] for d, e in zip(distance, errors[:, 0]))
        model = {"kind": "arm-kinematics", "arm_model": params.arm_model, "table": result.table.to_dict(),
                 "nominal": nominal.to_dict(), "tool": he.pose_to_dict(result.X), "tool_frame": "camera",
                 # the controller's pose is the flange (zero TCP offset), and so is the calibrated arm's
                 "tcp": he.pose_to_dict(np.eye(4)), "controller_tcp": he.pose_to_dict(np.eye(4)),
                 "camera": params.camera, "world": he.pose_to_dict(result.Y),
                 "intrinsics": result.intrinsics.to_dict(), "board_scale": result.board_scale,
                 "identified": result.identified, "fixed": result.fixed,
                 "deviations": {k: _human(k, v) for k, v in result.values.items()},
                 "sigma": {k: _human(k, v) for k, v in result.sigma.items()},
                 "before": {"tool": he.pose_to_dict(before.X), "world": he.pose_to_dict(before.Y)},
                 "sequential": {"table": seq_table.to_dict(), "tool": he.pose_to_dict(seq_X),
                                "world": he.pose_to_dict(seq_Y)},
                 "sequential_hand_eye": {"table": he_table.to_dict(), "tool": he.pose_to_dict(he_X),
                                         "world": he.pose_to_dict(he_Y)}}
        stats = {"calibration": {"n_poses": len(cal), "rms_px": result.rms_px, "noise": result.noise,
                                 "o1": result.observability["o1"], "condition": result.observability["condition"]},
                 "verification": verification}
        tables = [_parameter_table(result), _verification_table(verification)]
        if result.correlations:
            tables.append({"title": "Correlations above 0.9", "columns": ["a", "b", "r"],
                           "rows": [[a, b, round(r, 3)] for a, b, r in result.correlations]})
        summary = {"identified": len(result.identified), "rms_px": result.rms_px,
                   **{f"verify_position_{k}_mean_mm": v["position_mean_mm"] for k, v in verification.items()}}
        chart = {"name": "held_out_errors", "title": "Held-out poses: camera position error by model",
                 "x_label": "camera distance from the board's centre (mm)", "y_label": "position error (mm)",
                 "series": {LABELS[k]: series[k] for k in ("before", "sequential_hand_eye", "sequential", "after")},
                 "log_y": True}
        after = verification["after"]
        accuracy = (after["position_mean_mm"], after["orientation_mean_deg"]) if ver else (0.05, 0.005)
        camera = {f"hand-eye:{params.camera}": NewVersion(_hand_eye_model(result, params, accuracy),
                                                           {"made_by": self.name, "with_arm": "calibrated"}, None)}
        return FitOutcome(model, stats, refused, {}, tables, summary=summary, charts=[chart] if ver else [],
                          calibrations=camera)


def _hand_eye_model(result: ak.ArmResult, params: ArmKinematicsParams, accuracy: tuple[float, float]) -> dict:
    """The wrist camera's hand-eye calibration as this fit leaves it (X, Y and the lens fitted with the calibrated
    arm): a new version of `hand-eye:<camera>`, so that locate, table-pick and iso9283 use the camera consistent
    with the arm's new geometry. `accuracy` (mm, deg): the calibrated arm's, the floor of its sigma."""
    floor = (accuracy[0] * 1e-3, math.radians(accuracy[1]))
    sX, rX, sY, rY, bX, bR = he._covariance_blocks(result.camera_covariance, result.X, result.Y, floor)
    fitted = he.HandEyeResult("eye-in-hand", result.X, result.Y, result.intrinsics, result.board_scale, sX, rX, sY, rY,
                              bX, bR, result.camera_covariance, result.camera_names, result.rms_px)
    hand_eye_params = HandEyeParams(camera=params.camera, squares=params.squares, square_mm=params.square_mm,
                                    marker_mm=params.marker_mm, dictionary=params.dictionary,
                                    first_marker=params.first_marker, arm_accuracy_mm=accuracy[0],
                                    arm_accuracy_deg=accuracy[1])
    model = HandEye()._model(fitted, hand_eye_params)
    model["board_scale"] = result.board_scale * params.board_scale
    return model


def _table(params: ArmKinematicsParams) -> KinematicTable:
    try:
        return nominal_table(params.arm_model)
    except ValueError as exc:
        raise CalibrationInputError(f"arm_model: {exc}") from None


_STRUCTURAL: dict[tuple, frozenset[str]] = {}
def _refuse_unidentifiable(seen: dict, structural: frozenset[str], Q: np.ndarray, table: KinematicTable) -> None:
    """Refused when these poses leave deviations unidentified beyond the structural ones (no view identifies)."""
    poses_.refuse_unidentifiable([n for n in seen["fixed"] if n not in structural], Q, table,
                                 "tilt_deg, radius_mm or standoff_mm (views from more directions and distances)")


def _plan_observability(J: np.ndarray, table: KinematicTable, ratio: float = ak.OBSERVABLE_RATIO,
                        free: np.ndarray | None = None) -> dict:
    """What the planned poses can identify, from their pose Jacobians (X and Y projected out)."""
    names = [n for n, f in zip(table.parameter_names(), free if free is not None else [True] * J.shape[2]) if f]
    A = J.reshape(-1, J.shape[2])
    return ak.identifiable(A[:, :12], A[:, 12:], names, ratio)


def _views(rows: list[dict]) -> tuple[dict[str, list[ak.ArmView]], tuple[int, int], list[dict]]:
    by_pose: dict[str, list[dict]] = {}
    refused = []
    for r in rows:
        if r.get("status") != "ok":
            refused.append({"pose": r.get("pose"), "reason": r.get("message")})
            continue
        by_pose.setdefault(str(r["pose"]), []).append(r)
    views: dict[str, list[ak.ArmView]] = {"cal": [], "ver": []}
    size = None
    for pose, group in by_pose.items():
        first = group[0]
        joints = np.radians([float(first[c]) for c in samples_.JOINT_COLUMNS])
        ids = np.array([int(float(r["corner_id"])) for r in group])
        uv = np.array([[float(r["u_px"]), float(r["v_px"])] for r in group])
        views[first.get("set") or "cal"].append(ak.ArmView(pose, joints, ids, uv))
        size = (int(float(first["width_px"])), int(float(first["height_px"])))
    if size is None or len(views["cal"]) < 8:
        raise CalibrationInputError(f"{len(views['cal'])} calibration poses saw the board; the arm's calibration "
                                    "needs many more (the plan asks for 40)")
    return views, size, refused


def _human(name: str, value: float) -> float:
    """Lengths in mm, angles in deg."""
    return value * 1e3 if name.split("_")[0] in ("d", "a") else math.degrees(value)


def _error_stats(errors: np.ndarray) -> dict:
    if len(errors) == 0:
        return {"n": 0, "position_mean_mm": None, "position_max_mm": None, "orientation_mean_deg": None}
    return {"n": len(errors), "position_mean_mm": float(errors[:, 0].mean() * 1e3),
            "position_max_mm": float(errors[:, 0].max() * 1e3),
            "orientation_mean_deg": float(np.degrees(errors[:, 1]).mean())}


def _parameter_table(result: ak.ArmResult) -> dict:
    rows = [[name, round(_human(name, result.values[name]), 5), round(_human(name, result.sigma[name]), 5)]
            for name in result.identified]
    return {"title": "Identified deviations from the published table (mm, deg)", "columns": ["parameter", "value",
                                                                                              "sigma"],
            "rows": rows, "note": f"fixed at nominal (the views cannot tell them from X, Y or each other): "
                                  f"{', '.join(result.fixed)}"}


LABELS = {"before": "nominal arm + hand-eye", "sequential_hand_eye": "camera with the nominal arm, then the arm",
          "sequential": "camera on its own (OpenCV), then the arm", "after": "simultaneous (this calibration)"}


def _verification_table(v: dict) -> dict:
    rows = [[LABELS[k], v[k]["n"], *(None if v[k][c] is None else round(v[k][c], 4)
                                     for c in ("position_mean_mm", "position_max_mm", "orientation_mean_deg"))]
            for k in ("before", "sequential_hand_eye", "sequential", "after")]
    return {"title": "Held-out poses: the camera's pose as the image measures it against each model",
            "columns": ["model", "poses", "position mean mm", "position max mm", "orientation mean deg"], "rows": rows}
