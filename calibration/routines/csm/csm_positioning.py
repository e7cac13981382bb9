"""Camera-space manipulation: VW-CSM positioning of a six-axis arm with two uncalibrated cameras (seed 002).

The arm carries a fixture with one white and three black circles (seed Fig. 3) at known places in its
seventh DH frame; two fixed cameras, never calibrated, see it. Only the catalogue kinematics are known.

Steps (each one move and one capture per camera, persisted):

1. `survey` (one per target): the arm is put at a hidden pose; the white circle's camera-space location
   in both cameras is the target (seed section IV step 1; the joints give the error of a positioning
   in nominal kinematics, as in the seed). These 21 poses are also the data of Tables II-V.
2. `approach` (a few per target): a pre-planned trajectory of poses 90-220 mm from the target, in the
   target's orientation, sampled by both cameras (step 2).
3. `iterate` (up to `max_iterations` per target and loop): estimate the view parameters from the samples
   so far (flattening, the loop's weights), the target's 3D position (eq. 10), joints 1-3 by numerical IK
   (eq. 11); if the predicted correction is below `tolerance_mm` the loop has converged (no move, the
   remaining steps of the loop are skipped), else move there and sample (steps 3-4). A loop is
   `mode:scheme`: mode `white` (the white circle alone), `three` (the black circles as three features),
   `virtual` (their mean as one feature); scheme `equal`, `reciprocal`, `w1`..`w4` (eqs. 12-15) with the
   best k of the Table V sweep over `k_values` (computed from the survey samples, so resume is exact).

The samples and how they group into poses: _samples.py; the leave-one-out experiments and the
seed's tables the fit reports: _experiments.py.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
import pinocchio as pin
from pydantic import Field, field_validator
from scipy.spatial.transform import Rotation

from geometry.orientation import alpha_of, quaternion_wxyz

from drivers.interfaces import JointState, Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.models import csm
from calibration.models.arm_kinematics_stereo import StereoModel, stereo_point
from calibration.models.irb120 import Fixture, Kinematics
from calibration.routines.base import Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.csm._experiments import best_k, k_sweep, seed_tables
from calibration.routines.csm._samples import (
    BLACKS,
    FEATURES,
    FIT_COLUMNS,
    JOINT_COLS,
    SAMPLE_COLUMNS,
    SampleSet,
    camera_samples,
    locate,
)
from calibration.vision.csm_markers import MarkOptions, find_marks, label_fixture

MODES = ("white", "three", "virtual")
START_DEG = (0.0, 10.0, 10.0, 0.0, 70.0, 0.0)  # IK seed: elbow up, tool pointing down

Triple = tuple[float, float, float]


class CsmPositioningParams(Params):
    cameras: tuple[str, ...] = Field(("cam1", "cam2"), min_length=2, description="the cameras that see the fixture")
    d7_mm: float = Field(40.0, description="fixture drawing: DH d of the seventh frame")
    a7_mm: float = Field(0.0, description="fixture drawing: DH a of the seventh frame")
    white_mm: Triple = Field((0.0, 0.0, 0.0), description="white circle centre in frame 7")
    black_mm: tuple[Triple, Triple, Triple] = Field(((40.0, 0.0, 0.0), (55.0, 15.0, 0.0), (55.0, -15.0, 0.0)),
                                                    description="the three black circle centres in frame 7")
    distance_mm: float = Field(1200.0, gt=10, le=20000, description="roughly anticipated camera distance Z_r (eq. 9)")
    fit_depth: bool = Field(True, description="leave-one-out experiments and the survey fit: estimate Z_r with the "
                            "view parameters (the seed keeps it fixed)")
    loop_fit_depth: bool = Field(False, description="the same in the positioning loops")
    detector: Literal["contour", "dld"] = Field("contour", description="mark detector used by CSM")
    compare_detector: bool = Field(True, description="survey frames also measured by the other detector")
    n_targets: int = Field(21, ge=4, le=500, description="the view-parameter fit of the survey needs 4 poses")
    plan_seed: int = Field(0, ge=0, description="draws the hidden target poses")
    target_box_mm: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = Field(
        ((300.0, 400.0), (-80.0, 80.0), (170.0, 270.0)), description="white circle of the targets (robot frame)")
    tilt_deg: float = Field(6.0, ge=0, le=45, description="targets: +/- tilt of the tool from pointing down")
    turn_deg: float = Field(12.0, ge=0, le=180, description="targets: +/- turn about the vertical")
    approach_mm: tuple[Triple, ...] = Field(((-120.0, 90.0, 160.0), (100.0, -110.0, 130.0), (-80.0, -60.0, 90.0),
                                             (70.0, 40.0, 110.0), (50.0, 60.0, 60.0)), min_length=1,
                                            description="pre-planned approach: offsets of the white circle from the target")
    use_survey: bool = Field(False, description="loops also use the other targets' survey samples (never their own)")
    loops: tuple[str, ...] = Field(("three:equal", "three:w1", "three:w2", "three:w3", "three:w4",
                                    "white:reciprocal", "white:w4", "virtual:reciprocal"),
                                   description="positioning loops run for each target, mode:scheme (mode "
                                   "white, three or virtual; scheme equal, reciprocal or w1..w4)")
    primary: str = Field("white:w4", description="the loop whose terminal error is stats.positioning")
    k_values: tuple[float, ...] = Field((1.0, 2.0, 3.0, 4.0), min_length=1, description="k of the weights w1..w4 "
                                        "swept (Table V); each loop uses the best")
    max_iterations: int = Field(10, ge=1, le=100, description="at most this many moves per target and loop")
    open_loop: bool = Field(False, description="also move straight to each target through the active `arm` "
                            "calibration (arm-kinematics with fixed cameras): its cameras triangulate the target, "
                            "the calibrated arm goes there in one move, no camera iteration")
    tolerance_mm: float = Field(0.03, gt=0, le=100, description="stop when the predicted correction is below this")

    @field_validator("loops")
    @classmethod
    def _loops(cls, loops):
        for loop in loops:
            mode, _, scheme = loop.partition(":")
            if mode not in MODES or scheme not in csm.SCHEMES:
                raise ValueError(f"loop {loop!r}: expected mode:scheme with mode in {', '.join(MODES)} "
                                 f"and scheme in {', '.join(csm.SCHEMES)}")
        return loops

    def fixture(self) -> Fixture:
        features = {"white": tuple(v * 1e-3 for v in self.white_mm)}
        features.update({n: tuple(v * 1e-3 for v in p) for n, p in zip(BLACKS, self.black_mm)})
        return Fixture((self.d7_mm * 1e-3, self.a7_mm * 1e-3), features)


class CsmPositioning:
    name: ClassVar[str] = "csm-positioning"
    truth: ClassVar[str | None] = "cellctl.truth.csm:csm_truth"
    Params: ClassVar[type[CsmPositioningParams]] = CsmPositioningParams
    sample_columns: ClassVar[tuple[str, ...]] = SAMPLE_COLUMNS
    fit_columns: ClassVar[tuple[str, ...]] = FIT_COLUMNS

    def __init__(self):
        # one run's caches: the nominal kinematics per fixture, and the k sweep over the survey, which every
        # positioning step and the fit need (computed from the survey samples alone, so a resumed run and
        # an offline fit compute the same)
        self._kinematics: dict[tuple, Kinematics] = {}
        self._sweeps: dict[tuple, dict] = {}

    def kinematics(self, params: CsmPositioningParams) -> Kinematics:
        f = params.fixture()
        key = (f.tool, tuple(f.features.items()))
        if key not in self._kinematics:
            self._kinematics[key] = Kinematics.nominal(f)
        return self._kinematics[key]

    def k_sweep(self, data: SampleSet, params: CsmPositioningParams) -> dict[str, dict[float, float]]:
        key = (tuple((p.target, tuple(np.round(np.concatenate([p.uv[c]["white"] for c in params.cameras]), 9)))
                     for p in data.survey()), params.model_dump_json())
        if key not in self._sweeps:
            self._sweeps[key] = k_sweep(data, params, self.kinematics(params))
        return self._sweeps[key]

    def inputs(self, params, devices) -> list[str]:
        return ["arm"] if params.open_loop else []

    def output(self, params, devices) -> str | None:
        return None

    # -- plan ------------------------------------------------------------------
    def plan(self, params: CsmPositioningParams, devices: Devices) -> list[Step]:
        for cam in params.cameras:
            devices.camera(cam)  # unknown camera names fail before any motion
        if params.loops and params.primary not in params.loops:
            raise CalibrationInputError(f"primary={params.primary!r} is not one of loops ({', '.join(params.loops)})")
        if params.open_loop:
            _open_loop_model(devices.calibration("arm", self.name), params)  # refused before anything moves
        kin = self.kinematics(params)
        targets = draw_targets(params, kin)
        steps: list[tuple[str, dict]] = [("survey", {"target": t, "joints": list(q)}) for t, q in enumerate(targets)]
        for t, q in enumerate(targets):
            if params.open_loop:
                steps.append(("open-loop", {"target": t}))
            goal = kin.placement(q)
            for a, offset in enumerate(params.approach_mm):
                # the same orientation as the target, the white circle shifted by the offset
                shifted = pin.SE3(goal.rotation, goal.translation + np.asarray(offset) * 1e-3)
                qa = kin.solve_pose(shifted, q)
                if np.linalg.norm(pin.log6(kin.placement(qa).actInv(shifted)).vector) > 1e-6:
                    raise CalibrationInputError(f"approach offset {offset} mm of target {t} is out of reach")
                steps.append(("approach", {"target": t, "index": a, "joints": [float(v) for v in qa]}))
            for loop in params.loops:
                steps += [("iterate", {"target": t, "loop": loop, "iteration": i}) for i in range(params.max_iterations)]
        return [Step(i, action, args) for i, (action, args) in enumerate(steps)]

    # -- execute ---------------------------------------------------------------
    def execute(self, step: Step, params: CsmPositioningParams, devices: Devices, history=()) -> StepResult:
        a = step.args
        base = {"step": step.index, "phase": step.action, "target": a["target"]}
        if step.action in ("survey", "approach"):
            return self._visit(devices, params, np.asarray(a["joints"]), base, alt=step.action == "survey")
        if step.action == "open-loop":
            return self._open_loop(params, devices, list(history), base)
        return self._iterate(step, params, devices, list(history), base)

    def _open_loop(self, params, devices, history, base) -> StepResult:
        """The target's white circle triangulated by the arm calibration's cameras from its survey images, and the
        fixture sent there in one linear move through the calibrated arm (in force for every move of the run), in
        the survey's orientation as the calibrated arm has it; then measured like any visit."""
        t = base["target"]
        model = _open_loop_model(devices.calibration("arm", self.name), params)
        data = SampleSet.from_rows(history)
        try:
            if t not in data.by_target:
                raise CalibrationInputError(f"target {t}: its survey pose was not seen")
            white = stereo_point(model, params.cameras, data.target_uv(t, params.cameras))
        except CalibrationInputError as exc:
            return StepResult(dict(base, status="failed", message=str(exc)))
        T = model.table.forward(data.by_target[t].joints) @ model.mount  # the fixture at the survey, calibrated
        R = T[:3, :3]
        origin = white - R @ (np.asarray(params.white_mm) * 1e-3)
        rotation = Rotation.from_matrix(R)
        devices.arm.move_linear(Pose(*map(float, origin), alpha_of(rotation), quaternion_wxyz(rotation)))
        info = {f"pred_{c}_mm": float(v * 1e3) for c, v in zip("xyz", white)}
        return self._capture(devices, params, base, extra=info)

    def _visit(self, devices, params, q, base: dict, alt: bool = False, extra: dict | None = None) -> StepResult:
        devices.arm.move_joints(JointState(tuple(float(v) for v in q)))
        return self._capture(devices, params, base, alt, extra)

    def _capture(self, devices, params, base: dict, alt: bool = False, extra: dict | None = None) -> StepResult:
        reported = np.degrees(devices.arm.joints().positions)
        joints = dict(zip(JOINT_COLS, (float(v) for v in reported)))
        rows, frames = [], []
        for cam in params.cameras:
            frame = devices.camera(cam).capture()
            frames.append(frame)
            h, w = frame.image.shape[:2]
            common = dict(base, **joints, **(extra or {}), camera=cam, frame_id=frame.frame_id, width_px=w, height_px=h)
            try:
                named = measure(frame.image, params, params.detector)
            except VisionError as exc:
                rows.append(dict(common, status="no-marks", message=str(exc)))
                continue
            other = None
            if alt and params.compare_detector:
                try:
                    other = measure(frame.image, params, "dld" if params.detector == "contour" else "contour")
                except VisionError:
                    other = None
            for feat in FEATURES:
                uv = named[feat]
                alt_uv = other[feat] if other else (math.nan, math.nan)
                rows.append(dict(common, status="ok", feature=feat, u_px=float(uv[0]), v_px=float(uv[1]),
                                 u_alt_px=float(alt_uv[0]), v_alt_px=float(alt_uv[1]), message=""))
        return StepResult(rows, frames)

    def _iterate(self, step, params, devices, history, base) -> StepResult:
        a = step.args
        t, loop = a["target"], a["loop"]
        base.update(loop=loop, iteration=a["iteration"])
        done = [r for r in history if r.get("phase") == "iterate" and r.get("target") == t and r.get("loop") == loop]
        if any(r.get("status") in ("converged", "failed", "skipped") for r in done):
            return StepResult(dict(base, status="skipped", message="loop already finished"))
        data = SampleSet.from_rows(history)
        kin = self.kinematics(params)
        mode, _, scheme = loop.partition(":")
        # the best k of each VW scheme needs every target's survey
        k = best_k(self.k_sweep(data, params)).get(scheme, 1.0) if len(data.survey()) >= 5 else 1.0
        poses = data.loop_poses(t, loop, params.use_survey)
        q_start = data.last_joints(t, loop)
        try:
            if t not in data.by_target:
                raise CalibrationInputError(f"target {t}: its survey pose was not seen")
            target_uv = data.target_uv(t, params.cameras)
            est = locate(data, poses, target_uv, mode, scheme, k, params, kin, params.loop_fit_depth)
        except (CalibrationInputError, np.linalg.LinAlgError) as exc:
            return StepResult(dict(base, status="failed", message=str(exc)))
        # the seed's test set-up: joints 4-6 held at the target's, so joints 1-3 alone reach the target and
        # the error of the final pose is measurable in nominal kinematics (section IV)
        q_seed = np.concatenate([q_start[:3], data.by_target[t].joints[3:]])
        q_new = kin.solve_point("white", est.target, q_seed, active=(0, 1, 2))
        correction = float(np.linalg.norm(est.target - kin.point(q_start, "white")) * 1e3)
        info = {"k": k, "correction_mm": correction,
                **{f"pred_{c}_mm": float(v * 1e3) for c, v in zip("xyz", est.target)}}
        if correction < params.tolerance_mm:
            return StepResult(dict(base, **info, status="converged", message=""))
        return self._visit(devices, params, q_new, base, extra=info)

    # -- fit ---------------------------------------------------------------------
    def fit(self, samples: list[dict], params: CsmPositioningParams, resolutions=None) -> FitOutcome:
        """View parameters from the survey samples, and the seed's tables from everything recorded."""
        data = SampleSet.from_rows(samples)
        if params.cameras != tuple(data.cameras()) and set(params.cameras) - set(data.cameras()):
            raise CalibrationInputError(f"samples have cameras {data.cameras()}, params.cameras={list(params.cameras)}")
        kin = self.kinematics(params)
        survey = data.survey()
        if len(survey) < 4:
            raise CalibrationInputError(f"need at least 4 survey poses seen by every camera, got {len(survey)}")
        # Table III, rows 2-3: camera-space fit of all survey samples (white circle), equal weights
        cams = camera_samples(data, survey, "white", params.cameras, kin, params.distance_mm * 1e-3)
        centroid_uv = [c.uv.mean(axis=0) for c in cams]
        est = csm.estimate(cams, centroid_uv, fit_depth=params.fit_depth and len(survey) >= 10)
        model = {"kind": "csm-view-parameters", "feature": "white", "n_poses": len(survey),
                 "cameras": {c: {"C": [float(v) for v in C], "z_r_m": float(z)}
                             for c, C, z in zip(params.cameras, est.views, est.depths)}}
        sweep = self.k_sweep(data, params) if len(survey) >= 5 else None
        stats, tables, charts = seed_tables(data, samples, params, kin, est, sweep)
        rejected = [{"step": r.get("step"), "reason": r.get("message") or r.get("status")}
                    for r in samples if r.get("status") in ("no-marks", "failed")]
        opened = [p for p in data.poses if p.phase == "open-loop"]
        if opened:
            stats["open_loop"], table = _open_loop_table(data, opened, params)
            tables.append(table)
        return FitOutcome(model, stats, rejected, {}, tables, charts)


