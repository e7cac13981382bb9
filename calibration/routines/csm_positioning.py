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

Samples CSV (one row per camera and feature; `fit` needs only these columns, the rest is bookkeeping):
  step      step index; rows of one step are one pose (offline files without it: one pose per distinct joints)
  phase     survey | approach | iterate (default survey)
  target    target index (survey and the loops of that target)
  loop      `mode:scheme` of an iterate row
  iteration iteration index within its loop
  status    ok | no-marks | converged | skipped | failed (only ok rows carry a sample)
  camera    camera name; feature: white | black1 | black2 | black3 (default white)
  u_px, v_px            the mark's centre by the chosen detector; u_alt_px, v_alt_px: the other detector
  width_px, height_px   image size (flattening scales about the image centre)
  j1_deg .. j6_deg      joints reported by the controller
  k, correction_mm, pred_x_mm, pred_y_mm, pred_z_mm   the loop's estimate behind the move
"""

from __future__ import annotations

import functools
import math
from typing import ClassVar, Literal

import numpy as np
import pinocchio as pin
from pydantic import Field, field_validator
from scipy.spatial.transform import Rotation

from drivers.interfaces import JointState

from ..errors import CalibrationInputError, VisionError
from ..models import csm
from ..models.irb120 import Fixture, Kinematics
from ..vision.csm_markers import MarkOptions, find_marks, label_fixture
from .base import Devices, FitOutcome, Params, Step, StepResult

FEATURES = ("white", "black1", "black2", "black3")
BLACKS = FEATURES[1:]
MODES = ("white", "three", "virtual")
VW_SCHEMES = ("w1", "w2", "w3", "w4")
JOINT_COLS = tuple(f"j{i}_deg" for i in range(1, 7))
START_DEG = (0.0, 10.0, 10.0, 0.0, 70.0, 0.0)  # IK seed: elbow up, tool pointing down

# the seed's numbers, shown beside ours
SEED_TABLE_III = {"cam1": (0.065, 0.069, 0.106), "cam2": (0.081, 0.093, 0.137),
                  "white": (0.07, 0.29, 0.15, 0.33), "virtual": (0.12, 0.34, 0.13, 0.36)}
SEED_TABLE_II_MEAN, SEED_TABLE_IV_MEAN = 0.2989, 0.3541
SEED_TABLE_V = {"equal": 0.4691, "w1": 0.2303, "w2": 0.2572, "w3": 0.2206, "w4": 0.2203}
SEED_TABLE_VI = {"equal": 12, "w1": 7, "w2": 8, "w3": 5, "w4": 4}

Triple = tuple[float, float, float]


class CsmPositioningParams(Params):
    cameras: tuple[str, ...] = Field(("cam1", "cam2"), min_length=2, description="the cameras that see the fixture")
    d7_mm: float = Field(40.0, description="fixture drawing: DH d of the seventh frame")
    a7_mm: float = Field(0.0, description="fixture drawing: DH a of the seventh frame")
    white_mm: Triple = Field((0.0, 0.0, 0.0), description="white circle centre in frame 7")
    black_mm: tuple[Triple, Triple, Triple] = ((40.0, 0.0, 0.0), (55.0, 15.0, 0.0), (55.0, -15.0, 0.0))
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
    loops: tuple[str, ...] = ("three:equal", "three:w1", "three:w2", "three:w3", "three:w4",
                              "white:reciprocal", "white:w4", "virtual:reciprocal")
    primary: str = Field("white:w4", description="the loop whose terminal error is stats.positioning")
    k_values: tuple[float, ...] = Field((1.0, 2.0, 3.0, 4.0), min_length=1)
    max_iterations: int = Field(10, ge=1, le=100)
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


@functools.lru_cache(maxsize=8)
def _kinematics(fixture_key: tuple) -> Kinematics:
    tool, features = fixture_key
    return Kinematics.nominal(Fixture(tool, dict(features)))


def kinematics(params: CsmPositioningParams) -> Kinematics:
    f = params.fixture()
    return _kinematics((f.tool, tuple(f.features.items())))


class CsmPositioning:
    name: ClassVar[str] = "csm-positioning"
    Params: ClassVar[type[CsmPositioningParams]] = CsmPositioningParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "phase", "target", "loop", "iteration", "status", "camera", "feature", "frame_id",
        "u_px", "v_px", "u_alt_px", "v_alt_px", "width_px", "height_px", *JOINT_COLS,
        "k", "correction_mm", "pred_x_mm", "pred_y_mm", "pred_z_mm", "message",
    )
    fit_columns: ClassVar[tuple[str, ...]] = ("camera", "u_px", "v_px", *JOINT_COLS)

    def inputs(self, params, devices) -> list[str]:
        return []

    def output(self, params, devices) -> str | None:
        return None

    # -- plan ------------------------------------------------------------------
    def plan(self, params: CsmPositioningParams, devices: Devices) -> list[Step]:
        for cam in params.cameras:
            devices.camera(cam)  # unknown camera names fail before any motion
        if params.loops and params.primary not in params.loops:
            raise CalibrationInputError(f"primary={params.primary!r} is not one of loops ({', '.join(params.loops)})")
        kin = kinematics(params)
        targets = draw_targets(params, kin)
        steps: list[tuple[str, dict]] = [("survey", {"target": t, "joints": list(q)}) for t, q in enumerate(targets)]
        for t, q in enumerate(targets):
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
        return self._iterate(step, params, devices, list(history), base)

    def _visit(self, devices, params, q, base: dict, alt: bool = False, extra: dict | None = None) -> StepResult:
        devices.arm.move_joints(JointState(tuple(float(v) for v in q)))
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
        kin = kinematics(params)
        mode, _, scheme = loop.partition(":")
        k = best_k(data, params).get(scheme, 1.0)
        poses = data.loop_poses(t, loop, params.use_survey)
        q_start = data.last_joints(t, loop)
        try:
            if t not in data.by_target:
                raise CalibrationInputError(f"target {t}: its survey pose was not seen")
            target_uv = data.target_uv(t, params.cameras)
            est = locate(data, poses, target_uv, mode, scheme, k, params, params.loop_fit_depth)
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
        return fit_csm(samples, params, resolutions)


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


# --- samples ----------------------------------------------------------------------------------

class Pose_:
    """One sampled pose: joints (rad) and per camera, per feature, the mark's centre."""

    __slots__ = ("joints", "loop", "phase", "size", "step", "target", "uv")

    def __init__(self, step, phase, target, loop, joints):
        self.step, self.phase, self.target, self.loop, self.joints = step, phase, target, loop, joints
        self.uv: dict[str, dict[str, np.ndarray]] = {}
        self.size: dict[str, tuple[float, float]] = {}


