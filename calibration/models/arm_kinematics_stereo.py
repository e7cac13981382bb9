"""The arm's own geometry from fixed cameras that watch a circle fixture on its flange: kinematic identification in
one adjustment with the cameras (issue 28, the IRB 120 cell of seed 002).

Two (or more) fixed, uncalibrated cameras see a fixture of printed circles on the flange. The centre p_i of circle i
(fixture frame) is seen by camera c at

    uv = project(K_c, dist_c, T_camera_c_base @ T_base_flange(q; table) @ T_flange_fixture @ p_i)

with T_base_flange from the arm's kinematic table (geometry/kinematic_table.py) for the reported joints q. One
adjustment takes every centre in every image of every camera and adjusts the table's identifiable deviations, each
camera's intrinsics (fx, fy, cx, cy, k1, k2, p1, p2) and pose, and the fixture's mount T_flange_fixture. The
fixture's drawing (the circles' positions) is the length reference: cameras see angles only. Each pose keeps a
small shift of the fixture (base frame) with the arm's repeatability as its prior, so the covariance stays honest;
the pixel noise and the repeatability are re-estimated from the residuals (variance components, as
models/hand_eye.py does).

A circle's centre does not project onto the centre of its image ellipse: a tilted circle's near half looks larger.
The ellipse's centre is known in closed form (the pole of the vanishing line: in camera coordinates it is seen along
C_z C - r^2 (e_z - n_z n) for a circle of radius r about C with normal n), and the marks' detector
(calibration/vision/csm_markers.py) reports the mean of the centres of a ring's outer edge (r) and of its inner disc
(r/3); `centre_model="ellipse"` predicts that, `"point"` the projected centre. At 1.2 m the difference is a few
hundredths of a pixel, as large as the detector's noise.

Observability first (`observability`): the Jacobian of the centres with respect to every deviation, with the
cameras' intrinsics and poses and the fixture's mount projected out and each deviation scaled by its budget
(models/arm_kinematics.py); a pivoted QR keeps those above OBSERVABLE_RATIO of the largest deviation's effect. What
it fixes is named by what absorbs it: the cameras' poses (the base joint's zero and height move the whole arm, as
moving every camera does), the fixture's mount (everything after the last joint), or the other deviations
(translations along parallel axes, Hayati's beta where the axes are not parallel).

`sequential` is the usual chain for comparison: each camera calibrated first from the nominal arm's fixture points
(DLT, then OpenCV's calibrateCamera) and frozen, the fixture triangulated by them in every image, then the arm's
deviations, its base and the mount fitted to those points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import linalg, sparse
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative, group_columns  # least_squares' own sparse differences

from geometry.kinematic_table import KinematicTable

from calibration.errors import CalibrationInputError
from calibration.models import hand_eye as he
from calibration.models.arm_kinematics import (
    CORRELATION_SHOWN,
    OBSERVABLE_RATIO,
    budget_scales,
    global_jacobian,
    identifiable,
)

LENS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")  # k3 stays 0: a 1.2 m view of a 0.6 m field needs no more
POSE = ("rx", "ry", "rz", "x", "y", "z")
CENTRE_MODELS = ("ellipse", "point")
INNER = 1.0 / 3.0  # the marks' inner disc, relative to the ring (seed 002 Fig. 3)
GAUGE_TOL = 1e-4  # a deviation whose column a group of parameters reproduces to this share is that group's
GROSS_PX = 0.5  # a centre off by more than this and OUTLIER_Z sigmas is a detection gone wrong, dropped
OUTLIER_Z = 6.0
MIN_POSES = 8
PER_CAMERA = 14  # a camera's parameters: its lens, then its pose


# -- what the adjustment works on ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Fixture:
    """The fixture's drawing: its mount on the flange as drawn (T_flange_fixture), the circles' centres in its frame
    (m; the length reference) and their outer radius (m; the inner disc is a third of it)."""

    mount: np.ndarray
    points: np.ndarray
    radius: float


@dataclass(frozen=True)
class Camera:
    """A fixed camera: its lens (OpenCV's model, k3 = 0) and where the base frame is in it."""

    name: str
    lens: he.Intrinsics
    T_camera_base: np.ndarray

    def to_dict(self) -> dict:
        """The lens and the camera's pose in the base frame (T_base_camera, as an eye-to-hand result is stored)."""
        return {"intrinsics": self.lens.to_dict(), "pose": he.pose_to_dict(he._inv(self.T_camera_base))}

    @classmethod
    def from_dict(cls, name: str, d: dict) -> Camera:
        return cls(name, he.Intrinsics.from_dict(d["intrinsics"]), he._inv(he.pose_from_dict(d["pose"])))


@dataclass
class Observations:
    """Every circle centre seen: its pose (index into `poses`, `joints`), camera (into `cameras`), circle (into the
    fixture's points) and pixel."""

    poses: list[str]
    joints: np.ndarray  # (n, 6) rad, as the arm reported them
    cameras: tuple[str, ...]
    sizes: dict[str, tuple[int, int]]
    pose_of: np.ndarray
    camera_of: np.ndarray
    point_of: np.ndarray
    uv: np.ndarray

    def without(self, drop: np.ndarray) -> Observations:
        keep = ~np.isin(np.arange(len(self.uv)), drop)
        return Observations(self.poses, self.joints, self.cameras, self.sizes, self.pose_of[keep],
                            self.camera_of[keep], self.point_of[keep], self.uv[keep])


@dataclass
class StereoModel:
    """What predicts an image: the cameras, the arm's table and the fixture's mount."""

    cameras: list[Camera]
    table: KinematicTable
    mount: np.ndarray  # T_flange_fixture
    centre_model: str = "ellipse"

    def fixture_poses(self, joints) -> np.ndarray:
        """(n, 4, 4) T_base_fixture."""
        return self.table.forward_batch(np.atleast_2d(joints)) @ self.mount

    def to_dict(self) -> dict:
        return {"table": self.table.to_dict(), "tool": he.pose_to_dict(self.mount),
                "cameras": {c.name: c.to_dict() for c in self.cameras}, "centre_model": self.centre_model}

    @classmethod
    def from_dict(cls, d: dict) -> StereoModel:
        return cls([Camera.from_dict(n, c) for n, c in d["cameras"].items()], KinematicTable.from_dict(d["table"]),
                   he.pose_from_dict(d["tool"]), d.get("centre_model", "point"))


@dataclass
class StereoResult:
    model: StereoModel  # calibrated
    nominal: KinematicTable
    identified: list[str]  # deviation names, in the table's order
    fixed: list[str]
    gauge: dict[str, list[str]]  # what absorbs each fixed deviation -> the deviations
    values: dict[str, float]  # identified deviations (m or rad)
    sigma: dict[str, float]  # their 1-sigma (m or rad)
    correlations: list[tuple[str, str, float]]
    observability: dict
    rms_px: float
    noise: dict
    per_pose: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    camera_frame_sigma_mm: float | None = None  # the fixture's position in the first camera's frame, RMS 1-sigma


# -- projection ------------------------------------------------------------------------------------------------------
def image_centres(lens: he.Intrinsics, T_camera_fixture: np.ndarray, points: np.ndarray, radius: float,
                  centre_model: str = "ellipse") -> np.ndarray:
    """(m, 2) px: where the detector sees circles of `radius` about `points` (fixture frame, their plane the
    fixture's x-y) through poses T_camera_fixture (m, 4, 4) (module docstring)."""
    R, t = T_camera_fixture[:, :3, :3], T_camera_fixture[:, :3, 3]
    C = np.einsum("mij,mj->mi", R, points) + t
    if centre_model == "point" or radius <= 0:
        return he.distort(lens, C)
    n = R[:, :, 2]
    along = -n[:, 2:3] * n  # e_z - n_z n: the optical axis within the circle's plane
    along[:, 2] += 1.0
    xy = np.zeros((len(C), 2))
    for r in (radius, radius * INNER):
        h = C[:, 2:3] * C - r * r * along
        xy += 0.5 * h[:, :2] / h[:, 2:3]
    return he.distort(lens, np.column_stack([xy, np.ones(len(xy))]))


def predict(model: StereoModel, fixture: Fixture, joints: np.ndarray, pose_of, camera_of, point_of,
            shifts: np.ndarray | None = None) -> np.ndarray:
    """(m, 2) px of the centres (pose, camera, circle) through `model`; `shifts` (n, 3): the fixture moved in the base
    frame at each pose (the arm's repeatability)."""
    T = model.fixture_poses(joints)
    if shifts is not None:
        T = T.copy()
        T[:, :3, 3] += shifts
    out = np.zeros((len(pose_of), 2))
    for c, camera in enumerate(model.cameras):
        rows = np.flatnonzero(camera_of == c)
        if len(rows):
            out[rows] = image_centres(camera.lens, camera.T_camera_base[None] @ T[pose_of[rows]],
                                      fixture.points[point_of[rows]], fixture.radius, model.centre_model)
    return out


# -- the adjustment --------------------------------------------------------------------------------------------------
class StereoProblem:
    """x: per camera its lens (8) and pose (6: rotation vector in its own frame and translation of T_camera_base),
    the mount (6, the same for T_flange_fixture), the free deviations over their budgets, then per pose the
    fixture's shift (3, base frame). Residuals: every centre's (u, v) over the pixel sigma, then every shift over the
    arm's repeatability."""

    def __init__(self, obs: Observations, fixture: Fixture, nominal: KinematicTable, cameras0: list[Camera],
                 mount0: np.ndarray, free: np.ndarray, centre_model: str = "ellipse"):
        self.obs, self.fixture, self.nominal = obs, fixture, nominal
        self.cameras0, self.mount0, self.centre_model = cameras0, mount0, centre_model
        self.free = np.flatnonzero(free)
        self.scales = budget_scales(nominal)[self.free]
        self.k_mount = PER_CAMERA * len(cameras0)
        self.k_dev = self.k_mount + 6
        self.n_global = self.k_dev + len(self.free)
        self.n = len(obs.poses)
        self.sigma_px, self.sigma_t = 0.05, 1e-5

    def table(self, x) -> KinematicTable:
        v = self.nominal.vector()
        v[self.free] += x[self.k_dev:self.n_global] * self.scales
        return self.nominal.with_vector(v)

    def model(self, x) -> StereoModel:
        cameras = []
        for c, cam in enumerate(self.cameras0):
            k = PER_CAMERA * c
            lens = cam.lens.with_vector(np.r_[x[k:k + 8], 0.0])
            cameras.append(Camera(cam.name, lens, he._perturbed(cam.T_camera_base, x[k + 8:k + 14])))
        return StereoModel(cameras, self.table(x), he._perturbed(self.mount0, x[self.k_mount:self.k_dev]),
                           self.centre_model)

    def shifts(self, x) -> np.ndarray:
        return x[self.n_global:].reshape(self.n, 3)

    def x0(self) -> np.ndarray:
        x = np.zeros(self.n_global + 3 * self.n)
        for c, cam in enumerate(self.cameras0):
            x[PER_CAMERA * c:PER_CAMERA * c + 8] = cam.lens.vector()[:8]
        return x

    def project(self, x) -> np.ndarray:
        o = self.obs
        return predict(self.model(x), self.fixture, o.joints, o.pose_of, o.camera_of, o.point_of, self.shifts(x))

    def residuals(self, x) -> np.ndarray:
        r_img = ((self.project(x) - self.obs.uv) / self.sigma_px).ravel()
        return np.concatenate([r_img, self.shifts(x).ravel() / self.sigma_t])

    def sparsity(self) -> sparse.csr_matrix:
        o = self.obs
        m = len(o.uv)
        S = sparse.lil_matrix((2 * m + 3 * self.n, self.n_global + 3 * self.n), dtype=int)
        for c in range(len(self.cameras0)):
            rows = np.flatnonzero(np.repeat(o.camera_of == c, 2))
            S[np.ix_(rows, PER_CAMERA * c + np.arange(PER_CAMERA))] = 1
        S[:2 * m, self.k_mount:self.n_global] = 1
        rows = np.arange(2 * m)
        for a in range(3):
            S[rows, self.n_global + 3 * np.repeat(o.pose_of, 2) + a] = 1
        S[2 * m + np.arange(3 * self.n), self.n_global + np.arange(3 * self.n)] = 1
        return S.tocsr()

    def names(self) -> list[str]:
        names = [f"{cam.name}_{p}" for cam in self.cameras0 for p in (*LENS, *POSE)]
        names += [f"mount_{p}" for p in POSE]
        return names + [self.nominal.parameter_names()[i] for i in self.free]


def _jacobian(problem: StereoProblem, x, S=None) -> np.ndarray:
    """The Jacobian of the whitened residuals (no robust weights: the covariance is the model's, not the loss's),
    dense."""
    S = problem.sparsity() if S is None else S
    J = approx_derivative(problem.residuals, x, method="2-point", sparsity=(S, group_columns(S)))
    return J.toarray()


def _global_jacobian(problem: StereoProblem, x) -> np.ndarray:
    """The image rows' Jacobian with respect to the global parameters, by central differences."""
    return global_jacobian(problem.residuals, x, 2 * len(problem.obs.uv), problem.n_global, problem.k_dev, 1e-4)


def observability(problem: StereoProblem, x) -> dict:
    """Which deviations the images can identify, with the singular values and O1, and what absorbs the others
    (module docstring). `problem` must have every deviation free."""
    J = _global_jacobian(problem, x)
    k0 = problem.k_dev
    names = [problem.nominal.parameter_names()[i] for i in problem.free]
    seen = identifiable(J[:, :k0], J[:, k0:], names, OBSERVABLE_RATIO, against_raw=True)  # already over the budgets
    fixed = [names.index(n) for n in seen["fixed"]]
    return dict(seen, gauge=_gauge(J, problem, seen["fixed"], [k0 + i for i in fixed]))


def _gauge(J: np.ndarray, problem: StereoProblem, names: list[str], columns: list[int]) -> dict[str, list[str]]:
    """Each fixed deviation named by what reproduces its effect on the images: the cameras' poses together, the
    fixture's mount, or (neither alone) the other parameters, the other deviations among them."""
    pose_cols = [PER_CAMERA * c + 8 + k for c in range(len(problem.cameras0)) for k in range(6)]
    groups = {"the cameras' poses": pose_cols, "the fixture's mount": list(range(problem.k_mount, problem.k_dev))}
    bases = {g: np.linalg.qr(J[:, cols])[0] for g, cols in groups.items()}
    out: dict[str, list[str]] = {g: [] for g in (*groups, "the other deviations")}
    for name, j in zip(names, columns):
        col = J[:, j]
        norm = max(float(np.linalg.norm(col)), 1e-300)
        owner = next((g for g, Q in bases.items() if np.linalg.norm(col - Q @ (Q.T @ col)) / norm < GAUGE_TOL),
                     "the other deviations")
        out[owner].append(name)
    return out


def _adjust(problem: StereoProblem, x, loss: str, estimate_noise: bool = True):
    """The adjustment, its variance components (pixels, the arm's repeatability) re-estimated until they settle."""
    S = problem.sparsity()
    m = 2 * len(problem.obs.uv)
    groups = [np.arange(m), m + np.arange(3 * problem.n)]

    def jac(x_):
        return _jacobian(problem, x_, S)

    solution = None
    for _ in range(6 if estimate_noise else 0):
        solution = least_squares(problem.residuals, x, jac=jac, loss=loss, f_scale=3.0, x_scale="jac", method="trf",
                                 tr_solver="exact", max_nfev=10)
        x = solution.x
        reds, _ = he._redundancy(jac(x), groups)
        r = problem.residuals(x)
        factors = [float(np.sum(r[g] ** 2) / max(red, 1e-9)) for g, red in zip(groups, reds)]
        new = (problem.sigma_px * math.sqrt(factors[0]),
               float(np.clip(problem.sigma_t * math.sqrt(factors[1]), 1e-6, 5e-4)))
        settled = all(abs(math.log(a / b)) < 0.05 for a, b in zip(new, (problem.sigma_px, problem.sigma_t)))
        problem.sigma_px, problem.sigma_t = new
        if settled:
            break
    solution = least_squares(problem.residuals, x, jac=jac, loss=loss, f_scale=3.0, x_scale="jac", method="trf",
                             tr_solver="exact", max_nfev=100)
    return solution.x, {"pixel_px": problem.sigma_px, "repeatability_mm": problem.sigma_t * 1e3}


def _gross(problem: StereoProblem, x) -> np.ndarray:
    """The centres whose residual stands far out: a detection gone wrong."""
    e = np.linalg.norm(problem.project(x) - problem.obs.uv, axis=1)
    return np.flatnonzero((e > GROSS_PX) & (e > OUTLIER_Z * problem.sigma_px * math.sqrt(2)))


def fit(obs: Observations, fixture: Fixture, nominal: KinematicTable, cameras0: list[Camera],
        free: np.ndarray | None = None, loss: str = "soft_l1", centre_model: str = "ellipse",
        repeatability_m: float = 1e-5) -> StereoResult:
    """The simultaneous adjustment of the arm's identifiable deviations with the cameras and the mount, from
    cameras0 (`start_cameras`) and the drawing's mount. `free`: the deviations to adjust (None: what the images
    identify; none at all gives the nominal arm with the cameras and the mount fitted, the "before" model)."""
    if centre_model not in CENTRE_MODELS:
        raise CalibrationInputError(f"centre_model={centre_model!r}; allowed: {', '.join(CENTRE_MODELS)}")
    _check(obs, fixture)
    if free is None:
        every = np.ones(len(nominal.vector()), dtype=bool)
        probe = StereoProblem(obs, fixture, nominal, cameras0, fixture.mount, every, centre_model)
        seen = observability(probe, probe.x0())
        mask = seen["free_mask"]
    else:
        mask = np.asarray(free, dtype=bool)
        seen = {"gauge": {}, "free_mask": mask, "o1": None, "condition": None}
    rejected: list[dict] = []
    problem = StereoProblem(obs, fixture, nominal, cameras0, fixture.mount, mask, centre_model)
    problem.sigma_t = repeatability_m
    x, noise = _adjust(problem, problem.x0(), loss)
    drop = _gross(problem, x)
    if len(drop):  # once: the rest refitted without them, from where the fit stands
        e = np.linalg.norm(problem.project(x) - obs.uv, axis=1)
        rejected = [{"pose": obs.poses[obs.pose_of[i]], "camera": obs.cameras[obs.camera_of[i]],
                     "circle": int(obs.point_of[i]), "reason": f"centre off by {e[i]:.2f} px, over {OUTLIER_Z:g} "
                     f"sigmas ({problem.sigma_px:.3f} px): a detection gone wrong"} for i in drop]
        model = problem.model(x)
        problem = StereoProblem(obs.without(drop), fixture, nominal, model.cameras, model.mount, mask, centre_model)
        problem.sigma_px, problem.sigma_t = noise["pixel_px"], noise["repeatability_mm"] * 1e-3
        x0 = problem.x0()
        x0[problem.k_dev:] = x[problem.k_dev:]  # the deviations and the shifts as they stand
        x, noise = _adjust(problem, x0, loss)
    return _result(problem, x, noise, seen, rejected)


def _check(obs: Observations, fixture: Fixture) -> None:
    if len(obs.uv) == 0 or not np.all(np.isfinite(obs.uv)):
        raise CalibrationInputError("the circle centres must be finite pixels, and there must be some")
    if obs.point_of.min() < 0 or obs.point_of.max() >= len(fixture.points):
        raise CalibrationInputError(f"a circle index {int(obs.point_of.max())} outside the fixture's "
                                    f"0..{len(fixture.points) - 1}")
    seen = {c: len(np.unique(obs.pose_of[obs.camera_of == k])) for k, c in enumerate(obs.cameras)}
    few = {c: n for c, n in seen.items() if n < MIN_POSES}
    if few:
        raise CalibrationInputError(f"cameras {', '.join(f'{c} ({n})' for c, n in few.items())} saw the fixture in "
                                    f"fewer than the {MIN_POSES} poses an arm calibration needs at the very least "
                                    "(30 or more, from well-spread configurations)")


def _result(problem: StereoProblem, x, noise: dict, seen: dict, rejected: list[dict]) -> StereoResult:
    J = _jacobian(problem, x)
    _, Ninv = he._redundancy(J, [np.arange(2 * len(problem.obs.uv))])
    k0, k1 = problem.k_dev, problem.n_global
    cov = Ninv[k0:k1, k0:k1] * np.outer(problem.scales, problem.scales)
    names = problem.names()[k0:k1]
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.outer(np.maximum(sd, 1e-300), np.maximum(sd, 1e-300))
    correlations = [(names[i], names[j], float(corr[i, j])) for i in range(len(names)) for j in range(i + 1, len(names))
                    if abs(corr[i, j]) > CORRELATION_SHOWN]
    o = problem.obs
    err = problem.project(x) - o.uv
    shifts = problem.shifts(x)
    per_pose = [{"pose": p, "n": int(np.sum(o.pose_of == k)),
                 "rms_px": float(math.sqrt(np.mean(np.sum(err[o.pose_of == k] ** 2, axis=1))))
                 if np.any(o.pose_of == k) else None, "shift_mm": float(np.linalg.norm(shifts[k]) * 1e3)}
                for k, p in enumerate(o.poses)]
    all_names = problem.nominal.parameter_names()
    fixed = [n for n in all_names if n not in names]
    return StereoResult(problem.model(x), problem.nominal, names, fixed, seen["gauge"],
                        dict(zip(names, map(float, x[k0:k1] * problem.scales))), dict(zip(names, map(float, sd))),
                        correlations, seen, float(math.sqrt(np.mean(np.sum(err ** 2, axis=1)))), noise, per_pose,
                        rejected, _camera_frame_sigma(problem, x, Ninv[:k1, :k1]))


def _camera_frame_sigma(problem: StereoProblem, x, cov: np.ndarray) -> float:
    """RMS over the calibration poses of the 1-sigma of the fixture's position in the first camera's frame (mm):
    the camera's own frame is part of it (its principal point trades against its pose and decentring)."""
    Q = problem.obs.joints

    def position(x_):
        m = problem.model(x_)
        return (m.cameras[0].T_camera_base[None] @ m.fixture_poses(Q))[:, :3, 3].ravel()

    G = np.zeros((3 * len(Q), problem.n_global))
    for j in range(problem.n_global):
        h = 1e-4 if j >= problem.k_dev else 1e-6 * max(1.0, abs(x[j]))
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        G[:, j] = (position(xp) - position(xm)) / (2 * h)
    variance = np.einsum("ij,jk,ik->i", G, cov, G).reshape(len(Q), 3).sum(axis=1)
    return float(math.sqrt(np.mean(np.clip(variance, 0, None))) * 1e3)


# -- start values: each camera from the nominal arm's fixture points -------------------------------------------------
def nominal_points(obs: Observations, fixture: Fixture, table: KinematicTable) -> np.ndarray:
    """(m, 3) each observed centre's circle in the base frame, as `table` and the drawing place it."""
    T = table.forward_batch(obs.joints) @ fixture.mount
    T = T[obs.pose_of]
    return np.einsum("mij,mj->mi", T[:, :3, :3], fixture.points[obs.point_of]) + T[:, :3, 3]


def dlt(points: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K and T_camera_world of the 3x4 projection matrix that maps world points to pixels best (the direct linear
    transform, Hartley-normalised, split by an RQ decomposition): no lens guess needed, only points that do not lie
    in a plane."""
    P = np.asarray(points, float)
    x = np.asarray(uv, float)
    mp, sp = P.mean(axis=0), math.sqrt(3) / np.mean(np.linalg.norm(P - P.mean(axis=0), axis=1))
    mx, sx = x.mean(axis=0), math.sqrt(2) / np.mean(np.linalg.norm(x - x.mean(axis=0), axis=1))
    Tp = np.diag([sp, sp, sp, 1.0])
    Tp[:3, 3] = -sp * mp
    Tx = np.diag([sx, sx, 1.0])
    Tx[:2, 2] = -sx * mx
    Ph = (Tp @ np.column_stack([P, np.ones(len(P))]).T).T
    xh = (Tx @ np.column_stack([x, np.ones(len(x))]).T).T
    A = np.zeros((2 * len(P), 12))
    A[0::2, 0:4] = Ph
    A[0::2, 8:12] = -xh[:, 0:1] * Ph
    A[1::2, 4:8] = Ph
    A[1::2, 8:12] = -xh[:, 1:2] * Ph
    M = np.linalg.inv(Tx) @ np.linalg.svd(A)[2][-1].reshape(3, 4) @ Tp
    if np.mean((M @ np.column_stack([P, np.ones(len(P))]).T)[2]) < 0:
        M = -M  # the points in front of the camera
    K, R = linalg.rq(M[:, :3])
    S = np.diag(np.sign(np.diag(K)))  # a positive focal length and a proper rotation
    K, R = K @ S, S @ R
    t = np.linalg.solve(K, M[:, 3])
    if np.linalg.det(R) < 0:
        R, t = -R, -t
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return K / K[2, 2], T


def start_cameras(obs: Observations, fixture: Fixture, table: KinematicTable) -> list[Camera]:
    """Each camera calibrated on its own from the fixture points `table` (the nominal one) places: a DLT, then
    OpenCV's calibrateCamera from it (fx, fy, cx, cy, k1, k2, p1, p2 and the pose). The simultaneous adjustment
    starts here; the usual chain keeps them."""
    P = nominal_points(obs, fixture, table)
    cameras = []
    for c, name in enumerate(obs.cameras):
        rows = obs.camera_of == c
        if np.sum(rows) < 12:
            raise CalibrationInputError(f"camera {name} saw only {int(np.sum(rows))} circle centres; its start needs "
                                        "12 or more, from poses spread in depth (not in one plane)")
        K, T = dlt(P[rows], obs.uv[rows])
        K[0, 1] = 0.0  # OpenCV's camera has square pixel axes (no skew)
        w, h = obs.sizes[name]
        flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera([P[rows].astype(np.float32)],
                                                         [obs.uv[rows].astype(np.float32)], (w, h), K.copy(),
                                                         np.zeros(5), flags=flags)
        T = he._T(cv2.Rodrigues(rvecs[0])[0], tvecs[0].ravel())
        d = dist.ravel()
        lens = he.Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                             (float(d[0]), float(d[1]), float(d[2]), float(d[3]), 0.0))
        cameras.append(Camera(name, lens, T))
    return cameras


# -- the usual chain, for comparison ---------------------------------------------------------------------------------
def triangulate(cameras: list[Camera], obs: Observations, uv: np.ndarray | None = None) -> np.ndarray:
    """(n poses, n circles, 3) base frame: each circle where the rays of the cameras that saw it pass closest
    (least squares over the rays); NaN where fewer than two cameras saw it."""
    uv = obs.uv if uv is None else uv
    n_points = int(obs.point_of.max()) + 1
    A = np.zeros((len(obs.poses), n_points, 3, 3))
    b = np.zeros((len(obs.poses), n_points, 3))
    count = np.zeros((len(obs.poses), n_points), dtype=int)
    for c, cam in enumerate(cameras):
        rows = np.flatnonzero(obs.camera_of == c)
        if not len(rows):
            continue
        xy = cv2.undistortPoints(uv[rows].reshape(-1, 1, 2).astype(np.float64), cam.lens.K(),
                                 np.asarray(cam.lens.dist)).reshape(-1, 2)
        R, t = cam.T_camera_base[:3, :3], cam.T_camera_base[:3, 3]
        d = np.column_stack([xy, np.ones(len(xy))]) @ R  # R^T (x, y, 1): the ray in the base frame
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        centre = -R.T @ t
        M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
        np.add.at(A, (obs.pose_of[rows], obs.point_of[rows]), M)
        np.add.at(b, (obs.pose_of[rows], obs.point_of[rows]), M @ centre)
        np.add.at(count, (obs.pose_of[rows], obs.point_of[rows]), 1)
    X = np.full(b.shape, np.nan)
    ok = count >= 2
    X[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return X


def sequential(obs: Observations, fixture: Fixture, nominal: KinematicTable, cameras: list[Camera],
               free_mask: np.ndarray) -> StereoModel:
    """Cameras first, then the arm (module docstring): the same deviations, the base (6) and the mount (6) fitted
    to the fixture points the frozen cameras triangulate."""
    X = triangulate(cameras, obs)
    seen = np.isfinite(X[..., 0])
    k, i = np.nonzero(seen)
    target = X[k, i]
    free = np.flatnonzero(free_mask)
    scales = budget_scales(nominal)[free]

    def unpack(p):
        v = nominal.vector()
        v[free] += p[12:] * scales
        return nominal.with_vector(v), he._perturbed(np.eye(4), p[:6]), he._perturbed(fixture.mount, p[6:12])

    def residuals(p):
        table, base, mount = unpack(p)
        T = base[None] @ table.forward_batch(obs.joints) @ mount
        T = T[k]
        return ((np.einsum("mij,mj->mi", T[:, :3, :3], fixture.points[i]) + T[:, :3, 3] - target) / 1e-5).ravel()

    p = least_squares(residuals, np.zeros(12 + len(free)), method="trf", x_scale="jac", loss="soft_l1").x
    table, base, mount = unpack(p)
    # the base correction belongs to the cameras' poses: their frame is the one the arm was fitted in
    moved = [Camera(c.name, c.lens, c.T_camera_base @ base) for c in cameras]
    return StereoModel(moved, table, mount, "point")


# -- judging a model on images it never saw --------------------------------------------------------------------------
def held_out_errors(model: StereoModel, fixture: Fixture, obs: Observations) -> dict:
    """On images the fit never saw: the reprojection error of the centres through `model` (px), and the fixture's
    pose as the model's own cameras triangulate it (the drawing fitted to the circles: Kabsch) against the pose the
    model's arm predicts, position (m) and orientation (rad) per pose, (n, 2), with the predicted positions (n, 3)."""
    predicted = predict(model, fixture, obs.joints, obs.pose_of, obs.camera_of, obs.point_of)
    e = np.linalg.norm(predicted - obs.uv, axis=1)
    uv = obs.uv
    if model.centre_model == "ellipse":  # triangulate circle centres, not ellipse centres
        point = StereoModel(model.cameras, model.table, model.mount, "point")
        uv = uv - (predicted - predict(point, fixture, obs.joints, obs.pose_of, obs.camera_of, obs.point_of))
    X = triangulate(model.cameras, obs, uv)
    T_pred = model.fixture_poses(obs.joints)
    errors, kept = [], []
    for k in range(len(obs.poses)):
        seen = np.isfinite(X[k, :, 0])
        if np.sum(seen) < 3:
            continue
        T_meas = rigid_fit(fixture.points[:X.shape[1]][seen], X[k, seen])
        errors.append(he.transform_error(T_pred[k], T_meas))
        kept.append(k)
    return {"reprojection_rms_px": float(math.sqrt(np.mean(e ** 2))) if len(e) else None,
            "reprojection_max_px": float(e.max()) if len(e) else None,
            "pose_errors": np.array(errors).reshape(-1, 2),
            "positions": T_pred[kept, :3, 3].reshape(-1, 3)}  # where the model's arm put the fixture, per error


def rigid_fit(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The rigid transform T with T @ a ~ b over the pairs (Kabsch)."""
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return he._T(R, cb - R @ ca)


def stereo_point(model: StereoModel, cameras, uvs) -> np.ndarray:
    """(3,) base frame: one point seen at pixel uvs[i] by camera cameras[i] of the model, where their rays pass
    closest (csm-positioning's open loop: a target's white circle)."""
    by_name = {c.name: c for c in model.cameras}
    n = len(cameras)
    obs = Observations(["target"], np.zeros((1, 6)), tuple(cameras), {}, np.zeros(n, dtype=int), np.arange(n),
                       np.zeros(n, dtype=int), np.asarray(uvs, dtype=float).reshape(n, 2))
    point = triangulate([by_name[c] for c in cameras], obs)[0, 0]
    if not np.all(np.isfinite(point)):
        raise CalibrationInputError(f"the point is not seen by two of the cameras {', '.join(cameras)}")
    return point
