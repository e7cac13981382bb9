"""Camera-space manipulation (seed 002 section III): view parameters, flattening, VW weights, 3D target.

Per camera, six view parameters C map the nominal 3D position f(θ) of a feature to its camera-space
location (eqs. 1-2), an orthographic model with a scaled rotation:

    [Xc, Yc] = |C|² · [r1(e); r2(e)] · f(θ) + [C5, C6],   e = (C1..C4)/|C1..C4|  (a unit quaternion)

C is estimated by weighted nonlinear least squares (eqs. 8 / 16) from joint-space / camera-space samples.
Flattening (eq. 9) rescales every sample by Z_i / Z_r, its depth along the camera axis relative to the
anticipated depth Z_r of the target, so perspective images fit the orthographic model; since the depth
offsets ΔZ_i = r3(e) · (f_i - f_target) depend on C and on the target, fit and flattening are iterated
until both settle. With C of two cameras, the target's 3D position solves eq. 10 (linear in f), and the
weights ω(dis) of eqs. 12-15 favour samples near the target.

All positions here are nominal (from the catalogue kinematics): CSM never needs the true robot or the
camera parameters; what the model cannot represent is absorbed locally, near the target, by the weights.

Numerics (a positioning iteration takes about a millisecond, tools/bench_csm.py): the model is linear in
its coefficients γ = (|C|²·r1, C5, |C|²·r2, C6), themselves quadratic in C, so each Levenberg-Marquardt
step of a view fit needs only small products with the weighted Gram matrix of the samples (`_fit`),
whatever their number. The points are taken about their weighted centroid (else the translation
co-varies with the rotation and the fit crawls when the VW weights let a few samples dominate); Newton's
second-order term, constant in C, keeps convergence quadratic under the large residuals such weights
leave; a fitted flattening depth enters as s = 1/Z_r, in which the flattened data are linear. Each round
refits from the previous round's C with a few steps at most, and the rounds end only after one whose fits
all converged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import lapack

from calibration.errors import CalibrationInputError

SCHEMES = ("equal", "reciprocal", "w1", "w2", "w3", "w4")
# Levenberg-Marquardt steps per view fit within a flattening / weighting round: the next round refits from
# where this one stopped, and the rounds end only after one whose fits all converged
ROUND_STEPS = 4
MIN_DISTANCE_MM = 0.1  # a sample at the target would get an infinite weight: distances are floored


def weights(scheme: str, k: float, dis_mm: np.ndarray) -> np.ndarray:
    """ω per sample from its estimated distance to the target (mm): equal; 1/dis; ω1 = k/dis (eq. 12);
    ω2 = k + 1/dis (13); ω3 = 1/dis^k (14); ω4 = k/dis^k (15)."""
    dis = np.maximum(np.asarray(dis_mm, dtype=float), MIN_DISTANCE_MM)
    if scheme == "equal":
        return np.ones_like(dis)
    if scheme == "reciprocal":
        return 1.0 / dis
    if scheme == "w1":
        return k / dis
    if scheme == "w2":
        return k + 1.0 / dis
    if scheme == "w3":
        return dis ** (-k)
    if scheme == "w4":
        return k * dis ** (-k)
    raise CalibrationInputError(f"unknown weighting scheme {scheme!r}; allowed: {', '.join(SCHEMES)}")


def view_rows(C) -> tuple[np.ndarray, np.ndarray]:
    """(2x3 matrix |C|²·[r1; r2] of eqs. 1-2, unit depth direction r3 = (c31, c32, c33) of eq. 9)."""
    c1, c2, c3, c4 = np.asarray(C, float)[:4].tolist()  # Python floats: far cheaper than numpy scalars here
    n2 = c1 * c1 + c2 * c2 + c3 * c3 + c4 * c4  # r3 is that of the unit quaternion e = C1..4 / |C1..4|
    rows = np.array([[c1 * c1 + c2 * c2 - c3 * c3 - c4 * c4, 2 * (c2 * c3 + c1 * c4), 2 * (c2 * c4 - c1 * c3)],
                     [2 * (c2 * c3 - c1 * c4), c1 * c1 - c2 * c2 + c3 * c3 - c4 * c4, 2 * (c3 * c4 + c1 * c2)],
                     [2 * (c2 * c4 + c1 * c3) / n2, 2 * (c3 * c4 - c1 * c2) / n2,
                      (c1 * c1 - c2 * c2 - c3 * c3 + c4 * c4) / n2]])
    return rows[:2], rows[2]


def project(C, points) -> np.ndarray:
    """Camera-space locations g(f, C) of nominal 3D points (n, 3) -> (n, 2)."""
    M, _ = view_rows(C)
    return np.atleast_2d(points) @ M.T + np.asarray(C[4:6])


def _coefficients_jacobian_table(C) -> np.ndarray:
    """E = d γ / d θ (9, 7) for θ = (C1..C6, s): γ = (row 1 of M, C5, row 2 of M, C6, s) are the
    coefficients of the model [Xc, Yc] = [f, 1] · γ (s = 1/Z_r: the fitted flattening, see `_fit`).
    M is a homogeneous quadratic in C1..C4, so γ = E · (C1..C4 / 2, C5, C6, s)."""
    c1, c2, c3, c4 = (2.0 * float(v) for v in C[:4])
    return np.array([[c1, c2, -c3, -c4, 0, 0, 0], [c4, c3, c2, c1, 0, 0, 0], [-c3, c4, -c1, c2, 0, 0, 0],
                     [0, 0, 0, 0, 1, 0, 0], [-c4, c3, c2, -c1, 0, 0, 0], [c1, -c2, c3, -c4, 0, 0, 0],
                     [c2, c1, c4, c3, 0, 0, 0], [0, 0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0, 1]])


# E is affine in C1..C4: E = E0 + Σ C_m·E_m, as one product (building it from Python floats costs more)
_E_CONSTANT = _coefficients_jacobian_table(np.zeros(4))
_E_LINEAR = np.stack([_coefficients_jacobian_table(np.eye(4)[m]) - _E_CONSTANT for m in range(4)],
                     axis=2).reshape(63, 4)
_HALF = np.array([0.5, 0.5, 0.5, 0.5, 1.0, 1.0, 1.0])
_EYE = {p: np.eye(p) for p in (6, 7)}
_M_ROWS = [[0, 1, 2], [4, 5, 6]]  # where γ holds the rows of M
# and γ's second derivatives by C1..C4 are constant: d²γ_j / dC_m dC_k = d E[j, m] / dC_k, here laid out
# so that Σ_j b_j · d²γ_j is one product, (p x p) with p = 6 or 7 parameters (zero beyond C1..C4)
_CURVATURE = {}
for _p in (6, 7):
    _CURVATURE[_p] = np.zeros((8, _p, _p))
    _CURVATURE[_p][:, :4, :4] = _E_LINEAR.reshape(9, 7, 4)[:8, :4, :]
    _CURVATURE[_p] = _CURVATURE[_p].reshape(8, _p * _p)


_E_PARTS = {7: (_E_LINEAR, _E_CONSTANT),  # by the number of parameters: with s, or C alone (γ without s)
            6: (_E_LINEAR.reshape(9, 7, 4)[:8, :6].reshape(48, 4).copy(), _E_CONSTANT[:8, :6].copy())}


def _coefficients_jacobian(C, depth: bool = False) -> np.ndarray:
    """E of `_coefficients_jacobian_table`: (9, 7) with `depth`, else (8, 6) (θ = C, γ without s)."""
    linear, constant = _E_PARTS[7 if depth else 6]
    return (linear @ C[:4]).reshape(constant.shape) + constant


def initial_view(points, uv, w=None) -> np.ndarray:
    """A starting C: the best affine camera (linear least squares), its 2x3 part replaced by the nearest
    scaled rotation, turned into the quaternion form of eqs. 1-2."""
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    if len(points) < 4:
        raise CalibrationInputError(f"need at least 4 samples per camera to start the view parameters, got {len(points)}")
    sw = np.sqrt(np.ones(len(points)) if w is None else np.asarray(w, float))
    A = np.column_stack([points, np.ones(len(points))]) * sw[:, None]
    coef, *_ = np.linalg.lstsq(A, uv * sw[:, None], rcond=None)
    M = coef[:3].T  # 2x3
    U, S, Vt = np.linalg.svd(M, full_matrices=False)
    rows = U @ Vt  # orthonormal 2x3
    scale = float(S.mean())
    R = np.vstack([rows, np.cross(rows[0], rows[1])])
    # rows of R are the rows of the direction cosine matrix of eqs. 1-2, i.e. the rotation R.T
    w_, x, y, z = _quaternion(R.T)
    return np.array([*(np.sqrt(scale) * np.array([w_, x, y, z])), *coef[3]])


def _quaternion(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix, from its largest component (Shepperd's method;
    the same sign as scipy's Rotation.from_matrix, without its overhead)."""
    R = np.asarray(R, float)
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    i = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], trace]))
    q = np.empty(4)  # x, y, z, w
    if i == 3:
        q[:] = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1 + trace
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i], q[j], q[k] = 1 - trace + 2 * R[i, i], R[j, i] + R[i, j], R[k, i] + R[i, k]
        q[3] = R[k, j] - R[j, k]
    q /= np.linalg.norm(q)
    return q[[3, 0, 1, 2]]