class SampleSet:
    """The samples as poses, from rows (live history or an offline CSV)."""

    def __init__(self, poses: list[Pose_]):
        self.poses = poses
        self.by_target: dict[int, Pose_] = {p.target: p for p in poses if p.phase == "survey"}

    @classmethod
    def from_rows(cls, rows) -> SampleSet:
        poses: dict = {}
        for r in rows:
            if r.get("status", "ok") != "ok" or r.get("u_px") is None:
                continue
            joints = tuple(float(r[c]) for c in JOINT_COLS)
            key = r["step"] if r.get("step") is not None else joints
            phase = r.get("phase") or "survey"
            pose = poses.get(key)
            if pose is None:
                target = r.get("target")
                if target is None and phase == "survey":
                    target = len([p for p in poses.values() if p.phase == "survey"])
                pose = poses[key] = Pose_(key, phase, target, r.get("loop"), np.radians(joints))
            cam = str(r["camera"])
            pose.uv.setdefault(cam, {})[r.get("feature") or "white"] = np.array([float(r["u_px"]), float(r["v_px"])])
            if r.get("width_px") is not None:
                pose.size[cam] = (float(r["width_px"]), float(r["height_px"]))
        return cls(list(poses.values()))

    def cameras(self) -> list[str]:
        return sorted({c for p in self.poses for c in p.uv})

    def target_uv(self, t: int, cameras) -> list[np.ndarray]:
        pose = self.by_target.get(t)
        if pose is None or any("white" not in pose.uv.get(c, {}) for c in cameras):
            raise CalibrationInputError(f"target {t}: the white circle was not seen in every camera")
        return [pose.uv[c]["white"] for c in cameras]

    def loop_poses(self, t: int, loop: str, use_survey: bool) -> list[Pose_]:
        chosen = [p for p in self.poses if p.target == t and (p.phase == "approach" or
                                                               (p.phase == "iterate" and p.loop == loop))]
        if use_survey:
            chosen += [p for p in self.poses if p.phase == "survey" and p.target != t]
        return chosen

    def last_joints(self, t: int, loop: str) -> np.ndarray:
        own = [p for p in self.poses if p.target == t and p.phase == "iterate" and p.loop == loop]
        own = own or [p for p in self.poses if p.target == t and p.phase == "approach"]
        if not own:
            raise CalibrationInputError(f"target {t}: no approach samples")
        return max(own, key=lambda p: p.step).joints

    def centre(self, cam: str) -> np.ndarray:
        for p in self.poses:
            if cam in p.size:
                w, h = p.size[cam]
                return np.array([(w - 1) / 2, (h - 1) / 2])
        # offline files without the image size: the middle of the marks seen
        uv = np.array([v for p in self.poses for v in p.uv.get(cam, {}).values()])
        return (uv.min(axis=0) + uv.max(axis=0)) / 2


