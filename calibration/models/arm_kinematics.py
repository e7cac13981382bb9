"""The arm's own geometry from its wrist camera: kinematic identification in one adjustment with the camera.

The wrist camera sees a ChArUco board on the table from many arm configurations. A board corner p is in the camera
at inv(T(q; k) @ X) @ Y @ p, where T(q; k) is the flange pose the arm's kinematic table k gives for the reported
joints q (geometry/kinematic_table.py), X = T_flange_camera and Y = T_base_board. The hand-eye adjustment
(models/hand_eye.py) takes T from the nominal table; here the table's deviations from it are adjusted too, with X,
Y, the camera's intrinsics and the board's print scale, over the reprojection error of every corner in every image
(seed 000's simultaneous update, applied to the arm). Each image keeps its small flange correction with the arm's
repeatability as its prior, so the covariance stays honest.

Observability first (`observability`): with camera frames alone, some deviations can never be told apart from X or
Y (the base joint's zero and height move the whole arm, as Y does; everything after the last joint is X), and
translations along parallel axes add up. The Jacobian of the corners with respect to every deviation, with X, Y, the
lens and the scale projected out and each column scaled by its error budget, decides: a pivoted QR keeps the
deviations whose scaled singular value stands above OBSERVABLE_RATIO of the largest and fixes the rest at nominal,
named. Its singular values give the observability index O1 (Borm and Menq): the geometric mean over the square root
of the number of residuals.

`sequential` is the usual chain for comparison: the lens from a hand-eye fit with the nominal arm, a PnP pose per
image, then the arm's deviations, X and Y from those poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg
from scipy.optimize import least_squares

from geometry.kinematic_table import ROW_PARAMETERS, KinematicTable

from calibration.errors import CalibrationInputError
from calibration.models import hand_eye as he

OBSERVABLE_RATIO = 2e-3  # a deviation whose scaled singular value is below this share of the largest is fixed
LENGTH_BUDGET_M = 1e-3  # the scale of a length deviation (an uncalibrated arm's)
ANGLE_BUDGET_RAD = math.radians(0.1)  # ... and of an angle's
CORRELATION_SHOWN = 0.9


@dataclass
class ArmView:
    """One image at one arm configuration."""

    pose: str
    joints: np.ndarray  # rad, as the arm reported them
    ids: np.ndarray
    uv: np.ndarray


@dataclass
class ArmResult:
    table: KinematicTable  # calibrated
    nominal: KinematicTable
    X: np.ndarray  # T_flange_camera
    Y: np.ndarray  # T_base_board
    intrinsics: he.Intrinsics
    board_scale: float
    identified: list[str]  # deviation names, in the table's order
    fixed: list[str]
    values: dict[str, float]  # identified deviations (m or rad)
    sigma: dict[str, float]  # their 1-sigma (m or rad)
    correlations: list[tuple[str, str, float]]  # |r| above CORRELATION_SHOWN
    observability: dict
    rms_px: float
    noise: dict
    camera_covariance: np.ndarray  # X, Y and the lens (camera_names), rad and m: what a hand-eye calibration keeps
    camera_names: list[str]
    per_view: list[dict] = field(default_factory=list)


def budget_scales(table: KinematicTable) -> np.ndarray:
    """Each deviation's scale: a length's budget for d and a, an angle's for theta, alpha and beta."""
    per_row = np.array([ANGLE_BUDGET_RAD if p in ("theta", "alpha", "beta") else LENGTH_BUDGET_M for p in ROW_PARAMETERS])
    return np.tile(per_row, len(table.joints))


def views_of(views: list[ArmView], table: KinematicTable) -> list[he.View]:
    """The hand-eye views of arm views, their flange poses from `table` (the nominal one: what the controller
    reports)."""
    return [he.View(v.pose, table.forward(v.joints), np.asarray(v.ids), np.asarray(v.uv, dtype=float)) for v in views]


class ArmProblem(he.ViewProblem):
    """The hand-eye view problem with the table's free deviations after X, Y, the lens and the scale."""

    def __init__(self, views: list[ArmView], board: he.Board, lens0: he.Intrinsics, X0, Y0, nominal: KinematicTable,
                 free: np.ndarray, fit_intrinsics: bool = True, scale_sigma: float = 3e-4):
        super().__init__(views_of(views, nominal), board, "eye-in-hand", lens0, X0, Y0, fit_intrinsics, False)
        self.scale_sigma = scale_sigma
        self.Q = np.array([v.joints for v in views], dtype=float)
        self.nominal = nominal
        self.free = np.flatnonzero(free)
        self.n_hand_eye = self.n_global
        self.n_global += len(self.free)

    def table(self, x) -> KinematicTable:
        v = self.nominal.vector()
        v[self.free] += x[self.n_hand_eye:self.n_global]
        return self.nominal.with_vector(v)

    def flanges(self, x) -> np.ndarray:
        return self.table(x).forward_batch(self.Q)

    def names(self) -> list[str]:
        names = super().names()
        kinematic = [self.nominal.parameter_names()[i] for i in self.free]
        return names[:self.n_hand_eye] + kinematic + names[self.n_hand_eye:]


