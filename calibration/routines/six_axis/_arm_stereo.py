"""`arm-kinematics` with `observe: fixed-cameras`: the arm calibrated by fixed cameras that watch a circle fixture on
its flange (the IRB 120 cell of seed 002: two uncalibrated cameras about 1.2 m away, four printed circles in the
seventh DH frame). arm_kinematics.py hands its plan, preview, collection and fit over to this module.

Plan: fixture poses drawn through the field the cameras share (a `field_mm` cube about `aim_mm`, above
`floor_mm`), the plate (it faces -z7) turned up to `tilt_deg` from facing both cameras and anywhere about its
normal, each reached by the nominal inverse kinematics (geometry/irb120.py, within IRB120_LIMITS_DEG) and seen by
every camera (its rough pose and lens: each circle inside the image by `margin_px`, the plate at most
`view_angle_deg` from face-on). From them, greedily D-optimal over the cameras, the mount and the deviations any
camera view can identify; held-out poses farthest in joint space from the chosen; a plan that leaves a deviation
unidentified beyond those no view can identify is refused, naming it and the joints that hardly turn.

Collect: at each pose the joints the arm reports and, in every camera, the four circles' centres
(calibration/vision/csm_markers.py): one row per circle per camera (`corner_id` is the circle: 0 the white, 1-3
the black ones); a frame where the marks are not found is one row with status `refused` and the reason.

Fit (models/arm_kinematics_stereo.py): each camera started from the nominal arm's fixture points (DLT, then
calibrateCamera); the nominal arm with the cameras and the mount fitted ("before"); the simultaneous adjustment
("after"); the usual chain (those cameras frozen, the fixture triangulated, then the arm). Verify on the held-out
poses: the reprojection error of each model, and the fixture's pose its cameras triangulate against the pose its
arm predicts.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pinocchio as pin
from pydantic import Field
from scipy.stats import qmc

from geometry.irb120 import IRB120_DH, Chain
from geometry.kinematic_table import KinematicTable, nominal_table, row_matrices
from geometry.transforms import look_at

from drivers.interfaces import JointState

from calibration.errors import CalibrationInputError, VisionError
from calibration.models import arm_kinematics as ak
from calibration.models import arm_kinematics_stereo as msk
from calibration.models import hand_eye as he
from calibration.routines.base import Devices, FitOutcome, Params, Step, StepResult
from calibration.routines.six_axis import _arm_poses as poses_
from calibration.routines.six_axis import _samples as samples_
from calibration.vision.csm_markers import MarkOptions, find_marks, label_fixture

Triple = tuple[float, float, float]
CIRCLES = ("white", "black1", "black2", "black3")  # corner_id 0..3
HOME_DEG = (0.0, 0.0, 0.0, 0.0, 90.0, 0.0)  # the IRB 120 cell's start-up joints: the first move starts here
# IK starts (deg; joint 1 is turned toward the target): elbow up, the wrist both ways
IK_STARTS_DEG = ((0, 20, 10, 0, 60, 0), (0, 40, -20, 0, 90, 0), (0, 20, 10, 180, -60, 180), (0, 0, 30, 90, 90, 0),
                 (0, 50, -40, -90, 90, 0), (0, 40, -20, 180, -90, 180))
SIGMA_PX = 0.05  # a centre's precision (planning)
STRUCTURAL_CONFIGURATIONS = 200


class StereoParams(Params):
    """The parameters of the fixed-cameras observation (arm_kinematics.py's parameters inherit them)."""

    cameras: tuple[str, ...] = Field(("cam1", "cam2"), min_length=2, description="fixed-cameras: the cameras that "
                                     "watch the fixture (the first is the frame the truth judges in)")
    camera_positions_mm: tuple[Triple, ...] = Field(((950.0, -600.0, 1050.0), (950.0, 600.0, 1050.0)),
                                                    description="fixed-cameras: each camera's position, roughly "
                                                    "(base frame), each looking at aim_mm (planning only)")
    aim_mm: Triple = Field((350.0, 0.0, 200.0), description="fixed-cameras: where the cameras look, roughly")
    field_mm: float = Field(600.0, gt=0, le=3000, description="fixed-cameras: the fixture's poses fill this cube "
                            "about aim_mm")
    floor_mm: float = Field(50.0, ge=-1000, le=3000, description="fixed-cameras: the fixture and every joint stay "
                            "above this height (base frame)")
    view_angle_deg: float = Field(60.0, gt=0, lt=90, description="fixed-cameras: the plate at most this far from "
                                  "face-on to every camera")
    margin_px: float = Field(80.0, ge=0, le=1000, description="fixed-cameras: every circle this far inside the image "
                             "(planning: the cameras' poses are rough)")
    image_px: tuple[int, int] = Field((1600, 1200), description="fixed-cameras: the image size when the cameras do "
                                      "not say (a preview)")
    d7_mm: float = Field(40.0, ge=-500, le=500, description="fixture drawing: DH d of the seventh frame")
    a7_mm: float = Field(0.0, ge=-500, le=500, description="fixture drawing: DH a of the seventh frame")
    white_mm: Triple = Field((0.0, 0.0, 0.0), description="fixture drawing: the white circle's centre in frame 7")
    black_mm: tuple[Triple, Triple, Triple] = Field(((40.0, 0.0, 0.0), (55.0, 15.0, 0.0), (55.0, -15.0, 0.0)),
                                                    description="fixture drawing: the black circles' centres")
    diameter_mm: float = Field(14.0, gt=0, le=200, description="fixture drawing: the circles' outer diameter")
    centre_model: Literal["ellipse", "point"] = Field("ellipse", description="fixed-cameras: predict the centre of "
                                                      "a circle's image ellipse (what the detector measures) or the "
                                                      "projection of its centre")
    repeatability_mm: float = Field(0.01, gt=0, le=1, description="fixed-cameras: the arm's repeatability, 1-sigma "
                                    "per axis (the first guess; re-estimated)")

    def fixture(self) -> msk.Fixture:
        mount = np.eye(4)
        mount[:3, 3] = (self.a7_mm * 1e-3, 0.0, self.d7_mm * 1e-3)  # the seventh DH row: Tz(d7) Tx(a7)
        points = np.array([self.white_mm, *self.black_mm], dtype=float) * 1e-3
        return msk.Fixture(mount, points, self.diameter_mm * 0.5e-3)


# -- plan ------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StereoRegion:
    aim: np.ndarray  # m, base frame
    field: float  # m, the cube's edge
    floor: float  # m
    tilt: float  # rad, the plate's turn from facing the cameras
    view_angle: float  # rad
    margin: float  # px
    cameras: list[msk.Camera]  # rough
    fixture: msk.Fixture
    home: np.ndarray


def _table(params) -> KinematicTable:
    if params.arm_model != "irb120":
        raise CalibrationInputError(f"observe=fixed-cameras: arm_model={params.arm_model!r}; allowed: irb120 (the "
                                    "fixture rides its seventh DH frame; wrist-board serves ur5e)")
    return nominal_table("irb120")


def region_of(params, image_size) -> StereoRegion:
    if len(params.camera_positions_mm) != len(params.cameras):
        raise CalibrationInputError(f"camera_positions_mm has {len(params.camera_positions_mm)} positions for "
                                    f"{len(params.cameras)} cameras ({', '.join(params.cameras)}): give one each")
    aim = np.asarray(params.aim_mm) * 1e-3
    f = params.focal_mm / (params.pixel_um * 1e-3)
    w, h = image_size
    cameras = []
    for name, position in zip(params.cameras, params.camera_positions_mm):
        eye = np.asarray(position) * 1e-3
        T = look_at(eye, aim, right=np.cross(aim - eye, [0.0, 0.0, 1.0]))  # the image's rows level
        cameras.append(msk.Camera(name, he.Intrinsics(w, h, f, f, (w - 1) / 2, (h - 1) / 2, (0.0,) * 5), T))
    return StereoRegion(aim, params.field_mm * 1e-3, params.floor_mm * 1e-3, math.radians(params.tilt_deg),
                        math.radians(params.view_angle_deg), params.margin_px, cameras, params.fixture(),
                        np.radians(HOME_DEG))


def _facing(region: StereoRegion, p: np.ndarray) -> np.ndarray:
    """The unit direction that faces every camera alike from p (the bisector of the lines of sight)."""
    b = sum((_centre(c) - p) / np.linalg.norm(_centre(c) - p) for c in region.cameras)
    return b / np.linalg.norm(b)


def _centre(camera: msk.Camera) -> np.ndarray:
    T = camera.T_camera_base
    return -T[:3, :3].T @ T[:3, 3]


def _fixture_pose(region: StereoRegion, u: np.ndarray) -> np.ndarray | None:
    """T_base_fixture of one low-discrepancy draw u in [0, 1)^6, or None below the floor."""
    p = region.aim + (u[:3] - 0.5) * region.field
    if p[2] < region.floor:
        return None
    b = _facing(region, p)
    side = np.cross(b, [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([0.0, 1.0, 0.0])
    tilt, azimuth = region.tilt * math.sqrt(u[3]), 2 * math.pi * u[4]
    normal = math.cos(tilt) * b + math.sin(tilt) * (math.cos(azimuth) * side + math.sin(azimuth) * np.cross(b, side))
    z = -normal  # the plate faces -z7
    x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    turn = 2 * math.pi * u[5] - math.pi
    x, y = math.cos(turn) * x + math.sin(turn) * np.cross(z, x), -math.sin(turn) * x + math.cos(turn) * np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = p
    return T


def sees_fixture(cameras: list[msk.Camera], fixture: msk.Fixture, T_base_fixture: np.ndarray, view_angle: float,
                 margin: float) -> bool:
    """Every camera sees the plate's front within view_angle (rad) of face-on, every circle inside its image by
    margin (px)."""
    normal = -T_base_fixture[:3, 2]
    points = fixture.points @ T_base_fixture[:3, :3].T + T_base_fixture[:3, 3]
    for camera in cameras:
        sight = _centre(camera) - T_base_fixture[:3, 3]
        if normal @ sight < math.cos(view_angle) * np.linalg.norm(sight):
            return False
        p = points @ camera.T_camera_base[:3, :3].T + camera.T_camera_base[:3, 3]
        if np.any(p[:, 2] < 0.05):
            return False
        uv = he.distort(camera.lens, p)
        w, h = camera.lens.width, camera.lens.height
        if np.any(uv < margin) or np.any(uv[:, 0] > w - 1 - margin) or np.any(uv[:, 1] > h - 1 - margin):
            return False
    return True


def _above_floor(table: KinematicTable, q: np.ndarray, floor: float) -> bool:
    """Every joint's origin after the shoulder above the floor."""
    T = table.base
    for value, j in zip(q, table.joints):
        T = T @ row_matrices(np.array([value + j.theta]), j.d, j.a, j.alpha, j.beta)[0]
        if T[2, 3] < floor:
            return False
    return True


@functools.lru_cache(maxsize=4)
def _chain(d7: float, a7: float) -> Chain:
    return Chain(IRB120_DH, (d7, a7))


def candidates(region: StereoRegion, params, count: int, seed: int) -> list[poses_.Candidate]:
    """Up to `count` reachable configurations that show every camera the fixture (module docstring)."""
    chain = _chain(params.d7_mm * 1e-3, params.a7_mm * 1e-3)
    table = _table(params)
    draws = qmc.Halton(6, scramble=True, seed=seed).random(count * 8)
    starts = np.radians(IK_STARTS_DEG)
    out: list[poses_.Candidate] = []
    for k, u in enumerate(draws):
        T = _fixture_pose(region, u)
        if T is None or not sees_fixture(region.cameras, region.fixture, T, region.view_angle, region.margin):
            continue
        start = starts[k % len(starts)].copy()  # each draw tries one start: the pool mixes the branches
        start[0] = math.atan2(T[1, 3], T[0, 3])
        q, reached = chain.reach_pose(pin.SE3(T[:3, :3], T[:3, 3]), start, tol=1e-9, max_iter=60)
        if not reached or not chain.within_limits(q) or not _above_floor(table, q, region.floor):
            continue
        out.append(poses_.Candidate(q, table.forward(q)))
        if len(out) >= count:
            break
    return out


def pose_jacobians(cands: list[poses_.Candidate], table: KinematicTable, region: StereoRegion,
                   free: np.ndarray) -> np.ndarray:
    """(n, 2 x cameras x circles, p): how each candidate's centres move (over a centre's precision) with every
    camera's lens (8) and pose (6), the mount (6) and the free deviations (each over its budget)."""
    Q = np.array([c.joints for c in cands])
    n, n_cam, n_pt = len(Q), len(region.cameras), len(region.fixture.points)
    pose_of = np.repeat(np.arange(n), n_cam * n_pt)
    camera_of = np.tile(np.repeat(np.arange(n_cam), n_pt), n)
    point_of = np.tile(np.arange(n_pt), n * n_cam)
    problem = msk.StereoProblem(msk.Observations([str(i) for i in range(n)], Q, tuple(c.name for c in region.cameras),
                                                 {}, pose_of, camera_of, point_of, np.zeros((len(pose_of), 2))),
                                region.fixture, table, region.cameras, region.fixture.mount, free, "point")
    problem.sigma_px = SIGMA_PX
    J = msk._global_jacobian(problem, problem.x0())  # rows: pose by pose, camera by camera, circle, (u, v)
    return J.reshape(n, -1, J.shape[1])


def choose(J: np.ndarray, n: int) -> list[int]:
    """Greedy D-optimal choice of n candidates: each adds the most information, det(I + J M^-1 J^T)."""
    p = J.shape[2]
    M = 1e-6 * np.eye(p)
    chosen: list[int] = []
    eye = np.eye(J.shape[1])
    for _ in range(min(n, len(J))):
        Minv = np.linalg.inv(M)
        gains = np.array([np.linalg.slogdet(eye + Jk @ Minv @ Jk.T)[1] for Jk in J])
        gains[chosen] = -np.inf
        k = int(np.argmax(gains))
        chosen.append(k)
        M = M + J[k].T @ J[k]
    return chosen


def plan_observability(J: np.ndarray, names: list[str], n_other: int, ratio: float = ak.OBSERVABLE_RATIO) -> dict:
    """What the poses can identify, from their Jacobians: the cameras and the mount (the first n_other columns)
    projected out (models/arm_kinematics_stereo.py); rounding alone stays below the threshold."""
    A = J.reshape(-1, J.shape[2])
    return ak.identifiable(A[:, :n_other], A[:, n_other:], names, ratio, against_raw=True)


@functools.lru_cache(maxsize=4)
def structural(arm_model: str) -> frozenset[str]:
    """The deviations no view of the fixture can ever identify: those the fixture's full pose over many
    configurations cannot tell from the base's pose (which the cameras' poses absorb), the mount, or each other."""
    table = nominal_table(arm_model)
    rng = np.random.default_rng(28)
    lo, hi = np.array([j.limits for j in table.joints]).T
    Q = rng.uniform(lo, hi, (STRUCTURAL_CONFIGURATIONS, 6))
    base = table.forward_batch(Q)
    scales = ak.budget_scales(table)
    cols = []
    for i in range(12):  # the base's 6 and the mount's 6, as small turns and moves
        d = np.zeros(6)
        d[i % 6] = 1e-6
        M = he._perturbed(np.eye(4), d)
        T = M[None] @ base if i < 6 else base @ M
        cols.append(_pose_rows(base, T) / 1e-6)
    for i in range(len(scales)):
        v = table.vector()
        v[i] += 1e-6 * scales[i]
        cols.append(_pose_rows(base, table.with_vector(v).forward_batch(Q)) / 1e-6)
    J = np.column_stack(cols)
    return frozenset(plan_observability(J[None], table.parameter_names(), 12)["fixed"])


def _pose_rows(T0: np.ndarray, T1: np.ndarray) -> np.ndarray:
    """The small motion from T0 to T1 of every pose (rotation vector, translation), stacked."""
    R = np.einsum("nji,njk->nik", T0[:, :3, :3], T1[:, :3, :3])
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1) / 2
    return np.hstack([w * 0.1, T1[:, :3, 3] - T0[:, :3, 3]]).ravel()  # a turn over a 0.1 m lever


def pose_plan(params, image_size) -> dict:
    """The chosen poses (joints), the held-out ones, and what the plan can identify; or the reason not."""
    table = _table(params)
    region = region_of(params, image_size)
    cands = candidates(region, params, params.candidates, params.plan_seed)
    wanted = params.poses + params.verify_poses
    if len(cands) < wanted:
        raise CalibrationInputError(f"the region gives only {len(cands)} reachable poses where every camera sees the "
                                    f"fixture, fewer than the {wanted} asked for: widen field_mm, tilt_deg or "
                                    "view_angle_deg, check camera_positions_mm and aim_mm, or ask for fewer poses")
    fixed_always = structural(params.arm_model)
    names = table.parameter_names()
    free = np.array([n not in fixed_always for n in names])
    J = pose_jacobians(cands, table, region, free)
    chosen = choose(J, params.poses)
    n_other = msk.PER_CAMERA * len(region.cameras) + 6
    free_names = [n for n, f in zip(names, free) if f]
    seen = plan_observability(J[chosen], free_names, n_other)
    Q = np.array([cands[i].joints for i in chosen])
    # refused only when a deviation is far from identifiable (the fit decides again from the centres themselves)
    refuse_unidentifiable(plan_observability(J[chosen], free_names, n_other, ak.OBSERVABLE_RATIO / 10), Q, table)
    held = poses_.farthest(cands, chosen, params.verify_poses)
    order = poses_.tour(cands, chosen, region.home)
    ver_order = poses_.tour(cands, held, cands[order[-1]].joints) if held else []
    return {"cal": [cands[i].joints for i in order], "ver": [cands[i].joints for i in ver_order],
            "identified": seen["identified"], "fixed": sorted(set(seen["fixed"]) | fixed_always, key=names.index),
            "o1": seen["o1"], "joint_spread_deg": np.degrees(Q.max(axis=0) - Q.min(axis=0)).tolist()}


def refuse_unidentifiable(seen: dict, Q: np.ndarray, table: KinematicTable) -> None:
    """Refused when these poses leave deviations unidentified (beyond those no view can identify)."""
    poses_.refuse_unidentifiable(seen["fixed"], Q, table, "field_mm or tilt_deg (the fixture through more of the "
                                 "field, the plate turned more)")


def preview(params, image_size) -> list[dict]:
    plan = pose_plan(params, image_size or tuple(params.image_px))
    rows = [[f"cal{i + 1}", *[round(float(v), 2) for v in np.degrees(q)]] for i, q in enumerate(plan["cal"])]
    rows += [[f"ver{i + 1}", *[round(float(v), 2) for v in np.degrees(q)]] for i, q in enumerate(plan["ver"])]
    spread = ", ".join(f"{v:.0f}" for v in plan["joint_spread_deg"])
    return [{"title": "Planned arm configurations (fixed cameras)", "columns": ["pose", *samples_.JOINT_COLUMNS],
             "rows": rows,
             "note": (f"{len(plan['cal'])} calibration and {len(plan['ver'])} held-out poses seen by "
                      f"{', '.join(params.cameras)}; joint spread (deg) {spread}; identifies "
                      f"{len(plan['identified'])} deviations (observability O1 {plan['o1']:.3g}); fixed at nominal: "
                      f"{', '.join(plan['fixed'])}")}]


def plan(params, devices: Devices) -> list[Step]:
    sizes = {tuple(getattr(devices.camera(c), "resolution", None) or params.image_px) for c in params.cameras}
    if len(sizes) != 1:
        raise CalibrationInputError(f"cameras {', '.join(params.cameras)} have different image sizes {sorted(sizes)}; "
                                    "the plan takes one size for all")
    p = pose_plan(params, sizes.pop())
    steps = [(f"cal{i + 1}", "cal", q) for i, q in enumerate(p["cal"])]
    steps += [(f"ver{i + 1}", "ver", q) for i, q in enumerate(p["ver"])]
    return [Step(i, "pose", {"pose": name, "set": s, "joints": [float(v) for v in q]})
            for i, (name, s, q) in enumerate(steps)]


# -- collect ---------------------------------------------------------------------------------------------------------
def execute(step: Step, params, devices: Devices) -> StepResult:
    a = step.args
    devices.arm.move_joints(JointState(tuple(float(v) for v in a["joints"])))
    joints = np.degrees(devices.arm.joints().positions)
    white = np.asarray(params.white_mm[:2])
    black = np.asarray([b[:2] for b in params.black_mm])
    rows, frames = [], []
    for name in params.cameras:
        frame = devices.camera(name).capture()
        frames.append(frame)
        h, w = frame.image.shape[:2]
        common = {"step": step.index, "pose": a["pose"], "set": a["set"], "camera": name, "frame_id": frame.frame_id,
                  "width_px": w, "height_px": h, **{c: float(v) for c, v in zip(samples_.JOINT_COLUMNS, joints)}}
        try:
            centres = circle_centres(frame.image, white, black)
        except VisionError as exc:
            rows.append(dict(common, status="refused", message=str(exc)))
            continue
        rows += [dict(common, status="ok", corner_id=i, u_px=float(u), v_px=float(v), message="")
                 for i, (u, v) in enumerate(centres)]
    return StepResult(rows, frames)


def circle_centres(image: np.ndarray, white_xy, black_xy) -> np.ndarray:
    """(4, 2) px: the fixture's circles in one frame, in CIRCLES order (the drawing's white and black centres, x
    and y in its frame, name them); VisionError when the frame does not show exactly the four."""
    named = label_fixture(find_marks(image, "contour", MarkOptions()), np.asarray(white_xy), np.asarray(black_xy))
    return np.array([named[c] for c in CIRCLES])


# -- fit -------------------------------------------------------------------------------------------------------------
def observations(rows: list[dict], params) -> tuple[dict[str, msk.Observations], list[dict]]:
    """The samples as observations, calibration and held-out, and the refused frames with their reasons."""
    refused, by_set = [], {"cal": {}, "ver": {}}
    sizes: dict[str, tuple[int, int]] = {}
    for r in rows:
        if r.get("status") != "ok":
            refused.append({"pose": r.get("pose"), "camera": r.get("camera"), "reason": r.get("message")})
            continue
        camera = str(r["camera"])
        if camera not in params.cameras:
            raise CalibrationInputError(f"a sample of camera {camera!r}; params.cameras: {', '.join(params.cameras)}")
        s = r.get("set") or "cal"
        if s not in by_set:
            raise CalibrationInputError(f"pose {r.get('pose')}: set={s!r}; allowed: cal, ver (empty: cal)")
        by_set[s].setdefault(str(r["pose"]), []).append(r)
        sizes[camera] = (int(float(r["width_px"])), int(float(r["height_px"])))
    out = {}
    for s, poses in by_set.items():
        names, joints, pose_of, camera_of, point_of, uv = [], [], [], [], [], []
        for k, (pose, group) in enumerate(poses.items()):
            names.append(pose)
            joints.append(np.radians([float(group[0][c]) for c in samples_.JOINT_COLUMNS]))
            for r in group:
                pose_of.append(k)
                camera_of.append(params.cameras.index(str(r["camera"])))
                point_of.append(int(float(r["corner_id"])))
                uv.append((float(r["u_px"]), float(r["v_px"])))
        out[s] = msk.Observations(names, np.array(joints).reshape(-1, 6), tuple(params.cameras), sizes,
                                  np.array(pose_of, dtype=int), np.array(camera_of, dtype=int),
                                  np.array(point_of, dtype=int), np.array(uv, dtype=float).reshape(-1, 2))
    both = _seen_by_all(out["cal"])
    if both < msk.MIN_POSES:
        raise CalibrationInputError(f"{both} calibration poses were seen by every camera ({', '.join(params.cameras)});"
                                    " the arm's calibration needs many more (the plan asks for 40)")
    return out, refused


def _seen_by_all(obs: msk.Observations) -> int:
    return sum(len(np.unique(obs.camera_of[obs.pose_of == k])) == len(obs.cameras) for k in range(len(obs.poses)))


def fit(samples: list[dict], params, resolutions=None) -> FitOutcome:
    sets, refused = observations(samples, params)
    cal, ver = sets["cal"], sets["ver"]
    nominal = _table(params)
    fixture = params.fixture()
    cameras0 = msk.start_cameras(cal, fixture, nominal)
    before = msk.fit(cal, fixture, nominal, cameras0, free=np.zeros(len(nominal.vector()), dtype=bool),
                     loss=params.loss, centre_model=params.centre_model, repeatability_m=params.repeatability_mm * 1e-3)
    result = msk.fit(cal, fixture, nominal, cameras0, loss=params.loss, centre_model=params.centre_model,
                     repeatability_m=params.repeatability_mm * 1e-3)
    sequential = msk.sequential(cal, fixture, nominal, cameras0, result.observability["free_mask"])
    models = {"before": before.model, "after": result.model, "sequential": sequential}
    verification, series = {}, {}
    for name, m in models.items():
        verification[name], series[name] = _verify(m, fixture, ver, np.asarray(params.aim_mm) * 1e-3)
    point = msk.StereoModel(result.model.cameras, result.model.table, result.model.mount, "point")
    o = cal
    bias = np.linalg.norm(msk.predict(result.model, fixture, o.joints, o.pose_of, o.camera_of, o.point_of)
                          - msk.predict(point, fixture, o.joints, o.pose_of, o.camera_of, o.point_of), axis=1)
    model = {"kind": "arm-kinematics", "observe": "fixed-cameras", "arm_model": params.arm_model,
             **result.model.to_dict(), "tool_frame": "fixture", "nominal": nominal.to_dict(),
             # the drawing the cameras were calibrated on: what iso9283 measures them by (_iso_stereo.py)
             "fixture": {"points_mm": (fixture.points * 1e3).tolist(), "diameter_mm": fixture.radius * 2e3},
             # the controller's pose is the fixture frame as the drawing puts it; the calibrated one is the fitted mount
             "tcp": he.pose_to_dict(result.model.mount), "controller_tcp": he.pose_to_dict(fixture.mount),
             "identified": result.identified, "fixed": result.fixed, "gauge": result.gauge,
             "deviations": {k: _human(k, v) for k, v in result.values.items()},
             "sigma": {k: _human(k, v) for k, v in result.sigma.items()},
             "before": before.model.to_dict(), "sequential": sequential.to_dict()}
    stats = {"calibration": {"n_poses": len(cal.poses), "n_centres": len(cal.uv), "rms_px": result.rms_px,
                             "noise": result.noise, "o1": result.observability["o1"],
                             "condition": result.observability["condition"],
                             "ellipse_centre_shift_px": {"mean": float(bias.mean()), "max": float(bias.max())},
                             f"position_sigma_in_{params.cameras[0]}_mm": result.camera_frame_sigma_mm},
             "verification": verification}
    tables = [_parameter_table(result), _gauge_table(result), _verification_table(verification)]
    if result.correlations:
        tables.append({"title": "Correlations above 0.9", "columns": ["a", "b", "r"],
                       "rows": [[a, b, round(r, 3)] for a, b, r in result.correlations]})
    summary = {"identified": len(result.identified), "rms_px": result.rms_px,
               **{f"verify_position_{k}_mean_mm": v["position_mean_mm"] for k, v in verification.items()}}
    rejected = refused + result.rejected
    chart = {"name": "held_out_errors", "title": "Held-out poses: the fixture's position error by model",
             "x_label": "the fixture's distance from aim_mm (mm)", "y_label": "position error (mm)",
             "series": {LABELS[k]: series[k] for k in ("before", "sequential", "after")}, "log_y": True}
    return FitOutcome(model, stats, rejected, {}, tables, summary=summary, charts=[chart] if len(ver.poses) else [])


def _verify(model: msk.StereoModel, fixture: msk.Fixture, ver: msk.Observations,
            aim: np.ndarray) -> tuple[dict, list]:
    """The held-out figures of one model, and its (distance from aim mm, position error mm) points."""
    if not len(ver.poses):
        return {"n": 0, "reprojection_rms_px": None, "position_mean_mm": None, "position_max_mm": None,
                "orientation_mean_deg": None}, []
    h = msk.held_out_errors(model, fixture, ver)
    e = h["pose_errors"]
    distance = np.linalg.norm(h["positions"] - aim, axis=1) * 1e3
    return ({"n": len(e), "reprojection_rms_px": h["reprojection_rms_px"],
             "position_mean_mm": float(e[:, 0].mean() * 1e3) if len(e) else None,
             "position_max_mm": float(e[:, 0].max() * 1e3) if len(e) else None,
             "orientation_mean_deg": float(np.degrees(e[:, 1]).mean()) if len(e) else None},
            sorted([float(d), float(x * 1e3)] for d, x in zip(distance, e[:, 0])))


def _human(name: str, value: float) -> float:
    """Lengths in mm, angles in deg."""
    return value * 1e3 if name.split("_")[0] in ("d", "a") else math.degrees(value)


def _parameter_table(result: msk.StereoResult) -> dict:
    rows = [[name, round(_human(name, result.values[name]), 5), round(_human(name, result.sigma[name]), 5)]
            for name in result.identified]
    return {"title": "Identified deviations from the published table (mm, deg)",
            "columns": ["parameter", "value", "sigma"], "rows": rows,
            "note": f"fixed at nominal: {', '.join(result.fixed)}"}


def _gauge_table(result: msk.StereoResult) -> dict:
    return {"title": "Deviations fixed at nominal, and what absorbs them", "columns": ["absorbed by", "deviations"],
            "rows": [[who, ", ".join(names)] for who, names in result.gauge.items() if names]}


LABELS = {"before": "nominal arm, cameras and mount fitted", "sequential": "cameras first, then the arm",
          "after": "simultaneous (this calibration)"}


def _verification_table(v: dict) -> dict:
    def cell(x, digits=4):
        return None if x is None else round(x, digits)

    rows = [[LABELS[k], v[k]["n"], cell(v[k]["reprojection_rms_px"]), cell(v[k]["position_mean_mm"]),
             cell(v[k]["position_max_mm"]), cell(v[k]["orientation_mean_deg"], 5)]
            for k in ("before", "sequential", "after")]
    return {"title": "Held-out poses: the fixture as each model's cameras see it against its arm",
            "columns": ["model", "poses", "reprojection RMS px", "position mean mm", "position max mm",
                        "orientation mean deg"], "rows": rows}