class _Design:
    """What a weighted fit needs of the samples' nominal 3D points alone (shared by every camera, which all
    see the same points): the weighted design matrix Φ of the model, image x rows of every sample then y
    rows (the model is Φ·γ), and its Gram matrix ΦᵀΦ. The points are taken about their weighted centroid:
    this keeps the translation from co-varying with the rotation through the lever arm of the centroid
    (with the VW weights a few samples near the target dominate, and uncentred the fit crawls along that
    curved valley)."""

    def __init__(self, points, w):
        points, w = np.asarray(points, float), np.asarray(w, float)
        n = len(points)
        self.centroid = (w @ points) / w.sum()
        sw = np.sqrt(w)
        Qs = np.empty((n, 4))  # [f - f0, 1], weighted
        Qs[:, :3], Qs[:, 3] = (points - self.centroid) * sw[:, None], sw
        self.Phi = np.zeros((2 * n, 8))
        self.Phi[:n, :4] = self.Phi[n:, 4:] = Qs
        self.G = np.zeros((8, 8))
        self.G[:4, :4] = self.G[4:, 4:] = Qs.T @ Qs
        self.sw = np.concatenate([sw, sw])


def fit_view(points, uv, w, C0, iterations: int = 30, depth: tuple | None = None) -> np.ndarray:
    """Weighted least squares of eq. 16 by Levenberg-Marquardt on the analytic Jacobian, from C0.

    `depth` = (uv_centred (n, 2), dz (n,)): also fit the flattening depth Z_r as a seventh parameter
    (C0 then has 7 entries): uv = uv_centred * (Z_r + dz) / Z_r, the data side of eq. 9."""
    return _fit(_Design(points, w), np.asarray(uv, float), C0, iterations, depth)[0]