def _image_jacobian(problem: ArmProblem, x) -> np.ndarray:
    """Dense Jacobian of the whitened corner residuals with respect to the global parameters."""
    return global_jacobian(problem.residuals, x, 2 * len(problem.uv), problem.n_global, problem.n_hand_eye, 1e-7)


def global_jacobian(residuals, x, n_rows: int, n_global: int, first_deviation: int, deviation_step: float) -> np.ndarray:
    """Central differences of the first n_rows residuals (the images') over the first n_global parameters: the
    deviations (from `first_deviation` on) by `deviation_step`, the others relative to their size."""
    cols = []
    for j in range(n_global):
        h = deviation_step if j >= first_deviation else 1e-6 * max(1.0, abs(x[j]))
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        cols.append((residuals(xp)[:n_rows] - residuals(xm)[:n_rows]) / (2 * h))
    return np.column_stack(cols)


def observability(problem: ArmProblem, x) -> dict:
    """Which deviations the images can identify (module docstring), with the singular values and O1.

    `problem` must have every deviation free."""
    J = _image_jacobian(problem, x)
    k0 = problem.n_hand_eye
    names = [problem.nominal.parameter_names()[i] for i in problem.free]
    # X, Y and the lens are free; the print is the length reference
    return identifiable(J[:, :k0], J[:, k0:] * budget_scales(problem.nominal)[problem.free], names)