def _open_loop_table(data: SampleSet, opened, params: CsmPositioningParams) -> tuple[dict, dict]:
    """How far the white circle lands from its target in the images: one move through the calibrated arm, against
    the primary loop's last pose (its camera iterations counted)."""
    rows, errors = [], {"open loop": [], params.primary: []}
    for p in sorted(opened, key=lambda p: p.target):
        try:
            goal = data.target_uv(p.target, params.cameras)
        except CalibrationInputError:
            continue
        loop = sorted((q for q in data.poses if q.target == p.target and q.phase == "iterate" and q.loop == params.primary),
                      key=lambda q: q.step)
        row = [p.target]
        for name, pose in (("open loop", p), (params.primary, loop[-1] if loop else None)):
            seen = pose is not None and all("white" in pose.uv.get(c, {}) for c in params.cameras)
            e = (max(float(np.linalg.norm(np.asarray(pose.uv[c]["white"]) - g)) for c, g in zip(params.cameras, goal))
                 if seen else None)
            if e is not None:
                errors[name].append(e)
            row.append(None if e is None else round(e, 3))
        rows.append(row + [len(loop)])
    stats = {name: {"n": len(e), "mean_px": float(np.mean(e)) if e else None} for name, e in errors.items()}
    return stats, {"title": "Open loop through the calibrated arm against CSM (white circle, worst camera, px)",
                   "columns": ["target", "open loop px", f"{params.primary} px", f"{params.primary} moves"],
                   "rows": rows, "note": "the open loop makes one move and no camera iteration; in simulation "
                                         "truth.open_loop_physical is its error in mm"}


