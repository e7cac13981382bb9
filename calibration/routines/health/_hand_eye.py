"""calibration-check of a hand-eye calibration (target `hand-eye:<camera>`): was the camera bumped, or the board moved?

Collect: a few poses (`hand_eye_poses`), planned by the hand-eye routine's own planner (six_axis/_poses.py) in the
region the calibration itself describes: the board where its Y puts it, the camera where its X puts it, its lens.
At each, the flange pose the arm reports and the ChArUco corners the camera sees, by the hand-eye routine's own
step (a frame with too few corners or an ambiguous pose is kept as a refused row, with the reason).

Judge: one adjustment of the reprojection error of every corner, with the calibration's intrinsics and board scale
held as stored, for a 6-DOF correction of X and one of Y (each a turn about the transform's own origin, a camera's
centre or a board's origin, and a shift, both along its parent frame's axes: the flange's for X, the base's for Y).
Each view's flange pose is allowed the arm's stated accuracy (a random effect with that prior, as in the
calibration); the pixel noise is estimated from the residuals. Which transform is which part: eye-in-hand, X is the
camera on the flange and Y the board on the table; eye-to-hand, X is the board on the flange and Y the camera.

Under "nothing moved" each correction is zero within the check's own covariance plus the calibration's (its
covariance with the arm's accuracy as floor: the arm's error differs a little between the calibration's poses and
the check's, and each absorbs its own into X and Y). Each part is tested with its 6-DOF chi-square; a target's
p-value is the smaller of its two (times two), judged at `false_alarm` over the targets checked (Bonferroni), as the
micro cell's check judges its targets. A drifted target names the part that moved (the camera, the board, or both)
and by how much, in mm and deg with their 1-sigma. A hand-eye calibration is not touched up by a check: it is
recalibrated (hand-eye; `intrinsics=stored` keeps the lens).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from pydantic import Field
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.special import chdtrc  # the chi-square tail (scipy.stats takes 0.3 s to import, for one call)

from geometry.charuco import BoardDrawing

from calibration.errors import CalibrationInputError
from calibration.routines.base import Devices, FitOutcome, Params, Step, StepResult

if TYPE_CHECKING:
    from calibration.routines.six_axis.hand_eye import HandEyeParams

# The hand-eye model and routine (and with them scipy.stats) are imported where a hand-eye target is checked, not
# when the check is loaded: `cellctl check` loads the routines a cell file names, the micro cell's too.

NAME = "calibration-check"
PREFIX = "hand-eye:"
SET = "hand-eye"
ACTION = "hand-eye"
# the columns its rows add to the check's samples.csv: those of the hand-eye routine's own step
# (six_axis/_samples.py's SAMPLE_COLUMNS less its intrinsics and touch columns)
COLUMNS = ("pose", "width_px", "height_px", *(f"j{i}_deg" for i in range(1, 7)),
           *(f"flange_{f}" for f in ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")), "corner_id")
COMMON = ("step", "set", "status", "camera", "frame_id", "u_px", "v_px", "message")  # columns the check has already
PARTS = ("camera", "board")
MIN_ARM_M, MIN_ARM_RAD = 1e-5, math.radians(1e-3)  # a view's prior when the calibration states a perfect arm
Triple = tuple[float, float, float]


class HandEyeCheckParams(Params):
    """The check's parameters for hand-eye targets (the micro cell's are calibration_check.CheckParams')."""

    hand_eye_poses: int = Field(6, ge=4, le=30, description="hand-eye targets: poses viewed, planned as the hand-eye "
                                "routine plans them, in the region its calibration describes")
    hand_eye_plan_seed: int = Field(1, ge=0, description="hand-eye targets: draws those poses within the region")
    hand_eye_standoff_mm: float | None = Field(None, gt=50, le=2000, description="hand-eye targets: camera to board "
                                               "distance of the views (default: the hand-eye routine's)")
    hand_eye_target_mm: Triple | None = Field(None, description="hand-eye targets, base frame: eye-in-hand, where "
                                              "the views aim (default: the board's centre, where the calibration put "
                                              "it); eye-to-hand, where the flange's board is shown (default: on the "
                                              "camera's axis, hand_eye_standoff_mm from it)")


def is_target(name: str) -> bool:
    return name.startswith(PREFIX)


def active(devices: Devices) -> list[str]:
    """The hand-eye targets with an active calibration."""
    return sorted(t for t in devices.calibrations if is_target(t))