def identifiable(J_other: np.ndarray, J_deviations: np.ndarray, names: list[str],
                 ratio: float = OBSERVABLE_RATIO, against_raw: bool = False) -> dict:
    """Which deviations (columns of J_deviations, each scaled by its budget) the rows can identify once the other
    free parameters' columns are projected out: a pivoted QR keeps those whose diagonal stands above `ratio` of the
    largest (`against_raw`: of the largest column before the projection, so that poses which identify nothing leave
    only rounding, not a relative ranking of it); with the singular values of the kept ones and O1 (their geometric
    mean over the root of the rows)."""
    Q_other, _ = np.linalg.qr(J_other)
    J_perp = J_deviations - Q_other @ (Q_other.T @ J_deviations)
    _, R, order = linalg.qr(J_perp, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    keep = diag > ratio * (np.linalg.norm(J_deviations, axis=0).max() if against_raw else diag[0])
    identified = sorted(order[keep].tolist())
    singular = np.linalg.svd(J_perp[:, identified], compute_uv=False)
    o1 = float(np.exp(np.mean(np.log(singular))) / math.sqrt(len(J_perp))) if len(singular) else 0.0
    return {"identified": [names[i] for i in identified], "fixed": [names[i] for i in sorted(order[~keep].tolist())],
            "free_mask": np.isin(np.arange(len(names)), identified), "singular_values": singular.tolist(),
            "o1": o1, "condition": float(singular[0] / singular[-1]) if len(singular) else math.inf}


def fit(views: list[ArmView], board: he.Board, lens0: he.Intrinsics, nominal: KinematicTable, X0, Y0,
        fit_intrinsics: bool = True, loss: str = "soft_l1", repeatability_m: float = 1e-5,
        scale_sigma: float = 3e-4) -> ArmResult:
    """The simultaneous adjustment of the arm's identifiable deviations with X, Y and the lens, started from a
    hand-eye fit with the nominal table (X0, Y0, lens0). The board's print is the length reference: a camera sees
    angles only, so the arm's lengths and the board's scale can only be known relative to each other, and a print
    (within 0.05 %) is a better reference than an uncalibrated arm's links (1 mm in 425, 0.24 %). So the board's
    corners are taken as given (scaled by what the engineer measured), and their scale's uncertainty `scale_sigma`
    (relative, 1-sigma) is added to each length's sigma (a length scales with the reference). Fitting the scale
    with a prior instead leaves the adjustment a near-null direction (the whole cell scaled) to wander along."""
    if len(views) < 3:
        raise CalibrationInputError(f"{len(views)} images with board corners; an arm calibration needs many more "
                                    "(30 or more, from well-spread configurations)")
    every = np.ones(len(nominal.vector()), dtype=bool)
    probe = ArmProblem(views, board, lens0, X0, Y0, nominal, every, fit_intrinsics, scale_sigma)
    seen = observability(probe, probe.x0())
    problem = ArmProblem(views, board, lens0, X0, Y0, nominal, seen["free_mask"], fit_intrinsics, scale_sigma)
    problem, solution, noise = he.adjust(problem, loss, repeatability_m, math.radians(1e-3))
    return _result(problem, solution.x, noise, seen)


def _result(problem: ArmProblem, x, noise: dict, seen: dict) -> ArmResult:
    X, Y, lens, scale, deltas = problem.unpack(x)
    J = he._whitened_jacobian(problem, x, problem.sparsity())
    _, Ninv = he._redundancy(J, [np.arange(2 * len(problem.uv))])
    k0, k1 = problem.n_hand_eye, problem.n_global
    cov = Ninv[k0:k1, k0:k1]
    names = problem.names()[k0:k1]
    lengths = np.array([problem.table(x).vector()[i] if names[j].split("_")[0] in ("a", "d") else 0.0
                        for j, i in enumerate(problem.free)])
    cov = cov + np.outer(lengths, lengths) * problem.scale_sigma ** 2  # every length scales with the reference
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.outer(np.maximum(sd, 1e-300), np.maximum(sd, 1e-300))
    correlations = [(names[i], names[j], float(corr[i, j])) for i in range(len(names)) for j in range(i + 1, len(names))
                    if abs(corr[i, j]) > CORRELATION_SHOWN]
    err = problem.project(x) - problem.uv
    per_view = [{"pose": v.pose, "n": len(v.ids),
                 "rms_px": float(math.sqrt(np.mean(np.sum(err[problem.view_of == k] ** 2, axis=1))))}
                for k, v in enumerate(problem.views)]
    return ArmResult(problem.table(x), problem.nominal, X, Y, lens, scale, names, seen["fixed"],
                     dict(zip(names, map(float, x[k0:k1]))), dict(zip(names, map(float, sd))), correlations, seen,
                     float(math.sqrt(np.mean(np.sum(err ** 2, axis=1)))), noise, Ninv[:k0, :k0],
                     problem.names()[:k0], per_view)


# -- the usual chain, for comparison ---------------------------------------------------------------------------------
def sequential(views: list[ArmView], board: he.Board, lens: he.Intrinsics, nominal: KinematicTable, X0, Y0,
               free_mask: np.ndarray, board_scale: float = 1.0) -> tuple[KinematicTable, np.ndarray, np.ndarray]:
    """Cameras first, then the arm: a PnP pose of the board in every image through the given lens (a hand-eye fit's
    with the nominal arm), then the same deviations, X and Y fitted to those poses. (table, X, Y)."""
    board = he.Board(board.corners * board_scale)
    B = np.array([he._pnp(he.View(v.pose, np.eye(4), np.asarray(v.ids), np.asarray(v.uv, dtype=float)), board, lens)
                  for v in views])
    Q = np.array([v.joints for v in views])
    free = np.flatnonzero(free_mask)
    scales = budget_scales(nominal)[free]

    def unpack(p):
        v = nominal.vector()
        v[free] += p[12:] * scales
        return nominal.with_vector(v), he._perturbed(X0, p[:6]), he._perturbed(Y0, p[6:12])

    def residuals(p):
        table, X, Y = unpack(p)
        r = he._pair_residuals(X, Y, table.forward_batch(Q), B, "eye-in-hand")
        return np.hstack([r[:, :3] / math.radians(0.005), r[:, 3:] / 2e-5]).ravel()

    solution = least_squares(residuals, np.zeros(12 + len(free)), method="trf", x_scale="jac", loss="soft_l1")
    return unpack(solution.x)


# -- judging a model on images it never saw ---------------------------------------------------------------------------
def camera_errors(views: list[ArmView], board: he.Board, lens: he.Intrinsics, table: KinematicTable, X, Y,
                  board_scale: float = 1.0) -> np.ndarray:
    """(n, 2): for each view, how far the camera the model predicts (inv(Y) T(q) X, in the board frame) is from the
    one the image measures by PnP through `lens`: position (m) and orientation (rad)."""
    board = he.Board(board.corners * board_scale)
    out = []
    for v in views:
        B = he._pnp(he.View(v.pose, np.eye(4), np.asarray(v.ids), np.asarray(v.uv, dtype=float)), board, lens)
        predicted = he._inv(Y) @ table.forward(v.joints) @ X  # T_board_camera
        out.append(he.transform_error(predicted, he._inv(B)))
    return np.array(out).reshape(-1, 2)