def camera_samples(data: SampleSet, poses: list[Pose_], mode: str, cameras, params) -> list[csm.CameraSamples]:
    """Per camera, (nominal 3D, camera-space) samples of the poses seen by every camera."""
    kin = kinematics(params)
    names = {"white": ("white",), "three": BLACKS, "virtual": BLACKS}[mode]
    usable = [p for p in poses if all(all(n in p.uv.get(c, {}) for n in names) for c in cameras)]
    if not usable:
        raise CalibrationInputError(f"no pose with the {mode} feature(s) seen in every camera")
    points = np.array([kin.points(p.joints, names) for p in usable])  # (n, f, 3)
    out = []
    for c in cameras:
        uv = np.array([[p.uv[c][n] for n in names] for p in usable])
        if mode == "virtual":
            P, U = points.mean(axis=1), uv.mean(axis=1)
        else:
            P, U = points.reshape(-1, 3), uv.reshape(-1, 2)
        out.append(csm.CameraSamples(P, U, data.centre(c), params.distance_mm * 1e-3))
    return out


def locate(data, poses, target_uv, mode, scheme, k, params, fit_depth: bool | None = None) -> csm.Estimate:
    cams = camera_samples(data, poses, mode, params.cameras, params)
    fit_depth = params.fit_depth if fit_depth is None else fit_depth
    fit_depth = fit_depth and len(cams[0].points) >= 10  # Z_r needs samples spread in depth
    return csm.estimate(cams, target_uv, scheme, k, fit_depth=fit_depth)


# --- the seed's offline experiments ---------------------------------------------------------------

def loo_errors(data: SampleSet, params, mode: str, scheme: str = "equal", k: float = 1.0,
               target_feature: str = "white") -> np.ndarray:
    """Leave-one-out over the survey poses: the others' samples estimate C, the left-out pose's
    `target_feature` (the virtual point for mode virtual) is located by eq. 10; error in nominal 3D (mm)."""
    kin = kinematics(params)
    survey = [p for p in data.poses if p.phase == "survey"]
    errors = []
    for pose in survey:
        others = [p for p in survey if p is not pose]
        if mode == "virtual":
            tuv = [np.mean([pose.uv[c][n] for n in BLACKS], axis=0) for c in params.cameras]
            truth = kin.points(pose.joints, BLACKS).mean(axis=0)
        else:
            tuv = [pose.uv[c][target_feature] for c in params.cameras]
            truth = kin.point(pose.joints, target_feature)
        est = locate(data, others, tuv, mode, scheme, k, params)
        errors.append(np.linalg.norm(est.target - truth) * 1e3)
    return np.array(errors)