def camera_of(target: str) -> str:
    return target[len(PREFIX):]


def validate(params, devices: Devices, targets: list[str]) -> None:
    """Refuse, before anything moves: an unknown camera, a target without an active hand-eye calibration (or one
    fitted from pose pairs alone, which keeps no intrinsics), a touch-up asked for."""
    if params.update:
        raise CalibrationInputError("calibration-check: update=true touches up micro-cell calibrations only; a "
                                    "hand-eye calibration that drifted is recalibrated (run hand-eye)")
    for target in targets:
        devices.camera(camera_of(target))  # names the cameras the cell has
        model = devices.calibration(target, NAME)
        if model.get("kind") != "hand-eye":
            raise CalibrationInputError(f"calibration-check: the active calibration of {target} (id "
                                        f"{model.get('calibration_id')}) is not a hand-eye calibration")
        missing = [k for k in ("intrinsics", "covariance", "board", "hand_eye", "world", "mount") if k not in model]
        if missing:
            raise CalibrationInputError(
                f"calibration-check: the active calibration of {target} (id {model.get('calibration_id')}) keeps no "
                f"{', '.join(missing)} (fitted from pose pairs alone?); the check needs a hand-eye calibration made "
                f"from images: run hand-eye --param camera={camera_of(target)}")


# -- plan and collect ----------------------------------------------------------------------------------------------
def _drawing(model: dict) -> BoardDrawing:
    b = model["board"]
    return BoardDrawing(tuple(b["squares"]), b["square_mm"] * 1e-3, b["marker_mm"] * 1e-3, b["dictionary"],
                        int(b["first_marker"]))


def routine_params(model: dict, params: HandEyeCheckParams) -> HandEyeParams:
    """The hand-eye routine's parameters for the check's views: its board, mount and lens as the calibration found
    them, the region around where its X and Y put the camera and the board, the routine's defaults otherwise."""
    from calibration.models import hand_eye as he
    from calibration.routines.six_axis.hand_eye import HandEyeParams

    X, Y = he.pose_from_dict(model["hand_eye"]), he.pose_from_dict(model["world"])
    drawing = _drawing(model)
    lens = he.Intrinsics.from_dict(model["intrinsics"])
    centre = np.array([*np.asarray(drawing.size_m) / 2 * float(model.get("board_scale", 1.0)), 0.0])
    standoff = params.hand_eye_standoff_mm or HandEyeParams.model_fields["standoff_mm"].default
    mount, camera_mm = X.copy(), None
    if model["mount"] == "eye-in-hand":
        target = Y[:3, :3] @ centre + Y[:3, 3]
    else:  # X: the flange's board, aimed at by its centre; Y: the fixed camera
        mount[:3, 3] = X[:3, :3] @ centre + X[:3, 3]
        camera_mm = tuple(float(v) for v in Y[:3, 3] * 1e3)
        target = Y[:3, 3] + standoff * 1e-3 * Y[:3, 2]
    if params.hand_eye_target_mm is not None:
        target = np.asarray(params.hand_eye_target_mm) * 1e-3
    pixel_um = HandEyeParams.model_fields["pixel_um"].default
    return HandEyeParams(
        mount=model["mount"], camera=model["camera"], poses=params.hand_eye_poses, verify_poses=0,
        intrinsics="stored", squares=tuple(drawing.squares), square_mm=drawing.square_m * 1e3,
        marker_mm=drawing.marker_m * 1e3, dictionary=drawing.dictionary, first_marker=drawing.first_marker,
        target_mm=tuple(float(v) for v in target * 1e3), standoff_mm=standoff,
        mount_mm=tuple(float(v) for v in mount[:3, 3] * 1e3),
        mount_rotation_deg=tuple(float(v) for v in Rotation.from_matrix(mount[:3, :3]).as_euler("xyz", degrees=True)),
        camera_mm=camera_mm, focal_mm=lens.fx * pixel_um * 1e-3, pixel_um=pixel_um,
        plan_seed=params.hand_eye_plan_seed, touches=0)


def plan(params: HandEyeCheckParams, devices: Devices, targets: list[str]) -> list[tuple[str, dict]]:
    from calibration.models import hand_eye as he
    from calibration.routines.six_axis.hand_eye import HandEye

    steps = []
    for target in targets:
        model = devices.calibrations[target]
        lens = he.Intrinsics.from_dict(model["intrinsics"])
        poses = HandEye().pose_plan(routine_params(model, params), (lens.width, lens.height)).poses
        steps += [(ACTION, {"set": SET, "target": target, "camera": camera_of(target), "pose": f"c{k + 1:02d}",
                            "joints": [float(v) for v in p.joints]}) for k, p in enumerate(poses)]
    return steps