def _open_loop_model(model: dict, params: CsmPositioningParams) -> StereoModel:
    """The active arm calibration as open-loop positioning needs it: one from fixed cameras that include these."""
    if model.get("observe") != "fixed-cameras" or not set(params.cameras) <= set(model.get("cameras", {})):
        raise CalibrationInputError(f"open_loop needs an active arm calibration made by arm-kinematics with fixed "
                                    f"cameras {', '.join(params.cameras)} (observe: fixed-cameras); the active one "
                                    f"has cameras {', '.join(model.get('cameras', {})) or 'none'}")
    return StereoModel.from_dict(model)


def draw_targets(params: CsmPositioningParams, kin: Kinematics) -> list[np.ndarray]:
    """Hidden target poses: the white circle in the box, the tool pointing down within tilt and turn."""
    rng = np.random.default_rng(params.plan_seed)
    box = np.asarray(params.target_box_mm) * 1e-3
    start = np.radians(START_DEG)
    targets = []
    offset = np.asarray(params.white_mm) * 1e-3
    for _ in range(params.n_targets * 50):
        if len(targets) == params.n_targets:
            break
        R = (Rotation.from_euler("z", math.radians(rng.uniform(-params.turn_deg, params.turn_deg)))
             * Rotation.from_rotvec(np.r_[np.radians(rng.uniform(-params.tilt_deg, params.tilt_deg, 2)), 0.0])
             * Rotation.from_euler("x", math.pi)).as_matrix()
        white = rng.uniform(box[:, 0], box[:, 1])
        goal = pin.SE3(R, white - R @ offset)  # fixture frame placing the white circle at `white`
        q = kin.solve_pose(goal, start)
        if np.linalg.norm(pin.log6(kin.placement(q).actInv(goal)).vector) < 1e-8 and kin.within_limits(q):
            targets.append(q)
    if len(targets) < params.n_targets:
        raise CalibrationInputError("target_box_mm / tilt_deg: too few reachable target poses")
    return targets


def measure(image, params: CsmPositioningParams, method: str) -> dict[str, np.ndarray]:
    marks = find_marks(image, method, MarkOptions())
    return label_fixture(marks, np.asarray(params.white_mm[:2]), np.asarray([b[:2] for b in params.black_mm]))