def k_sweep(data: SampleSet, params) -> dict[str, dict[float, float]]:
    """Table V / Figs. 12-15: mean LOO error (white circle) per weighting scheme and k."""
    key = (tuple((p.target, tuple(np.round(np.concatenate([p.uv[c]["white"] for c in params.cameras]), 9)))
                 for p in data.poses if p.phase == "survey"), params.model_dump_json())
    return _k_sweep_cached(key, data, params)


_SWEEPS: dict = {}


def _k_sweep_cached(key, data, params):
    if key not in _SWEEPS:
        out = {"equal": {1.0: float(loo_errors(data, params, "white").mean())}}
        for scheme in VW_SCHEMES:
            out[scheme] = {float(k): float(loo_errors(data, params, "white", scheme, k).mean()) for k in params.k_values}
        if len(_SWEEPS) > 8:
            _SWEEPS.clear()
        _SWEEPS[key] = out
    return _SWEEPS[key]


def best_k(data: SampleSet, params) -> dict[str, float]:
    """The k of smallest mean LOO error per VW scheme (Table V); needs every target's survey."""
    survey = [p for p in data.poses if p.phase == "survey"]
    if len(survey) < 5:
        return {s: 1.0 for s in VW_SCHEMES}
    sweep = k_sweep(data, params)
    return {s: min(sweep[s], key=sweep[s].get) for s in VW_SCHEMES}