def _fit(d: _Design, uv: np.ndarray, C0, iterations: int = 30,
         depth: tuple | None = None) -> tuple[np.ndarray, bool]:
    """fit_view on a prepared design. The model is linear in its coefficients γ(θ) (see
    `_coefficients_jacobian`), so the normal matrix is Eᵀ·G·E with the Gram matrix G of the design:
    a step costs products of 9x9 matrices and one residual.

    Flattening with a fitted depth (eq. 9) is taken on the data side as uv + s·a, a = uv_centred·dz,
    s = 1/Z_r: linear in s, so the fit solves s exactly (in Z_r itself Gauss-Newton would only double Z_r
    per step when the samples ask for almost no flattening, s ≈ 0).

    Levenberg-Marquardt on Newton's matrix (Gauss-Newton's plus the second-order term, constant in C:
    with the VW weights a few samples near the target dominate a model that cannot fit them all, large
    residuals under which Gauss-Newton alone converges only linearly), Gauss-Newton's where Newton's is
    indefinite. It stops when the quadratic model predicts a decrease below rounding, or no step decreases
    the cost any more (converged: True), or after `iterations` steps (False)."""
    theta = np.array(C0, dtype=float)
    y = np.asarray(uv, float).T.ravel() * d.sw  # weighted data, image x of every sample then y
    Phi, G = d.Phi, d.G
    fit_z = depth is not None
    if fit_z:  # the data term s·a joins the model: coefficient s, column -a
        theta[6] = 1.0 / theta[6]
        centred, dz = depth
        a = (np.asarray(centred, float) * np.asarray(dz, float)[:, None]).T.ravel() * d.sw
        Phi = np.column_stack([Phi, -a])
        G = Phi.T @ Phi
    p = len(theta)
    half, eye, curvature = _HALF[:p], _EYE[p], _CURVATURE[p]
    PhiT = Phi.T
    E = _coefficients_jacobian(theta, fit_z)
    gamma = E @ (theta * half)
    # the model about the centroid: its image is the translation (γ holds M's rows, γ3 = C5, γ7 = C6)
    theta[4:6] += gamma[_M_ROWS] @ d.centroid
    gamma[[3, 7]] = theta[4:6]
    r = y - Phi @ gamma
    F = float(r @ r)
    floor = 1e-26 * float(y @ y)  # rounding of F: residuals ~1e-13 of the data
    lam, converged = 1e-3, True
    for _ in range(iterations):
        b = PhiT @ r
        g = -(E.T @ b)  # gradient of F/2
        H_gn = E.T @ G @ E
        D = H_gn.diagonal() + 1e-12  # Marquardt's scaling
        H = H_gn - (b[:8] @ curvature).reshape(p, p)
        _, step, info = lapack.dposv(H + eye * (lam * D), -g)
        if info != 0:  # Newton's matrix is indefinite here (far from the minimum)
            H = H_gn
            _, step, info = lapack.dposv(H + eye * (lam * D), -g)
            if info != 0:  # degenerate samples: nothing better to be had
                break
        predicted = float(lam * ((D * step) @ step) - g @ step)  # F's decrease by the quadratic model
        if predicted <= 1e-12 * F + floor:
            break
        trial = theta + step
        E_t = _coefficients_jacobian(trial, fit_z)
        gamma_t = E_t @ (trial * half)
        r_t = y - Phi @ gamma_t
        F_t = float(r_t @ r_t)
        if F_t <= F:
            theta, E, gamma, r, F, lam = trial, E_t, gamma_t, r_t, F_t, lam * 0.3
        else:
            lam *= 10
            if lam > 1e8:  # no step decreases F any more
                break
    else:
        converged = False
    theta[4:6] -= gamma[_M_ROWS] @ d.centroid  # back to the origin
    if fit_z:
        theta[6] = 1.0 / theta[6] if theta[6] != 0 else np.inf  # s = 0 exactly: no flattening at all
    return theta, converged