def execute(step: Step, params: HandEyeCheckParams, devices: Devices) -> StepResult:
    """One pose: the hand-eye routine's own step (move, the flange pose reported, the corners seen)."""
    from calibration.routines.six_axis.hand_eye import HandEye

    a = step.args
    model = devices.calibration(a["target"], NAME)
    taken = HandEye().execute(Step(step.index, "pose", {"pose": a["pose"], "set": "cal", "joints": a["joints"]}),
                              routine_params(model, params), devices)
    rows = [dict({k: v for k, v in r.items() if k in COLUMNS or k in COMMON}, set=SET) for r in taken.rows]
    return StepResult(rows, taken.frames)


def read(samples: list[dict]) -> bool:
    """Whether these are a hand-eye check's samples."""
    return any(r.get("set") == SET for r in samples)


# -- judge -----------------------------------------------------------------------------------------------------------
@dataclass
class Part:
    """One part's correction: `delta` (turn as a rotation vector, rad, then shift, m, both along the parent frame's
    axes) and its covariance under "nothing moved" (the check's plus the calibration's with the arm's floor)."""

    name: str  # camera | board
    transform: str  # X | Y
    frame: str  # the parent frame: flange | base
    delta: np.ndarray
    cov: np.ndarray
    statistic: float
    p_value: float

    def figures(self) -> dict:
        sd = np.sqrt(np.clip(np.diag(self.cov), 0, None))
        turn, shift = self.delta[:3], self.delta[3:]
        return {"transform": self.transform, "frame": self.frame,
                "translation_mm": [float(v * 1e3) for v in shift],
                "translation_std_mm": [float(v * 1e3) for v in sd[3:]],
                "rotation_deg": [float(math.degrees(v)) for v in turn],
                "rotation_std_deg": [float(math.degrees(v)) for v in sd[:3]],
                "shift_mm": float(np.linalg.norm(shift) * 1e3),
                "shift_std_mm": float(_along(shift, self.cov[3:, 3:]) * 1e3),
                "turn_deg": float(math.degrees(np.linalg.norm(turn))),
                "turn_std_deg": float(math.degrees(_along(turn, self.cov[:3, :3]))),
                "chi2": self.statistic, "dof": 6, "p_value": self.p_value}


def _along(v: np.ndarray, C: np.ndarray) -> float:
    """1-sigma of a vector's length: along its direction (a vector near zero: the mean over the axes)."""
    n = float(np.linalg.norm(v))
    if n < 1e-15:
        return float(math.sqrt(max(np.trace(C) / 3, 0.0)))
    u = v / n
    return float(math.sqrt(max(u @ C @ u, 0.0)))


@dataclass
class Estimate:
    target: str
    mount: str
    parts: dict[str, Part]
    p_value: float
    readings: dict
    per_pose: list[dict]


def judge(samples: list[dict], params, calibrations: dict[str, dict]) -> FitOutcome:
    by_target: dict[str, list[dict]] = {}
    for r in samples:
        if r.get("set") == SET:
            by_target.setdefault(f"{PREFIX}{r['camera']}", []).append(r)
    asked = None if params.targets is None else [t.strip() for t in params.targets.split(",") if t.strip()]
    targets = [t for t in by_target if asked is None or t in asked]
    if not targets:
        raise CalibrationInputError("calibration-check: no hand-eye target was read")
    estimates = {t: estimate(by_target[t], calibrations[t], t) for t in targets}
    threshold = params.false_alarm / len(targets)
    drifted = [t for t in targets if estimates[t].p_value < threshold]
    actions, drift, test = {}, {}, {}
    for t, e in estimates.items():
        moved = [name for name, part in e.parts.items() if t in drifted and min(1.0, 2 * part.p_value) < threshold]
        drift[t] = _drift_figures(e, moved)
        actions[t] = _action(t, e, moved)
        test[t] = {"p_value": e.p_value, "drifted": t in drifted,
                   **{name: {"p_value": p.p_value, "chi2": p.statistic, "dof": 6} for name, p in e.parts.items()}}
    test.update(p_value={t: e.p_value for t, e in estimates.items()}, alpha=params.false_alarm, threshold=threshold,
                tests=len(targets))
    stats = {"drift": drift, "test": test, "readings": {t: e.readings for t, e in estimates.items()}, "touch_up": {}}
    checked = {t: calibrations[t].get("calibration_id") for t in targets}
    summary = {"verdict": "drift" if drifted else "ok", "drifted": drifted, "actions": actions, "checked": checked,
               "updated": {}}
    rejected = [{"step": r.get("step"), "pose": r.get("pose"), "reason": r.get("message") or r.get("status")}
                for r in samples if r.get("set") == SET and r.get("status") != "ok"]
    model = {"kind": "check", "targets": targets, "parameters": [f"{t}.{p}" for t in targets for p in PARTS]}
    tables = [_verdict_table(estimates, drift, test, actions, checked), _pose_table(estimates)]
    return FitOutcome(model, stats, rejected, tables=tables, summary=summary)