def fit_csm(samples: list[dict], params: CsmPositioningParams, resolutions=None) -> FitOutcome:
    """View parameters from the survey samples, and the seed's tables from everything recorded."""
    data = SampleSet.from_rows(samples)
    if params.cameras != tuple(data.cameras()) and set(params.cameras) - set(data.cameras()):
        raise CalibrationInputError(f"samples have cameras {data.cameras()}, params.cameras={list(params.cameras)}")
    kin = kinematics(params)
    survey = [p for p in data.poses if p.phase == "survey"]
    if len(survey) < 4:
        raise CalibrationInputError(f"need at least 4 survey poses seen by every camera, got {len(survey)}")
    tables, charts, stats = [], [], {}

    # Table III, rows 2-3: camera-space fit of all survey samples (white circle), equal weights
    cams = camera_samples(data, survey, "white", params.cameras, params)
    centroid_uv = [c.uv.mean(axis=0) for c in cams]
    est = csm.estimate(cams, centroid_uv, fit_depth=params.fit_depth and len(survey) >= 10)
    model = {"kind": "csm-view-parameters", "feature": "white", "n_poses": len(survey),
             "cameras": {c: {"C": [float(v) for v in C], "z_r_m": float(z)}
                         for c, C, z in zip(params.cameras, est.views, est.depths)}}
    fit_rows, camera_fit = [], {}
    for c, res in zip(params.cameras, est.residual_px):
        ax, ay = np.abs(res).mean(axis=0)
        e = float(np.linalg.norm(res, axis=1).mean())
        camera_fit[c] = {"x_px": float(ax), "y_px": float(ay), "mean_px": e, "rms_px": float(np.sqrt((res ** 2).sum(1).mean()))}
        seed = SEED_TABLE_III.get(c, ("-", "-", "-"))
        fit_rows.append([f"camera-space fit, {c} (px)", ax, ay, "-", e, f"{seed[0]} / {seed[1]} / - / {seed[2]}"])
    stats["camera_fit"] = camera_fit

    # Table II: LOO with one virtual feature; Table IV: the three black circles separately, white predicted
    blacks = all(all(n in p.uv.get(c, {}) for n in BLACKS for c in params.cameras) for p in survey)
    if blacks and len(survey) >= 5:
        loo_virtual = loo_errors(data, params, "virtual")
        loo_three = loo_errors(data, params, "three")
        stats["loo_3d"] = _err_stats(loo_virtual)
        stats["loo_3d_three"] = _err_stats(loo_three)
        tables.append(_per_point_table("Table II: leave-one-out 3D error, one virtual feature (mm)", loo_virtual,
                                       SEED_TABLE_II_MEAN))
        tables.append(_per_point_table("Table IV: leave-one-out 3D error, three features separately, white circle "
                                       "predicted (mm)", loo_three, SEED_TABLE_IV_MEAN))

    # Table V, Figs. 12-15: weighting schemes over k
    if len(survey) >= 5:
        sweep = k_sweep(data, params)
        best = {s: min(sweep[s], key=sweep[s].get) for s in VW_SCHEMES}
        tables.append({"title": "Table V: smallest mean positioning error per weighting scheme (mm), leave-one-out "
                                "over the survey poses, white circle",
                       "columns": ["scheme", "best k", "cellctl", "seed 002"],
                       "rows": [["equal", "-", sweep["equal"][1.0], SEED_TABLE_V["equal"]]]
                       + [[s, best[s], sweep[s][best[s]], SEED_TABLE_V[s]] for s in VW_SCHEMES]})
        for i, s in enumerate(VW_SCHEMES):
            charts.append({"name": f"fig{12 + i}_{s}_k", "title": f"Fig. {12 + i}: mean error with varying {s}",
                           "x_label": "k", "y_label": "mean error (mm)",
                           "series": {s: [[k, v] for k, v in sorted(sweep[s].items())],
                                      "equal": [[k, sweep["equal"][1.0]] for k in sorted(sweep[s])]}})
        stats["weights"] = {"best_k": best, "mean_mm": {s: sweep[s][best[s]] if s in best else sweep[s][1.0]
                                                        for s in ("equal", *VW_SCHEMES)}}

    # the closed loops: terminal error, iterations, error against iteration
    loops = loop_results(data, params, kin, samples)
    if loops:
        stats["loops"] = {name: {"n": r["n"], "mean_mm": r["mean_mm"], "max_mm": r["max_mm"],
                                 "iterations_mean": r["iterations_mean"], "converged": r["converged"], "k": r["k"]}
                          for name, r in loops.items()}
        if params.primary in loops:
            p = loops[params.primary]
            stats["positioning"] = {"n": p["n"], "mean_mm": p["mean_mm"], "max_mm": p["max_mm"], "loop": params.primary,
                                    "note": "nominal kinematics of the final joints against the target's joints"}
        stats["iterations"] = {("equal" if s == "equal" else s): loops[f"three:{s}"]["iterations_mean"]
                               for s in ("equal", *VW_SCHEMES) if f"three:{s}" in loops}
        for mode, seed_key, label in (("white", "white", "first: white circle"), ("virtual", "virtual", "second: virtual point")):
            name = next((n for n in loops if n.startswith(mode + ":")), None)
            if name:
                r = loops[name]
                s = SEED_TABLE_III[seed_key]
                fit_rows.append([f"{label} positioning ({name}), 3D (mm)", *r["axis_mean_mm"], r["mean_mm"],
                                 " / ".join(map(str, s))])
        tables.append({"title": "Table VI: iterations per weighting scheme (three black circles)",
                       "columns": ["scheme", "k", "mean iterations", "converged", "terminal mean (mm)", "seed 002"],
                       "rows": [[s, loops[f"three:{s}"]["k"], loops[f"three:{s}"]["iterations_mean"],
                                 loops[f"three:{s}"]["converged"], loops[f"three:{s}"]["mean_mm"], SEED_TABLE_VI[s]]
                                for s in ("equal", *VW_SCHEMES) if f"three:{s}" in loops]})
        tables.append({"title": "Terminal positioning error per loop (mm, nominal kinematics)",
                       "columns": ["loop", "k", "n", "mean", "max", "mean iterations", "converged"],
                       "rows": [[n, r["k"], r["n"], r["mean_mm"], r["max_mm"], r["iterations_mean"], r["converged"]]
                                for n, r in loops.items()]})
        for fig, mode in ((10, "white"), (11, "virtual")):
            series = {n: r["curve"] for n, r in loops.items() if n.startswith(mode + ":")}
            if series:
                charts.append({"name": f"fig{fig}_{mode}", "title": f"Fig. {fig}: positioning with the {mode} feature",
                               "x_label": "iteration", "y_label": "mean error (mm)", "series": series, "log_y": True})
        charts.append({"name": "iterations_three", "title": "error against iteration, three features, per scheme",
                       "x_label": "iteration", "y_label": "mean error (mm)", "log_y": True,
                       "series": {n: r["curve"] for n, r in loops.items() if n.startswith("three:")}})
    tables.insert(0, {"title": "Table III: error magnitudes", "columns": ["set", "x", "y", "z", "Euclidean",
                                                                         "seed 002 (x / y / z / Euclidean)"],
                      "rows": fit_rows})
    detectors = detector_agreement(samples)
    if detectors:
        stats["detector_agreement"] = detectors
    rejected = [{"step": r.get("step"), "reason": r.get("message") or r.get("status")}
                for r in samples if r.get("status") in ("no-marks", "failed")]
    return FitOutcome(model, stats, rejected, {}, {"tables": tables, "charts": charts})


