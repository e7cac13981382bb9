"""On-board camera calibration (seed 001 section 7).

The camera rides on the end effector. The robot lays a grid of spheres on the
working area, then looks at it from poses P1..Pn with different rotations alpha.
Pose 1 calibrates the camera (B1+B2 from pixels to positions relative to the
gripper at P1, virtual-grid style); the location D of the rotation axis relative
to the reported gripper position follows from every other pose by eq. (4),

    (R_k - I) D = P_k - P_1 + R_k A_(b)k,i - A_(a)i,

stacked over poses and points and solved by least squares (the seed's generalisation).
The cross-reference test of Tables IV-VI measures, for D estimated from one pose
(c_l) or all (c*), the error of eq. (5) at every pose against the position seen at
pose 1; verification measures it against where the spheres were placed.

Accuracy target (issue 31, calibration/routines/targeted.py): the budget is the views after the two the model
needs (pose 1, the reference, and the widest turn from it). The spheres, nearly all of the routine's cell time, are
not: every sphere is laid before the first view, so no sample says how many are enough while they are being laid,
and laying a second batch after the views would need a second round of views. The views come information first:
pose 1, the widest turn, then the others by decreasing turn from pose 1 (a wide turn pins the rotation axis D best:
its error enters a located point as (I - R) dD), each tie to the nearer. After each view the joint adjustment is
refitted and the error of a sphere the camera locates from a view at the plan's turns is predicted: the floor
from the views' common noise (the arm's repeatability at a view) and each sphere's own, on the views' degrees of
freedom (2 per view after the first), the model share from the adjustment's covariance of the map (at the image
places the spheres were seen) and of D (averaged over the plan's turns). The placement error of the spheres
enters the verification figure but not the calibration, and is left out. Views stop once that, at its 95 % bound,
meets `target_um` (default: what all the views are predicted to reach + 2 %). The map's share shrinks with each
view (the views' common noise dominates it), so the default target took every view on seeds 0-9: a view costs
half a second, and a target can shorten this routine by a few seconds at most. It needs the joint adjustment
(its covariance): with `joint_adjustment` false every view is taken.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from pydantic import Field, model_validator
from scipy.optimize import least_squares

from drivers.interfaces import Pose

from calibration.errors import CalibrationInputError, VisionError
from calibration.models.planar import MapUncertainty, PlanarModelOptions, fit_planar_map
from calibration.models.sphere_height import SphereHeights, diameter_column
from calibration.models.tool_offset import rot
from calibration.routines import targeted
from calibration.routines.base import Devices, FitOutcome, PlanarFitParams, Step, StepResult, execute_split
from calibration.routines.steps import pick_sphere, place_sphere
from calibration.routines.tables import radial_error_tables
from calibration.stats import error_stats
from calibration.vision.centroid import find_blobs

PLACE, VIEW = "place", "pose"
# default target: today's figure + 2 %: the map and D carry into every sphere the camera locates later
EXCESS = 0.02

# Seed 001, Table IV: RMS error (µm) of the cross-reference test, pose p_k (rows) x estimate c (columns).
SEED_TABLE_IV = {
    "p2": {"c*": 26.2, "c2": 16.6, "c3": 24.3, "c4": 30.4, "c5": 21.0, "c6": 25.3},
    "p3": {"c*": 22.5, "c2": 41.1, "c3": 20.4, "c4": 27.6, "c5": 23.2, "c6": 28.3},
    "p4": {"c*": 28.1, "c2": 79.2, "c3": 36.1, "c4": 23.4, "c5": 49.0, "c6": 35.6},
    "p5": {"c*": 18.8, "c2": 20.7, "c3": 17.1, "c4": 21.7, "c5": 16.2, "c6": 20.3},
    "p6": {"c*": 20.1, "c2": 33.6, "c3": 22.9, "c4": 22.2, "c5": 25.5, "c6": 17.7},
}

# Seed 001, Table V: maximum error (µm) of the same test. (Table VI, the mean, has no numbers in the seed text.)
SEED_TABLE_V = {
    "p2": {"c*": 46.1, "c2": 35.0, "c3": 42.2, "c4": 51.2, "c5": 36.8, "c6": 46.5},
    "p3": {"c*": 45.4, "c2": 77.3, "c3": 42.9, "c4": 51.6, "c5": 53.8, "c6": 55.3},
    "p4": {"c*": 61.7, "c2": 121.9, "c3": 72.2, "c4": 46.3, "c5": 88.3, "c6": 69.0},
    "p5": {"c*": 45.6, "c2": 42.0, "c3": 41.0, "c4": 50.2, "c5": 42.2, "c6": 47.9},
    "p6": {"c*": 51.9, "c2": 65.5, "c3": 58.4, "c4": 49.8, "c5": 62.3, "c6": 44.1},
}


class OnboardCameraParams(PlanarFitParams):
    area: str = Field("board", description="free working area where the sphere grid is laid; its camera rides the arm")
    rows: int = Field(4, ge=2, le=20, description="rows of the sphere grid laid in the area")
    cols: int = Field(5, ge=2, le=20, description="columns of the sphere grid")
    pitch_mm: tuple[float, float] = Field((3.0, 2.5), description="grid pitch (x, y)")
    alphas_deg: tuple[float, ...] = Field((0.0, 15.0, 30.0, -15.0, -30.0, 45.0), description="rotation of each pose")
    view_z_mm: float = Field(20.5, description="gripper height at which the spheres are in focus")
    mount_offset_mm: tuple[float, float] | None = Field(None, description="nominal: where the camera looks, "
                                                                          "from the gripper")
    pixel_um: float | None = Field(None, gt=0, description="nominal spatial resolution, to tell the spheres apart")
    sphere_diameter_mm: float = Field(1.0, description="nominal sphere diameter")
    sphere_tolerance_mm: float = Field(0.2, description="+/- on the sphere diameter")
    supply_mm: tuple[float, float] | None = Field(None, description="where the feeder presents a sphere")
    supply_z_mm: float = Field(0.0, description="the feeder's surface height")
    radial_terms: int = Field(1, ge=0, le=3, description="radial distortion terms fitted (k2, k4, k6: 0 to 3)")
    tangential: bool = Field(False, description="fit the tangential distortion (p1, p2)")
    fit_centre: bool = Field(False, description="fit the distortion centre (false: the image centre)")
    working_distance_mm: float | None = Field(None, gt=1, le=5000, description="the lens's nominal working "
                                              "distance: correct each sphere for its height (None: no correction)")
    joint_adjustment: bool = Field(True, description="refine the map, D and the spheres' rest positions together "
                                   "over all poses (False: the seed's procedure, map from pose 1, c* by eq. 4)")
    pose_sigma_um: float = Field(2.0, gt=0, le=1000, description="weight: the robot's repeatability at a view")
    placement_sigma_um: float = Field(6.0, gt=0, le=1000, description="weight: how far a sphere rests from where "
                                      "it was placed")
    target_um: float | None = Field(None, gt=0, le=10000, description="predicted RMS error of a sphere the camera "
                                    "locates (95 % upper bound; placement error left out) before the views stop; "
                                    "none: today's figure (what all the poses are predicted to reach) + 2 %. The "
                                    "spheres are always all laid; only views after the first two are cut")

    @model_validator(mode="after")
    def _poses(self):
        a = sorted(self.alphas_deg)
        if len(a) < 2 or min(np.diff(a)) <= 10:
            raise ValueError(f"alphas_deg {list(self.alphas_deg)}: at least 2 poses, more than 10 degrees apart")
        return self


class OnboardCamera:
    name: ClassVar[str] = "onboard-camera"
    truth: ClassVar[str | None] = "cellctl.truth.micro:onboard_truth"
    Params: ClassVar[type[OnboardCameraParams]] = OnboardCameraParams
    sample_columns: ClassVar[tuple[str, ...]] = (
        "step", "set", "status", "camera", "frame_id", "pose", "sphere", "alpha_deg",
        "x_mm", "y_mm", "u_px", "v_px", "diameter_px", "message",
    )
    fit_columns: ClassVar[tuple[str, ...]] = ("set", "pose", "sphere", "alpha_deg", "x_mm", "y_mm", "u_px", "v_px")

    def inputs(self, params, devices: Devices) -> list[str]:
        return []

    def output(self, params, devices: Devices) -> str | None:
        return devices.area(params.area).camera

    def _grid(self, params, devices: Devices) -> np.ndarray:
        area = devices.area(params.area)
        jj, ii = np.meshgrid(np.arange(params.rows), np.arange(params.cols), indexing="ij")
        offsets = np.column_stack([(ii.ravel() - (params.cols - 1) / 2) * params.pitch_mm[0],
                                   (jj.ravel() - (params.rows - 1) / 2) * params.pitch_mm[1]]) * 1e-3
        return offsets + area.centre

    def plan(self, params: OnboardCameraParams, devices: Devices) -> list[Step]:
        if params.supply_mm is None or devices.gripper is None:
            raise CalibrationInputError("onboard-camera needs a gripper and supply_mm (where the feeder presents spheres)")
        if params.mount_offset_mm is None or params.pixel_um is None:
            raise CalibrationInputError("onboard-camera needs the camera's nominal mount_offset_mm and pixel_um "
                                        "(cell file, routines.onboard-camera) to move over the grid and tell spheres apart")
        area = devices.area(params.area)
        contact = (params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
        steps = [(PLACE, {"sphere": k, "x": float(x), "y": float(y), "z": area.z + contact})
                 for k, (x, y) in enumerate(self._grid(params, devices))]
        mount = np.array(params.mount_offset_mm) * 1e-3
        for n, k in enumerate(view_order(params.alphas_deg)):  # the camera over the grid's centre at each alpha
            a = math.radians(params.alphas_deg[k - 1])
            x, y = np.array(area.centre) - rot(a) @ mount
            steps.append((VIEW, {"pose": k, "x": float(x), "y": float(y), "z": params.view_z_mm * 1e-3, "alpha": a,
                                 "budget": n >= 2}))  # pose 1 and the widest turn: what the model needs
        return [Step(i, action, dict(args, camera=area.camera)) for i, (action, args) in enumerate(steps)]

    def execute(self, step: Step, params: OnboardCameraParams, devices: Devices, history=()) -> StepResult:
        return execute_split(self, step, params, devices, history)

    # the step in parts (Pipelines): a view's spheres are found while the arm makes the next view's move; a place
    # does not split (its capture does the whole step) and never overlaps
    def approach(self, step: Step, params: OnboardCameraParams, devices: Devices, history=()) -> None:
        a = step.args
        if step.action == VIEW:
            devices.arm.move_linear(Pose(a["x"], a["y"], a["z"], a["alpha"]))

    def capture(self, step: Step, params: OnboardCameraParams, devices: Devices, history=()) -> dict | StepResult:
        a = step.args
        if step.action == PLACE:
            contact = (params.supply_z_mm + params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
            pick_sphere(devices, tuple(v * 1e-3 for v in params.supply_mm), contact, 0.0)
            reported = place_sphere(devices, Pose(a["x"], a["y"], a["z"], 0.0))
            return StepResult({"step": step.index, "set": PLACE, "status": "ok", "sphere": a["sphere"],
                               "x_mm": reported.x * 1e3, "y_mm": reported.y * 1e3, "message": ""})
        camera = devices.camera(a["camera"])
        reported = devices.arm.pose()
        return {"reported": reported, "frame": camera.capture(), "resolution": camera.resolution}

    def measure(self, step: Step, captured: dict | StepResult, params: OnboardCameraParams,
                history=()) -> StepResult:
        if isinstance(captured, StepResult):
            return captured
        a = step.args
        reported, frame = captured["reported"], captured["frame"]
        common = {"step": step.index, "set": VIEW, "camera": a["camera"], "frame_id": frame.frame_id, "pose": a["pose"],
                  "alpha_deg": math.degrees(reported.alpha), "x_mm": reported.x * 1e3, "y_mm": reported.y * 1e3}
        try:
            blobs = find_blobs(frame.image)
        except VisionError as exc:
            return StepResult(dict(common, status="no-feature", message=str(exc)), [frame])
        placed = {int(r["sphere"]): (r["x_mm"] * 1e-3, r["y_mm"] * 1e-3) for r in history if r["set"] == PLACE}
        rows = [dict(common, status="ok", sphere=k, u_px=b.u, v_px=b.v, diameter_px=b.diameter_px, message="")
                for k, b in self.identify(blobs, placed, reported, params, captured["resolution"])]
        if not rows:
            return StepResult(dict(common, status="no-feature", message="no placed sphere recognised"), [frame])
        return StepResult(rows, [frame])

    def overlaps(self, step: Step) -> bool:
        return step.action == VIEW  # a view needs only the places, all done before the first view

    @staticmethod
    def identify(blobs, placed, reported: Pose, params, resolution):
        """Which sphere is which: predicted from the nominal mount (down-looking, u along x, v against y),
        good to a fraction of the grid pitch; each blob goes to the nearest prediction within half a pitch."""
        centre = (np.array(resolution) - 1) / 2
        mount = np.array(params.mount_offset_mm) * 1e-3
        pixel = params.pixel_um * 1e-6
        back = rot(-reported.alpha)
        found = []
        for k, (x, y) in placed.items():
            rel = back @ (np.array([x, y]) - [reported.x, reported.y]) - mount
            predicted = centre + np.array([rel[0], -rel[1]]) / pixel
            distance = [math.hypot(b.u - predicted[0], b.v - predicted[1]) for b in blobs]
            if distance and min(distance) < 0.5 * min(params.pitch_mm) * 1e-3 / pixel:
                found.append((k, blobs[int(np.argmin(distance))]))
        return found

    # -- accuracy target (calibration/routines/targeted.py) -----------------
    def budget(self, step: Step) -> bool:
        return step.action == VIEW and bool(step.args.get("budget"))

    def enough(self, samples: list[dict], params: OnboardCameraParams) -> bool:
        p = predict_onboard(samples, params)
        return p is not None and p.meets(params.target_um, len(params.alphas_deg), EXCESS)

    def fit(self, samples: list[dict], params: OnboardCameraParams, resolutions=None) -> FitOutcome:
        options = params.model_options()
        cameras = {r.get("camera") for r in samples} - {None, ""}
        size = (resolutions or {}).get(cameras.pop()) if len(cameras) == 1 else None
        outcome = fit_onboard(samples, options, size or (resolutions or {}).get("*"), _working_distance(params),
                              _weights(params))
        placed = [r for r in samples if r.get("set") == PLACE]
        points = targeted.curve([r for r in samples if r.get("set") == VIEW],
                                lambda views: predict_onboard(placed + views, params))
        stats, table, chart = targeted.stopping_report(params.area, points, params.target_um, len(params.alphas_deg),
                                                       EXCESS)
        if not points:  # nothing to predict from, nothing to draw
            stats["samples"] = len({r["pose"] for r in samples if r.get("set") == VIEW})
            stats["reason"] = table["note"] = (
                "the prediction needs the joint adjustment's covariance (joint_adjustment is false): every view "
                "was taken" if not params.joint_adjustment else
                f"too few views to predict ({targeted.MIN_DOF // 2 + 1} needed): every view of the plan was taken")
            outcome.stats["target"] = stats
            return replace(outcome, tables=[*outcome.tables, table])
        outcome.stats["target"] = stats
        return replace(outcome, tables=[*outcome.tables, table], charts=[*outcome.charts, chart])


def _working_distance(params: OnboardCameraParams) -> float | None:
    return params.working_distance_mm * 1e-3 if params.working_distance_mm else None


def _weights(params: OnboardCameraParams) -> "Weights | None":
    return Weights(params.pose_sigma_um * 1e-6, params.placement_sigma_um * 1e-6) if params.joint_adjustment else None


def view_order(alphas_deg) -> list[int]:
    """The poses (1-based, as numbered in `alphas_deg`) in the order they are viewed: pose 1, then by decreasing
    turn from it (the widest first: they pin D best), a tie going to the pose nearer the previous one."""
    turn = [abs(math.remainder(math.radians(a - alphas_deg[0]), 2 * math.pi)) for a in alphas_deg]
    order, left = [0], list(range(1, len(alphas_deg)))
    while left:
        last = math.radians(alphas_deg[order[-1]])
        k = min(left, key=lambda j: (-round(turn[j], 9), abs(math.remainder(math.radians(alphas_deg[j]) - last,
                                                                            2 * math.pi)), j))
        order.append(k)
        left.remove(k)
    return [k + 1 for k in order]


def predict_onboard(samples: list[dict], params: OnboardCameraParams) -> targeted.Prediction | None:
    """The predicted RMS error of a sphere the camera locates, from the views so far (the module's docstring);
    None without the joint adjustment or with too few views to know the floor."""
    if not params.joint_adjustment:
        return None
    views = [r for r in samples if r.get("set") == VIEW and r.get("status", "ok") == "ok"]
    if len({int(r["pose"]) for r in views}) < 2:
        return None
    try:
        model = fit_onboard([dict(r) for r in samples], params.model_options(), None, _working_distance(params),
                            _weights(params)).model
        uncertainty = MapUncertainty.from_dict(model["uncertainty"])
    except (CalibrationInputError, np.linalg.LinAlgError, ValueError, KeyError):
        return None
    uv = np.array([[float(r["u_px"]), float(r["v_px"])] for r in views])
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    places = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 7), np.linspace(lo[1], hi[1], 7)), -1).reshape(-1, 2)
    map_var = float(np.mean(np.square(uncertainty.std(places))))
    # (I - R) dD at the plan's turns from pose 1: mean |.|^2 = (2 - 2 cos turn) trace(Cov D)
    turns = np.radians(np.asarray(params.alphas_deg, dtype=float) - params.alphas_deg[0])
    d_var = float(np.mean(2.0 - 2.0 * np.cos(turns))) * float(np.trace(np.asarray(model["d_covariance_um2"]))) * 1e-12
    sigma = math.hypot(model["view_sigma_um"], model["sphere_sigma_um"]) * 1e-6
    n = len({int(r["pose"]) for r in views})
    return targeted.prediction(n, sigma, int(model["view_dof"]), map_var + d_var, 2 * (len(params.alphas_deg) - 1))


def fit_onboard(samples: list[dict], options: PlanarModelOptions, image_size=None,
                working_distance: float | None = None, adjust: "Weights | None" = None) -> FitOutcome:
    """`working_distance` (m, the lens's nominal): correct each sphere for its height from its apparent
    diameter (`models.sphere_height`; rows need `diameter_px`); None: no correction.
    `adjust`: refine the map, D and the spheres' positions together over every pose (`_adjust`); None:
    the seed's procedure, the map from pose 1 alone and c* from eq. (4)."""
    placed = {int(r["sphere"]): np.array([r["x_mm"], r["y_mm"]]) * 1e-3 for r in samples if r["set"] == PLACE}
    views = [r for r in samples if r["set"] == VIEW and r.get("status", "ok") == "ok"]
    poses = sorted({int(r["pose"]) for r in views})
    if len(poses) < 2:
        raise CalibrationInputError(f"views from {len(poses)} pose(s); the rotation axis needs at least 2")
    by_pose = {k: [r for r in views if int(r["pose"]) == k] for k in poses}
    first = by_pose[poses[0]]
    P = {k: np.array([by_pose[k][0]["x_mm"], by_pose[k][0]["y_mm"]]) * 1e-3 for k in poses}
    alpha = {k: math.radians(by_pose[k][0]["alpha_deg"]) for k in poses}
    uv1 = np.array([[r["u_px"], r["v_px"]] for r in first])
    rel1 = np.array([placed[int(r["sphere"])] for r in first]) - P[poses[0]]
    if image_size is None:
        lo, hi = uv1.min(axis=0), uv1.max(axis=0)
        image_size = (int(round(lo[0] + hi[0] + 1)), int(round(lo[1] + hi[1] + 1)))
    camera = fit_planar_map(uv1, rel1, image_size, options)  # pixels -> position relative to the gripper at P1
    heights, dz = None, {}
    if working_distance is not None:
        diameter_column(views)  # every view needs its diameter (a clear error otherwise)
        for _ in range(2):  # the heights need the map's scale, the map the heights: twice is converged
            d1 = diameter_column(first)
            heights = SphereHeights.for_map(camera.map, uv1, d1, working_distance)
            dz = _mean_heights(views, camera.map, heights)
            plane = heights.to_map_plane(rel1, np.array([dz[int(r["sphere"])] for r in first]))
            camera = fit_planar_map(uv1, plane, image_size, options)

    joint = None
    if adjust is not None:
        joint = _adjust(camera, views, placed, P, alpha, poses[0], heights, dz, adjust)
        camera_map = camera.map_with(joint["theta"], [(r["u_px"], r["v_px"]) for r in views])  # every view fits it
    else:
        camera_map = camera.map

    def seen(r) -> np.ndarray:
        """Position of the sphere of row r relative to the gripper (its frame at that pose)."""
        xy = camera_map.pixel_to_plane([r["u_px"], r["v_px"]])
        return (xy if heights is None else heights.to_true(xy, np.array([dz[int(r["sphere"])]])))[0]

    a_first = {int(r["sphere"]): seen(r) for r in first}

    def equations(k):
        """Rows of eq. (4) for pose k: (R_k - I) D = P_k - P_1 + R_k A_(b) - A_(a)."""
        R = rot(alpha[k] - alpha[poses[0]])
        lhs, rhs = [], []
        for r in by_pose[k]:
            s = int(r["sphere"])
            if s not in a_first:
                continue
            b = seen(r)
            lhs.append(R - np.eye(2))
            rhs.append(P[k] - P[poses[0]] + R @ b - a_first[s])
        return lhs, rhs

    def solve(ks):
        lhs, rhs = [], []
        for k in ks:
            left, right = equations(k)
            lhs += left
            rhs += right
        return np.linalg.lstsq(np.vstack(lhs), np.concatenate(rhs), rcond=None)[0]

    others = poses[1:]
    estimates = {"c*": joint["D"] if joint else solve(others), **{f"c{k}": solve([k]) for k in others}}

    def errors(D, k, reference):
        """Eq. (5) at pose k against `reference` (sphere -> absolute position), for every sphere seen at both."""
        R = rot(alpha[k] - alpha[poses[0]])
        out = []
        for r in by_pose[k]:
            s = int(r["sphere"])
            if s in reference:
                b = seen(r)
                out.append(np.linalg.norm(P[k] + (np.eye(2) - R) @ D + R @ b - reference[s]))
        return np.array(out)

    # The cross-reference test of Tables IV-VI: E_jk against A_(0)j = P_1 + A_(a)j, the position seen at pose 1
    # (the seed's definition; the sphere's placement error cancels, as it is the same sphere at every pose).
    seen_first = {s: P[poses[0]] + a for s, a in a_first.items()}
    table = {kind: {f"p{k}": {} for k in others} for kind in ("rms_um", "max_um", "mean_um")}
    for name, D in estimates.items():
        for k in others:
            e = errors(D, k, seen_first) * 1e6
            table["rms_um"][f"p{k}"][name] = float(np.sqrt(np.mean(e**2)))
            table["max_um"][f"p{k}"][name] = float(e.max())
            table["mean_um"][f"p{k}"][name] = float(e.mean())
    # Absolute accuracy: eq. (5) against where the spheres were placed (includes their placement error).
    all_errors = np.concatenate([errors(estimates["c*"], k, placed) for k in others])
    D = estimates["c*"]
    stats = {"calibration": error_stats(np.linalg.norm(camera.residuals, axis=1)[camera.inliers]),
             "verification": error_stats(all_errors), "cross_reference": table}
    model = {"kind": "onboard-camera", "plane_unit": "m", "d_x_um": float(D[0] * 1e6), "d_y_um": float(D[1] * 1e6),
             "alpha1_deg": math.degrees(alpha[poses[0]]), "map": camera_map.to_dict(),
             "sphere_heights": heights.to_dict() if heights else None,
             "estimates_um": {n: (v * 1e6).tolist() for n, v in estimates.items()}}
    if joint is not None:  # what a check needs to tell drift from noise
        n = len(joint["theta"])
        cov, noise = joint["covariance"], joint["noise"]
        model.update(uncertainty=camera.uncertainty_with(joint["theta"], cov[:n, :n], noise["view_sigma"],
                                                         joint["dof"]).to_dict(),
                     d_covariance_um2=(cov[n:, n:] * 1e12).tolist(), d_map_covariance=(cov[:n, n:] * 1e6).tolist(),
                     view_sigma_um=noise["view_sigma"] * 1e6, sphere_sigma_um=noise["sphere_sigma"] * 1e6,
                     # the views' common noise is known from this many numbers only (each view's mean residual)
                     view_dof=2 * (len(poses) - 1), alphas_deg=[math.degrees(alpha[k]) for k in poses])
    rejected = [{"step": r.get("step"), "reason": r.get("message") or r.get("status")}
                for r in samples if r.get("status", "ok") != "ok"]
    return FitOutcome(model, stats, rejected, tables=[*radial_error_tables(stats), *cross_reference_tables(table)])


def cross_reference_tables(table: dict) -> list[dict]:
    """Seed 001 Tables IV-VI: the error at each pose p_k with the axis located from pose l alone (c_l) or from
    all poses (c*), ours beside the seed's."""
    out = []
    for kind, seed, title in (("rms_um", SEED_TABLE_IV, "IV, RMS"), ("max_um", SEED_TABLE_V, "V, maximum"),
                              ("mean_um", {}, "VI, mean")):
        estimates = list(next(iter(table[kind].values())))
        rows = []
        for pose, ours in table[kind].items():
            for source, values in (("cellctl", ours), ("seed 001", seed.get(pose))):
                shown = [values.get(e) for e in estimates] if values else []
                known = [v for v in shown if v is not None]
                if known:
                    rows.append([pose if source == "cellctl" else "", source,
                                 *(None if v is None else round(v, 1) for v in shown),
                                 round(min(known), 1), round(max(known), 1)])
        out.append({"title": f"Cross-reference test (seed Table {title} error, µm)",
                    "columns": ["pose", "source", *estimates, "min", "max"], "rows": rows})
    out[0]["note"] = ("Error of eq. (5) at pose p_k against the sphere's position seen at pose 1 (E_jk of the seed); "
                      "the verification figures compare with where the spheres were placed instead.")
    return out


def _mean_heights(views, map_, heights: SphereHeights) -> dict[int, float]:
    """Each sphere's height over the map's plane, averaged over every pose that saw it."""
    out: dict[int, list[float]] = {}
    for r in views:
        dz = heights.dz(map_, [[r["u_px"], r["v_px"]]], [float(r["diameter_px"])])[0]
        out.setdefault(int(r["sphere"]), []).append(dz)
    return {k: float(np.mean(v)) for k, v in out.items()}


@dataclass(frozen=True)
class Weights:
    """Standard deviations of the joint adjustment's two kinds of residual (m)."""

    pose: float  # a sphere seen from one pose: the robot's repeatability there, per axis
    placement: float  # a sphere's rest position about where it was placed: placement + centring + repeatability


def _adjust(camera, views, placed, P, alpha, first_pose, heights, dz, weights: Weights) -> dict:
    """The map, D and every sphere's rest position X_s from all poses at once.

    Eq. (5) for each view, P_k + (I - R_k) D + R_k b_ks = X_s, with b_ks the mapped pixel, and the
    prior X_s = placed_s. The spheres do not move between poses, so seeing each one through several
    parts of the image at several rotations pins the map's shape far better than the placed positions
    (each off by its placement error) can; those only fix the frame. Starts from pose 1's map."""
    spheres = sorted({int(r["sphere"]) for r in views} & set(placed))
    index = {s: i for i, s in enumerate(spheres)}
    rows = [r for r in views if int(r["sphere"]) in index]
    uv = np.array([[r["u_px"], r["v_px"]] for r in rows], dtype=float)
    which = np.array([index[int(r["sphere"])] for r in rows])
    R = np.array([rot(alpha[int(r["pose"])] - alpha[first_pose]) for r in rows])
    Pk = np.array([P[int(r["pose"])] for r in rows])
    heights_of = np.array([dz[int(r["sphere"])] for r in rows]) if heights is not None else None
    X0 = np.array([placed[s] for s in spheres])
    theta0 = camera.theta
    n = len(theta0)

    def residuals(p):
        theta, D, X = p[:n], p[n:n + 2], p[n + 2:].reshape(-1, 2)
        b = camera.pixel_to_plane_with(theta, uv)
        if heights is not None:
            b = heights.to_true(b, heights_of)
        seen = Pk + (np.eye(2) - R) @ D + np.einsum("nij,nj->ni", R, b)
        return np.concatenate([((seen - X[which]) / weights.pose).ravel(), ((X - X0) / weights.placement).ravel()])

    start = np.concatenate([theta0, [0.0, 0.0], X0.ravel()])
    result = least_squares(residuals, start, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    if not result.success:
        raise CalibrationInputError(f"on-board camera: the joint adjustment did not converge ({result.message})")
    dof = max(len(result.fun) - len(result.x), 1)
    pose_of = np.array([int(r["pose"]) for r in rows])
    J = result.jac
    same_view = np.kron((pose_of[:, None] == pose_of[None, :]).astype(float), np.eye(2))
    seen = slice(0, 2 * len(rows))
    noise = view_noise(result.fun, J, same_view, weights.pose)
    # The parameters' covariance under the noise the residuals show: each sphere's own, plus the part common to
    # every sphere of one view (the arm's error there moves the camera), which the fit's weights took as
    # independent. A sandwich, (J'J)^-1 J' S J (J'J)^-1, with S the weighted residuals' covariance.
    S = np.eye(len(result.fun))
    S[seen, seen] = (noise["sphere_sigma"] ** 2 * np.eye(2 * len(rows)) + noise["view_sigma"] ** 2 * same_view) \
        / weights.pose ** 2
    bread = np.linalg.pinv(J.T @ J)
    covariance = bread @ J.T @ S @ J @ bread
    return {"theta": result.x[:n], "D": result.x[n:n + 2], "X": dict(zip(spheres, result.x[n + 2:].reshape(-1, 2))),
            "covariance": covariance[:n + 2, :n + 2], "dof": dof, "noise": noise}


def view_noise(weighted: np.ndarray, J: np.ndarray, same_view: np.ndarray, pose_weight: float) -> dict:
    """Per axis, the part of the views' residuals common to every sphere of one view (the arm's error there moves
    the camera, and with it every sphere seen) and the part of each sphere alone (m), from the adjustment's
    weighted residuals `weighted` (seen rows first, then the placement priors) and its Jacobian J.

    By moments that count what the fit absorbed: the residuals are M = I - H of the noise (H the hat matrix), so
    for the within-view and the between-view sums Q, E[r' Q r] = tr(Q M S M'), linear in the two variances. The
    fit takes up a share of each, most of all of the few views' common errors, which plain sums would miss."""
    n, N = same_view.shape[0], len(weighted)
    M = np.eye(N) - J @ np.linalg.pinv(J.T @ J) @ J.T

    def padded(block):
        out = np.zeros((N, N))
        out[:n, :n] = block
        return out

    sphere_part, view_part = padded(np.eye(n)), padded(same_view)  # noise covariances per unit variance (seen)
    prior_part = np.eye(N) - sphere_part  # the priors' noise, at the variance their weights assume (1)
    between = same_view / same_view.sum(axis=1)[:, None]  # each row's view mean
    A, b = [], []
    for Q in (padded(np.eye(n) - between), padded(between)):
        MQM = M.T @ Q @ M
        A.append([np.trace(MQM @ sphere_part), np.trace(MQM @ view_part)])  # per m², in weighted units / pose²
        b.append(float(weighted @ Q @ weighted) - np.trace(MQM @ prior_part))
    sphere, common = np.linalg.solve(np.array(A), np.array(b)) * pose_weight ** 2
    return {"view_sigma": math.sqrt(max(common, 0.0)), "sphere_sigma": math.sqrt(max(sphere, 0.0))}