def estimate(rows: list[dict], model: dict, target: str) -> Estimate:
    """The corrections of X and Y from a target's readings, each part's test against the calibration."""
    from calibration.models import hand_eye as he
    from calibration.routines.six_axis import _samples as samples_

    data = samples_.image_samples([dict(r, set="cal") for r in rows])
    views = data.views["cal"]
    he.check_motion([v.T_base_flange for v in views])  # a check of too few, too alike views is refused, saying why
    lens = he.Intrinsics.from_dict(model["intrinsics"])
    points = _drawing(model).corners() * float(model.get("board_scale", 1.0))
    X0, Y0 = he.pose_from_dict(model["hand_eye"]), he.pose_from_dict(model["world"])
    accuracy = model.get("arm_accuracy") or {"mm": 0.1, "deg": 0.01}
    arm = (max(accuracy["mm"] * 1e-3, MIN_ARM_M), max(math.radians(accuracy["deg"]), MIN_ARM_RAD))
    fit = _Adjustment(views, points, lens, X0, Y0, model["mount"], arm).solve()
    stored = _stored_covariance(model, X0, Y0)
    mine = _to_parent(fit.cov, X0, Y0)
    delta = np.concatenate([X0[:3, :3] @ fit.x[:3], fit.x[3:6], Y0[:3, :3] @ fit.x[6:9], fit.x[9:12]])
    physical = {"X": "camera", "Y": "board"} if model["mount"] == "eye-in-hand" else {"X": "board", "Y": "camera"}
    frames = {"X": "flange", "Y": "base"}
    parts = {}
    for k, T in enumerate(("X", "Y")):
        block = slice(6 * k, 6 * k + 6)
        d, C = delta[block], mine[block, block] + stored[block, block]
        statistic = float(d @ np.linalg.solve(C, d))
        parts[physical[T]] = Part(physical[T], T, frames[T], d, C, statistic, float(chdtrc(6, statistic)))
    parts = {name: parts[name] for name in PARTS}
    p_value = min(1.0, 2 * min(p.p_value for p in parts.values()))
    readings = {"n_poses": len(views), "n_corners": int(sum(len(v.ids) for v in views)), "rms_px": fit.rms_px,
                "sigma_px": fit.sigma_px, "arm_prior_mm": arm[0] * 1e3, "arm_prior_deg": math.degrees(arm[1])}
    return Estimate(target, model["mount"], parts, p_value, readings, fit.per_pose)