def loop_results(data: SampleSet, params, kin: Kinematics, samples: list[dict]) -> dict:
    """Per loop: terminal error of the white circle (nominal kinematics of the final joints against the
    target's), moves made, how many converged, the k used, the mean error against iteration."""
    out = {}
    iterate = [p for p in data.poses if p.phase == "iterate"]
    loops = [l for l in params.loops if any(p.loop == l for p in iterate)]
    for loop in loops:
        errors, axes, iterations, curves = [], [], [], []
        for t, target in sorted(data.by_target.items()):
            goal = kin.point(target.joints, "white")
            approach = [p for p in data.poses if p.target == t and p.phase == "approach"]
            own = sorted((p for p in iterate if p.target == t and p.loop == loop), key=lambda p: p.step)
            if not approach:
                continue
            path = [max(approach, key=lambda p: p.step)] + own
            errs = [np.linalg.norm(kin.point(p.joints, "white") - goal) * 1e3 for p in path]
            final = kin.point(path[-1].joints, "white") - goal
            errors.append(errs[-1])
            axes.append(np.abs(final) * 1e3)
            iterations.append(len(own))
            curves.append(errs + [errs[-1]] * (params.max_iterations + 1 - len(errs)))
        if not errors:
            continue
        rows = [r for r in samples if r.get("phase") == "iterate" and r.get("loop") == loop]
        converged = len({r["target"] for r in rows if r.get("status") == "converged"})
        ks = sorted({float(r["k"]) for r in rows if r.get("k") is not None})
        out[loop] = {"n": len(errors), "mean_mm": float(np.mean(errors)), "max_mm": float(np.max(errors)),
                     "axis_mean_mm": [float(v) for v in np.mean(axes, axis=0)],
                     "iterations_mean": float(np.mean(iterations)),
                     "converged": converged, "k": ks[0] if len(ks) == 1 else ks,
                     "curve": [[i, float(v)] for i, v in enumerate(np.mean(curves, axis=0))]}
    return out


def detector_agreement(samples: list[dict]) -> dict | None:
    d = np.array([[r["u_px"] - r["u_alt_px"], r["v_px"] - r["v_alt_px"]] for r in samples
                  if r.get("status") == "ok" and r.get("u_alt_px") is not None
                  and not math.isnan(float(r["u_alt_px"]))])
    if not len(d):
        return None
    n = np.linalg.norm(d, axis=1)
    return {"n": len(d), "rms_px": float(np.sqrt((n ** 2).mean())), "max_px": float(n.max())}


def _err_stats(errors_mm) -> dict:
    e = np.asarray(errors_mm, dtype=float)
    return {"n": int(e.size), "mean_mm": float(e.mean()), "max_mm": float(e.max()), "rms_mm": float(np.sqrt((e ** 2).mean()))}


def _per_point_table(title: str, errors, seed_mean: float) -> dict:
    rows = [[f"point {i + 1}", float(e)] for i, e in enumerate(errors)]
    rows.append(["mean", float(np.mean(errors))])
    return {"title": title, "columns": ["point", "error (mm)"], "rows": rows,
            "note": f"seed 002: mean {seed_mean} mm over 21 points"}