@dataclass
class CameraSamples:
    """One camera's samples: nominal 3D positions (n, 3) m, their camera-space locations (n, 2) px."""

    points: np.ndarray
    uv: np.ndarray
    centre_px: np.ndarray  # where flattening scales about (the image centre: the principal point is unknown)
    z_r: float  # roughly anticipated distance of the target along the camera axis, m


@dataclass
class Estimate:
    target: np.ndarray  # nominal 3D position of the target (m)
    views: list[np.ndarray]  # C per camera
    depths: list[float]  # flattening depth Z_r per camera (m): anticipated, or fitted
    rounds: int  # flattening / weighting rounds until both settled
    residual_px: list[np.ndarray] = field(default_factory=list)  # per camera (n, 2): sample - model, flattened
    weights: np.ndarray | None = None


def flatten(cam: CameraSamples, C, reference, z_r: float | None = None) -> np.ndarray:
    """Eq. 9: Xc0 = Xc · Z_i / Z_r, Z_i = Z_r + r3 · (f_i - f_ref), about the image centre."""
    z_r = cam.z_r if z_r is None else z_r
    _, r3 = view_rows(C)
    z = z_r + (cam.points - reference) @ r3
    return (cam.uv - cam.centre_px) * (z / z_r)[:, None] + cam.centre_px


