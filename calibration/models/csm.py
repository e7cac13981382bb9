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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import CalibrationInputError

SCHEMES = ("equal", "reciprocal", "w1", "w2", "w3", "w4")
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
    c1, c2, c3, c4 = C[:4]
    M = np.array([[c1 * c1 + c2 * c2 - c3 * c3 - c4 * c4, 2 * (c2 * c3 + c1 * c4), 2 * (c2 * c4 - c1 * c3)],
                  [2 * (c2 * c3 - c1 * c4), c1 * c1 - c2 * c2 + c3 * c3 - c4 * c4, 2 * (c3 * c4 + c1 * c2)]])
    e0, e1, e2, e3 = np.asarray(C[:4]) / np.linalg.norm(C[:4])
    r3 = np.array([2 * (e1 * e3 + e0 * e2), 2 * (e2 * e3 - e0 * e1), e0 * e0 - e1 * e1 - e2 * e2 + e3 * e3])
    return M, r3


def project(C, points) -> np.ndarray:
    """Camera-space locations g(f, C) of nominal 3D points (n, 3) -> (n, 2)."""
    M, _ = view_rows(C)
    return np.atleast_2d(points) @ M.T + np.asarray(C[4:6])


def _jacobian(C, points) -> np.ndarray:
    """d g / d C for every point: (2n, 6), rows Xc0, Yc0, Xc1, ..."""
    c1, c2, c3, c4 = C[:4]
    d1 = np.array([[c1, c4, -c3], [c2, c3, c4], [-c3, c2, -c1], [-c4, c1, c2]]) * 2  # d row1 / dC1..4
    d2 = np.array([[-c4, c1, c2], [c3, -c2, c1], [c2, c3, c4], [-c1, -c4, c3]]) * 2  # d row2 / dC1..4
    n = len(points)
    J = np.zeros((n, 2, 6))
    J[:, 0, :4] = points @ d1.T
    J[:, 1, :4] = points @ d2.T
    J[:, 0, 4] = 1.0
    J[:, 1, 5] = 1.0
    return J.reshape(2 * n, 6)


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
    # rows of R are the rows of the direction cosine matrix of eqs. 1-2, i.e. Rotation(e).as_matrix().T
    x, y, z, w_ = Rotation.from_matrix(R.T).as_quat()
    return np.array([*(np.sqrt(scale) * np.array([w_, x, y, z])), *coef[3]])


def fit_view(points, uv, w, C0, iterations: int = 30, depth: tuple | None = None) -> np.ndarray:
    """Weighted least squares of eq. 16 by Levenberg-Marquardt on the analytic Jacobian, from C0.

    `depth` = (uv_centred (n, 2), dz (n,)): also fit the flattening depth Z_r as a seventh parameter
    (C0 then has 7 entries): uv = uv_centred * (Z_r + dz) / Z_r, the data side of eq. 9."""
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    sw = np.repeat(np.sqrt(np.asarray(w, float)), 2)
    C = np.array(C0, dtype=float)
    lam = 1e-3
    if depth is not None:
        centred, dz = depth
        offset = uv - centred  # the image centre, per row

        def data(c):
            return centred * ((c[6] + dz) / c[6])[:, None] + offset
    else:
        def data(c):
            return uv

    def cost(c):
        return float(np.sum((sw * (data(c) - project(c, points)).ravel()) ** 2))

    current = cost(C)
    for _ in range(iterations):
        r = sw * (data(C) - project(C, points)).ravel()
        J = _jacobian(C, points)
        if depth is not None:  # d(data)/dZ_r enters with the opposite sign of d(model)/dC
            J = np.column_stack([J, -(centred * (-dz / C[6] ** 2)[:, None]).ravel()])
        J = J * sw[:, None]
        JtJ, Jtr = J.T @ J, J.T @ r
        step = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), Jtr)
        trial = cost(C + step)
        if trial <= current:
            C, lam = C + step, lam * 0.3
            done = current - trial <= 1e-14 * max(current, 1e-30) or np.abs(step).max() < 1e-12 * np.abs(C).max()
            current = trial
            if done:
                break
        else:
            lam *= 10
            if lam > 1e8:
                break
    return C


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
    return np.linalg.lstsq(A, b, rcond=None)[0]


def estimate(cameras: list[CameraSamples], targets_uv, scheme: str = "equal", k: float = 1.0,
             start: Estimate | None = None, max_rounds: int = 30, tol_m: float = 1e-7,
             fit_depth: bool = False) -> Estimate:
    """View parameters of every camera and the target's nominal 3D position, with flattening and the
    weights iterated to a fixed point (each round: weights from the distances to the current target,
    flatten about it, refit C, re-solve the target).

    fit_depth: estimate each camera's flattening depth Z_r with C instead of keeping the anticipated one
    (needs samples spread in depth; the seed keeps Z_r fixed)."""
    if len(cameras) < 2:
        raise CalibrationInputError("CSM needs at least two cameras to place a point in 3D")
    n = len(cameras[0].points)
    if any(len(c.points) != n for c in cameras):
        raise CalibrationInputError("every camera needs the same samples (one per pose and feature)")
    if start is not None:
        views, reference = [np.array(v) for v in start.views], np.array(start.target)
        depths = list(start.depths)
    else:  # equal weights, unflattened: a first look
        views = [fit_view(c.points, c.uv, np.ones(n), initial_view(c.points, c.uv)) for c in cameras]
        reference = solve_target(views, targets_uv)
        depths = [c.z_r for c in cameras]
    w = np.ones(n)
    for rounds in range(1, max_rounds + 1):
        w = weights(scheme, k, np.linalg.norm(cameras[0].points - reference, axis=1) * 1e3)
        for i, (c, C) in enumerate(zip(cameras, views)):
            if fit_depth:
                dz = (c.points - reference) @ view_rows(C)[1]
                fitted = fit_view(c.points, c.uv, w, [*C[:6], depths[i]], depth=(c.uv - c.centre_px, dz))
                views[i], depths[i] = fitted[:6], float(fitted[6])
            else:
                views[i] = fit_view(c.points, flatten(c, C, reference), w, C)
        target = solve_target(views, targets_uv)
        moved = float(np.linalg.norm(target - reference))
        reference = target
        if moved < tol_m:
            break
    residual = [flatten(c, C, reference, z) - project(C, c.points) for c, C, z in zip(cameras, views, depths)]
    return Estimate(reference, views, depths, rounds, residual, w)