def _stored_covariance(model: dict, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """The calibration's covariance of X and Y (12 x 12, turns along the parent frames' axes), with the arm's
    accuracy added to each as the floor that the calibration's own sigmas carry."""
    names = list(model["covariance"]["names"])
    wanted = [f"{T}_{a}" for T in ("X", "Y") for a in ("rx", "ry", "rz", "x", "y", "z")]
    index = [names.index(n) for n in wanted]
    C = np.asarray(model["covariance"]["matrix"], dtype=float)[np.ix_(index, index)]
    C = _to_parent(C, X, Y)
    accuracy = model.get("arm_accuracy") or {"mm": 0.0, "deg": 0.0}
    floor = np.r_[[math.radians(accuracy["deg"]) ** 2] * 3, [(accuracy["mm"] * 1e-3) ** 2] * 3]
    return C + np.diag(np.tile(floor, 2))


def _to_parent(C: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """A covariance of (turn in X's own frame, shift, turn in Y's own frame, shift) with the turns along the parent
    frames' axes."""
    A = np.eye(12)
    A[:3, :3], A[6:9, 6:9] = X[:3, :3], Y[:3, :3]
    return A @ C[:12, :12] @ A.T


# -- the adjustment ------------------------------------------------------------------------------------------------
def _perturbed(T0: np.ndarray, p: np.ndarray) -> np.ndarray:
    """T0 turned by rotation vector p[:3] in its own frame and shifted by p[3:] in its parent's (as the calibration
    parameterises X and Y)."""
    T = np.eye(4)
    T[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec(p[:3]).as_matrix()
    T[:3, 3] = T0[:3, 3] + p[3:6]
    return T


def _rigid(p: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(p[:, :3]).as_matrix()
    T[:, :3, 3] = p[:, 3:]
    return T


def _inverse(T: np.ndarray) -> np.ndarray:
    out = np.tile(np.eye(4), (len(T), 1, 1))
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    return out


@dataclass
class _Fit:
    x: np.ndarray
    cov: np.ndarray  # of x[:12]
    sigma_px: float
    rms_px: float
    per_pose: list[dict]


class _Adjustment:
    """Parameters: X's correction (6), Y's (6), each view's flange correction (6, true flange = reported @ D, with a
    zero-mean prior of the arm's accuracy). Residuals: each corner's pixel error over the pixel sigma (re-estimated
    from the residuals), each view's correction over its prior."""

    def __init__(self, views, points, lens, X0, Y0, mount, arm):
        self.views, self.lens, self.X0, self.Y0, self.mount = views, lens, X0, Y0, mount
        self.n = len(views)
        self.view_of = np.concatenate([np.full(len(v.ids), k) for k, v in enumerate(views)])
        self.points = np.concatenate([points[v.ids] for v in views])
        self.uv = np.concatenate([v.uv for v in views])
        self.F = np.array([v.T_base_flange for v in views])
        self.prior = np.r_[[arm[1]] * 3, [arm[0]] * 3]
        self.sigma_px = 0.2

    def project(self, x) -> np.ndarray:
        from calibration.models.hand_eye import distort

        X, Y = _perturbed(self.X0, x[:6]), _perturbed(self.Y0, x[6:12])
        flange = self.F @ _rigid(x[12:].reshape(self.n, 6))
        if self.mount == "eye-in-hand":
            T = _inverse(flange @ X) @ Y
        else:
            T = np.linalg.inv(Y) @ flange @ X
        T = T[self.view_of]
        p = np.einsum("nij,nj->ni", T[:, :3, :3], self.points) + T[:, :3, 3]
        return distort(self.lens, p)

    def residuals(self, x) -> np.ndarray:
        r_img = ((self.project(x) - self.uv) / self.sigma_px).ravel()
        return np.concatenate([r_img, (x[12:].reshape(self.n, 6) / self.prior).ravel()])

    def jacobian(self, x) -> np.ndarray:
        """Central differences (rad and m: one step suits both)."""
        J = np.empty((2 * len(self.uv) + 6 * self.n, len(x)))
        h = 1e-7
        for i in range(len(x)):
            up, down = x.copy(), x.copy()
            up[i] += h
            down[i] -= h
            J[:, i] = (self.residuals(up) - self.residuals(down)) / (2 * h)
        return J

    def solve(self) -> _Fit:
        x = np.zeros(12 + 6 * self.n)
        n_img = 2 * len(self.uv)
        for _ in range(4):  # the pixel sigma from the residuals (its redundancy), until it settles
            x = least_squares(self.residuals, x, jac=self.jacobian, loss="soft_l1", f_scale=3.0, x_scale="jac",
                              method="trf").x
            J = self.jacobian(x)
            Ninv = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
            redundancy = n_img - float(np.sum(Ninv * (J[:n_img].T @ J[:n_img])))
            r = self.residuals(x)[:n_img]
            new = self.sigma_px * math.sqrt(float(np.sum(r ** 2)) / max(redundancy, 1.0))
            settled = abs(math.log(new / self.sigma_px)) < 0.02
            self.sigma_px = new
            if settled:
                break
        x = least_squares(self.residuals, x, jac=self.jacobian, loss="soft_l1", f_scale=3.0, x_scale="jac",
                          method="trf").x
        J = self.jacobian(x)
        cov = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)[:12, :12]
        err = self.project(x) - self.uv
        per_pose = []
        for k, v in enumerate(self.views):
            e = err[self.view_of == k]
            d = x[12 + 6 * k:18 + 6 * k]
            per_pose.append({"pose": v.pose, "n": len(v.ids), "rms_px": float(math.sqrt(np.mean(np.sum(e ** 2, axis=1)))),
                             "arm_correction_mm": float(np.linalg.norm(d[3:]) * 1e3),
                             "arm_correction_deg": float(math.degrees(np.linalg.norm(d[:3])))})
        return _Fit(x, cov, self.sigma_px, float(math.sqrt(np.mean(np.sum(err ** 2, axis=1)))), per_pose)


# -- what the check says ---------------------------------------------------------------------------------------------
def _drift_figures(e: Estimate, moved: list[str]) -> dict:
    """Each part's correction in mm and deg with its 1-sigma, the parts it is attributed to, and (for `cellctl
    health`, which lists every target's dx, dy in µm) the camera's shift and turn."""
    camera = e.parts["camera"].figures()
    t, s = camera["translation_mm"], camera["translation_std_mm"]
    return {"attributed_to": moved, **{name: p.figures() for name, p in e.parts.items()},
            "dx_um": t[0] * 1e3, "dx_std_um": s[0] * 1e3, "dy_um": t[1] * 1e3, "dy_std_um": s[1] * 1e3,
            "dz_um": t[2] * 1e3, "dz_std_um": s[2] * 1e3,
            "rotation_urad": math.radians(camera["turn_deg"]) * 1e6,
            "rotation_std_urad": math.radians(camera["turn_std_deg"]) * 1e6}


def _moved_text(part: Part) -> str:
    f = part.figures()
    where = {"camera": "on its mount" if part.frame == "flange" else "in the cell",
             "board": "on the flange" if part.frame == "flange" else "on the table"}[part.name]
    return f"the {part.name} moved {where} by {f['shift_mm']:.2f} mm, {f['turn_deg']:.3f} deg"


def _action(target: str, e: Estimate, moved: list[str]) -> str:
    if not moved:
        return "ok"
    said = "; ".join(_moved_text(e.parts[name]) for name in moved)
    return f"recalibrate: {said}; run hand-eye --param camera={camera_of(target)} --param mount={e.mount}"


def _pm(values, sds, digits: int) -> str:
    return ", ".join(f"{v:+.{digits}f}" for v in values) + " ± " + ", ".join(f"{s:.{digits}f}" for s in sds)


def _verdict_table(estimates: dict, drift: dict, test: dict, actions: dict, checked: dict) -> dict:
    rows = []
    for t in estimates:
        for name in PARTS:
            f = drift[t][name]
            rows.append([t, checked.get(t), f"{name} ({f['transform']}, in the {f['frame']} frame)",
                         f"{f['p_value']:.3g}", "moved" if name in drift[t]["attributed_to"] else "held",
                         f"{f['shift_mm']:.3f} ± {f['shift_std_mm']:.3f}", f"{f['turn_deg']:.4f} ± {f['turn_std_deg']:.4f}",
                         _pm(f["translation_mm"], f["translation_std_mm"], 3),
                         _pm(f["rotation_deg"], f["rotation_std_deg"], 4),
                         actions[t] if name == PARTS[0] else ""])
    return {"title": "Does the hand-eye calibration still hold? (drift estimate ± 1 σ)",
            "columns": ["target", "calibration", "part", "p-value", "verdict", "shift (mm)", "turn (deg)",
                        "x, y, z (mm)", "turn x, y, z (deg)", "action"],
            "rows": rows,
            "note": f"Drift when a target's p < {test['threshold']:.3g} (its smaller part p-value times two): a "
                    f"false-alarm rate of {test['alpha']:g} for the whole check, shared by its {test['tests']} "
                    "target(s). Each part's correction is a turn about its own origin (a camera's centre, a "
                    "board's origin) and a shift, along the axes of the frame it sits in; its sigma is the check's "
                    "and the calibration's together, with the arm's stated accuracy."}


def _pose_table(estimates: dict) -> dict:
    rows = [[t, p["pose"], p["n"], round(p["rms_px"], 3), round(p["arm_correction_mm"], 4),
             round(p["arm_correction_deg"], 5)] for t, e in estimates.items() for p in e.per_pose]
    return {"title": "Hand-eye check: per pose", "columns": ["target", "pose", "corners", "rms_px",
                                                             "arm_correction_mm", "arm_correction_deg"],
            "rows": rows, "note": "Each view's reprojection error after the correction, and the flange correction "
                                  "it was allowed (the arm's error at that pose)."}