def solve_target(views, targets_uv) -> np.ndarray:
    """Eq. 10: the 3D point whose camera-space locations best match the target's in every camera
    (the target sits at the reference depth, so its location needs no flattening): linear least squares."""
    A = np.vstack([view_rows(C)[0] for C in views])
    b = np.concatenate([np.asarray(t, float) - C[4:6] for C, t in zip(views, targets_uv)])
    try:  # the normal equations: as exact here (cameras well apart), and a fraction of lstsq's cost
        return np.linalg.solve(A.T @ A, A.T @ b)
    except np.linalg.LinAlgError:  # views that cannot place a point: the least-norm solution
        return np.linalg.lstsq(A, b, rcond=None)[0]


def estimate(cameras: list[CameraSamples], targets_uv, scheme: str = "equal", k: float = 1.0,
             start: Estimate | None = None, max_rounds: int = 30, tol_m: float = 1e-7,
             fit_depth: bool = False) -> Estimate:
    """View parameters of every camera and the target's nominal 3D position, with flattening and the
    weights iterated to a fixed point (each round: weights from the distances to the current target,
    flatten about it, refit C with at most ROUND_STEPS steps from the last round's, re-solve the target;
    done when the target moved less than tol_m in a round whose fits all converged).

    fit_depth: estimate each camera's flattening depth Z_r with C instead of keeping the anticipated one
    (needs samples spread in depth; the seed keeps Z_r fixed)."""
    if len(cameras) < 2:
        raise CalibrationInputError("CSM needs at least two cameras to place a point in 3D")
    n = len(cameras[0].points)
    if any(len(c.points) != n for c in cameras):
        raise CalibrationInputError("every camera needs the same samples (one per pose and feature)")
    # the weighted design depends on the points alone: one per round for all cameras when they share them
    shared = all(c.points is cameras[0].points or np.array_equal(c.points, cameras[0].points) for c in cameras)

    def designs(w):
        return [_Design(cameras[0].points, w)] * len(cameras) if shared else [_Design(c.points, w) for c in cameras]

    if start is not None:
        views, reference = [np.array(v) for v in start.views], np.array(start.target)
        depths = list(start.depths)
    else:  # equal weights, unflattened: a first look
        views = [_fit(d, c.uv, initial_view(c.points, c.uv), ROUND_STEPS)[0]
                 for c, d in zip(cameras, designs(np.ones(n)))]
        reference = solve_target(views, targets_uv)
        depths = [c.z_r for c in cameras]
    w = np.ones(n)
    for rounds in range(1, max_rounds + 1):  # noqa: B007 - the rounds taken are read after the loop
        w = weights(scheme, k, np.linalg.norm(cameras[0].points - reference, axis=1) * 1e3)
        settled = True
        for i, (c, C, d) in enumerate(zip(cameras, views, designs(w))):
            if fit_depth:
                dz = (c.points - reference) @ view_rows(C)[1]
                fitted, converged = _fit(d, c.uv, [*C[:6], depths[i]], ROUND_STEPS, (c.uv - c.centre_px, dz))
                views[i], depths[i] = fitted[:6], float(fitted[6])
            else:
                views[i], converged = _fit(d, flatten(c, C, reference), C, ROUND_STEPS)
            settled &= converged
        target = solve_target(views, targets_uv)
        moved = float(np.linalg.norm(target - reference))
        reference = target
        if moved < tol_m and settled:
            break
    residual = [flatten(c, C, reference, z) - project(C, c.points) for c, C, z in zip(cameras, views, depths)]
    return Estimate(reference, views, depths, rounds, residual, w)
