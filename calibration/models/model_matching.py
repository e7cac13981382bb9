"""Line- and point-based model matching of seed 000 (Kim, sections IV-V).

Cameras are pinholes with the principal point at the image centre and square pixels
(the seed's assumptions): a world point X_w goes to camera coordinates p = V X_w
(V: 4x4, world -> camera, OpenCV axes: z forward, y down) and to the image at
u = f p_x / p_z + c_u, v = f p_y / p_z + c_v. An object's model point X goes to the
world by its pose M (4x4, object -> world).

The unknowns are incremental (eqs. 49-50): a camera update is pre-multiplied,
V <- dV V, so its 6 variables are a translation and a rotation vector in the camera
frame, plus a relative focal-length change (f <- f (1 + df)); an object update is
post-multiplied, M <- M dM, in the object frame. The covariance (J^T W J)^-1 of
the last iteration is therefore that of the camera pose in its own frame and of
the object pose in its own frame, as in the seed's Fig. 11.

Measurements:
- lines (eqs. 21-26): two image-line endpoints per model line, residual = their
  normal distances h1, h2 to the projected model line, weighted by the 2x2 matrix
  of eq. 11 (from calibration.vision.lines);
- points: an image point per model point (operator clicks), residual = the
  projection error, weighted by 1/sigma^2.

One Gauss-Newton solver (eq. 35, with J^T W J and J^T W H accumulated per 2x2
block, eqs. 40-41) serves camera calibration (7 or 6 variables), object
localisation (6) and the simultaneous update of two cameras and one object (20,
eqs. 46-48): which blocks are free is a choice of the caller. A step that raises
the cost is damped (Levenberg-Marquardt style) rather than taken; the seed's
plain Gauss-Newton is the undamped case, which is what every converging
iteration here is.

How it is computed: all measurements at once, no loop over them or over the
camera-object pairs. Each model point takes its pair's transform; the 13
derivatives of its (u, v) (camera translation, rotation and focal length, object
translation and rotation) are written out component by component, a line's two
endpoints are combined in that space (they share the pair), and one indexing
operation puts each row's derivatives into its pair's columns of J (a fixed
block's into a spare column, dropped). J^T W J and J^T W r are then single
matrix products over the stacked rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.projection import pinhole
from geometry.transforms import inverse

# ---------------------------------------------------------------- poses

def increment(xi) -> np.ndarray:
    """4x4 of an increment (tx, ty, tz, rx, ry, rz): translation and rotation vector."""
    xi = np.asarray(xi, dtype=float)
    T = np.eye(4)
    T[:3, :3] = _rotation_of(xi[3:6])
    T[:3, 3] = xi[:3]
    return T


def _rotation_of(w: np.ndarray) -> np.ndarray:
    """Rodrigues: I + sin(t)/t K + (1 - cos(t))/t^2 K^2, K = [w]x, t = |w|; the second coefficient as
    2 sin^2(t/2)/t^2, without cancellation near t = 0. Written out because every solver step builds a few of
    these and scipy's Rotation costs more than the step's arithmetic."""
    wx, wy, wz = (float(c) for c in w)
    t = math.sqrt(wx * wx + wy * wy + wz * wz)
    if t < 1e-8:
        a, b = 1.0, 0.5  # the series' first terms; the next ones are below 1e-17
    else:
        a, b = math.sin(t) / t, 2.0 * (math.sin(0.5 * t) / t) ** 2
    K = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    return np.eye(3) + a * K + b * (K @ K)


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(dx, dy, dz, rx, ry, rz) of T_true^-1 T_est: the estimate's error in the true pose's own frame."""
    D = inverse(T_true) @ T_est
    return np.concatenate([D[:3, 3], Rotation.from_matrix(D[:3, :3]).as_rotvec()])


# ---------------------------------------------------------------- state

@dataclass
class CameraState:
    V: np.ndarray  # world -> camera
    f: float  # focal length, px
    cu: float  # principal point (image centre), px
    cv: float
    free_pose: bool = True
    free_f: bool = True
    f_prior: float | None = None  # the lens's nominal focal length (px), a weak prior when f is free
    f_prior_rel: float = 0.1  # its relative 1-sigma

    @classmethod
    def centred(cls, V, f, width: int, height: int, **kw) -> CameraState:
        return cls(np.asarray(V, float), float(f), (width - 1) / 2.0, (height - 1) / 2.0, **kw)

    def n_free(self) -> int:
        return 6 * self.free_pose + self.free_f

    def project(self, X_world: np.ndarray) -> np.ndarray:
        p = np.asarray(X_world, float) @ self.V[:3, :3].T + self.V[:3, 3]
        return pinhole(p, self.f, self.cu, self.cv)

    def to_dict(self) -> dict:
        return {"V": self.V.tolist(), "f": self.f, "cu": self.cu, "cv": self.cv}

    @classmethod
    def from_dict(cls, d: dict, **kw) -> CameraState:
        return cls(np.asarray(d["V"], float), float(d["f"]), float(d["cu"]), float(d["cv"]), **kw)


@dataclass
class ObjectState:
    M: np.ndarray  # object -> world
    free: bool = True

    def n_free(self) -> int:
        return 6 * self.free


@dataclass
class Observations:
    """Line and point measurements, each tied to a camera and an object (indices into the solver's lists).

    Lines: model endpoints P1, P2 (object frame, m), image endpoints Q1, Q2 (px), 2x2 weights W (1/px^2).
    Points: model points X (object frame), image points uv, 2x2 weights.
    """

    line_cam: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    line_obj: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    P1: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    P2: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    Q1: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    Q2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    line_W: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    point_cam: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    point_obj: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    X: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point_W: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))

    @property
    def n_lines(self) -> int:
        return len(self.line_cam)

    @property
    def n_points(self) -> int:
        return len(self.point_cam)

    def select(self, cams=None, objs=None) -> Observations:
        """Only the measurements of the given cameras and objects."""
        lk = np.ones(self.n_lines, bool)
        pk = np.ones(self.n_points, bool)
        if cams is not None:
            lk &= np.isin(self.line_cam, list(cams))
            pk &= np.isin(self.point_cam, list(cams))
        if objs is not None:
            lk &= np.isin(self.line_obj, list(objs))
            pk &= np.isin(self.point_obj, list(objs))
        return Observations(self.line_cam[lk], self.line_obj[lk], self.P1[lk], self.P2[lk], self.Q1[lk], self.Q2[lk],
                            self.line_W[lk], self.point_cam[pk], self.point_obj[pk], self.X[pk], self.uv[pk],
                            self.point_W[pk])

    def select_lines(self, keep: np.ndarray) -> Observations:
        """The chosen lines (boolean mask) and no points."""
        return Observations(self.line_cam[keep], self.line_obj[keep], self.P1[keep], self.P2[keep], self.Q1[keep],
                            self.Q2[keep], self.line_W[keep])

    @staticmethod
    def concat(parts: list[Observations]) -> Observations:
        names = ("line_cam", "line_obj", "P1", "P2", "Q1", "Q2", "line_W", "point_cam", "point_obj", "X", "uv", "point_W")
        return Observations(*(np.concatenate([getattr(p, n) for p in parts]) for n in names))


# ---------------------------------------------------------------- projection with Jacobian

class _Layout:
    """Where each free block's variables sit in the unknown vector x."""

    def __init__(self, cameras: list[CameraState], objects: list[ObjectState]):
        self.cam_pose, self.cam_f, self.obj = {}, {}, {}
        k = 0
        self.names = []
        for i, c in enumerate(cameras):
            if c.free_pose:
                self.cam_pose[i] = k
                self.names += [f"cam{i}.{n}" for n in ("tx", "ty", "tz", "rx", "ry", "rz")]
                k += 6
            if c.free_f:
                self.cam_f[i] = k
                self.names.append(f"cam{i}.f_rel")
                k += 1
        for j, o in enumerate(objects):
            if o.free:
                self.obj[j] = k
                self.names += [f"obj{j}.{n}" for n in ("tx", "ty", "tz", "rx", "ry", "rz")]
                k += 6
        self.n = k
        # per camera-object pair (camera i, object j: row i * n_objects + j), the column of each of the 13
        # derivatives of _project; a fixed block's go to a spare column n, dropped after
        self.columns = np.full((len(cameras) * len(objects), 13), k)
        for i in range(len(cameras)):
            for j in range(len(objects)):
                row = self.columns[i * len(objects) + j]
                if i in self.cam_pose:
                    row[0:6] = self.cam_pose[i] + np.arange(6)
                if i in self.cam_f:
                    row[6] = self.cam_f[i]
                if j in self.obj:
                    row[7:13] = self.obj[j] + np.arange(6)


def project_with_jacobian(cameras, objects, cam_idx, obj_idx, X, layout: _Layout, with_jacobian: bool = True):
    """Image points (n, 2) of model points X (n, 3) and d(uv)/dx (n, 2, n_unknowns) (None without the Jacobian)."""
    uv, D, pair = _project(cameras, objects, cam_idx, obj_idx, X, with_jacobian)
    return uv, (_scatter(D, pair, layout) if with_jacobian else None)


def _project(cameras, objects, cam_idx, obj_idx, X, with_jacobian: bool = True):
    """Image points (n, 2) of model points X (n, 3), the 13 derivatives D (n, 2, 13) of each point's (u, v)
    (camera translation and rotation, focal length, object translation and rotation) and each point's
    camera-object pair (cam_idx * n_objects + obj_idx).

    All points at once, each with its pair's transform; the derivatives written out component by component."""
    pair = np.asarray(cam_idx) * len(objects) + np.asarray(obj_idx)
    CM = np.array([c.V[:3] @ o.M for c in cameras for o in objects])[pair]  # (n, 3, 4): model -> camera
    f = np.array([c.f for c in cameras])[cam_idx]
    R = CM[:, :, :3]
    p = np.einsum("nij,nj->ni", R, X) + CM[:, :, 3]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fz = f / z
    u, v = fz * x, fz * y  # relative to the principal point
    uv = np.column_stack([u + np.array([c.cu for c in cameras])[cam_idx],
                          v + np.array([c.cv for c in cameras])[cam_idx]])
    if not with_jacobian:
        return uv, None, pair
    uz, vz = u / z, v / z
    D = np.zeros((len(X), 2, 13))
    # camera translation, p' = p + dt + dw x p: d(u, v)/dp, rows du = (f/z, 0, -u/z), dv = (0, f/z, -v/z)
    D[:, 0, 0], D[:, 0, 2] = fz, -uz
    D[:, 1, 1], D[:, 1, 2] = fz, -vz
    # camera rotation: -d^T [p]x = (p x d)^T
    D[:, 0, 3], D[:, 0, 4], D[:, 0, 5] = -y * uz, f + x * uz, -y * fz
    D[:, 1, 3], D[:, 1, 4], D[:, 1, 5] = -f - y * vz, x * vz, x * fz
    D[:, 0, 6], D[:, 1, 6] = u, v  # f' = f (1 + df)
    # object, X' = X + dt + dw x X in the object frame: d R, and -(d R) [X]x = (X x d R)^T
    dR = D[:, :, 0:3] @ R  # (n, 2, 3)
    D[:, :, 7:10] = dR
    X2 = X[:, None, :]
    D[:, :, 10] = X2[..., 1] * dR[..., 2] - X2[..., 2] * dR[..., 1]
    D[:, :, 11] = X2[..., 2] * dR[..., 0] - X2[..., 0] * dR[..., 2]
    D[:, :, 12] = X2[..., 0] * dR[..., 1] - X2[..., 1] * dR[..., 0]
    return uv, D, pair


def _scatter(D: np.ndarray, pair: np.ndarray, layout: _Layout) -> np.ndarray:
    """Rows of pair-derivatives D (n, k, 13) into the unknowns' columns (n, k, layout.n), one indexing operation."""
    n, k = D.shape[:2]
    J = np.zeros((n, k, layout.n + 1))
    rows = (np.arange(n * k) * (layout.n + 1)).reshape(n, k, 1)
    J.ravel()[(rows + layout.columns[pair][:, None, :]).ravel()] = D.ravel()
    return J[:, :, :layout.n]


def line_residuals(a: np.ndarray, b: np.ndarray, Q1: np.ndarray, Q2: np.ndarray, with_jacobian: bool = True):
    """Normal distances (eqs. 21-26) of image endpoints Q1, Q2 to the lines through projected endpoints a, b.

    Returns h (n, 2) and dh/d(u1, v1, u2, v2) (n, 2, 4)."""
    u1, v1, u2, v2 = a[:, :1], a[:, 1:], b[:, :1], b[:, 1:]  # (n, 1): broadcast over the two endpoints
    A, B, C = v2 - v1, u1 - u2, u2 * v1 - u1 * v2
    M = np.maximum(np.hypot(A, B), 1e-9)  # a model line seen end-on (a diverging solve) must not divide by 0
    Qx, Qy = np.column_stack([Q1[:, 0], Q2[:, 0]]), np.column_stack([Q1[:, 1], Q2[:, 1]])  # (n, 2)
    h = (A * Qx + B * Qy + C) / M
    dh = np.zeros((len(a), 2, 4))
    if with_jacobian:
        # dh = dN / M - N / M^2 dM with N = A Qx + B Qy + C, dN = (Qy - v2, u2 - Qx, v1 - Qy, Qx - u1) and
        # dM = (B, -A, -B, A) / M
        k = h / M**2
        dh[:, :, 0] = (Qy - v2) / M - k * B
        dh[:, :, 1] = (u2 - Qx) / M + k * A
        dh[:, :, 2] = (v1 - Qy) / M + k * B
        dh[:, :, 3] = (Qx - u1) / M - k * A
    return h, dh


def weighted_residuals(cameras, objects, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """The residuals (n, 2) of `obs` at the given states and their weights (n, 2, 2), without the Jacobian."""
    r, _, W = residuals_and_jacobian(cameras, objects, obs, _Layout(cameras, objects), with_jacobian=False)
    return r, W


def residuals_and_jacobian(cameras, objects, obs: Observations, layout: _Layout, with_jacobian: bool = True):
    """Stacked 2-vectors r (n, 2), their Jacobians (n, 2, n_unknowns) (None without) and weights (n, 2, 2):
    lines, then points."""
    rs, Js, Ws = [], [], []
    if obs.n_lines:
        cam2 = np.concatenate([obs.line_cam, obs.line_cam])
        obj2 = np.concatenate([obs.line_obj, obs.line_obj])
        uv, D, pair = _project(cameras, objects, cam2, obj2, np.vstack([obs.P1, obs.P2]), with_jacobian)
        n = obs.n_lines
        h, dh = line_residuals(uv[:n], uv[n:], obs.Q1, obs.Q2, with_jacobian)
        rs.append(h)
        if with_jacobian:
            # dh/dx = dh/d(u1, v1) d(u1, v1)/dx + dh/d(u2, v2) d(u2, v2)/dx, in the 13 derivatives of the line's
            # camera-object pair (both endpoints have the same), then into the unknowns' columns
            Dh = dh[:, :, :2] @ D[:n] + dh[:, :, 2:] @ D[n:]
            Js.append(_scatter(Dh, pair[:n], layout))
        Ws.append(obs.line_W)
    if obs.n_points:
        uv, Juv = project_with_jacobian(cameras, objects, obs.point_cam, obs.point_obj, obs.X, layout, with_jacobian)
        rs.append(uv - obs.uv)
        Js.append(Juv)
        Ws.append(obs.point_W)
    if not rs:
        raise ValueError("no measurements to match")
    return np.concatenate(rs), (np.concatenate(Js) if with_jacobian else None), np.concatenate(Ws)


def apply_step(cameras, objects, layout: _Layout, dx: np.ndarray):
    """New states after the incremental update (eqs. 49-50)."""
    cams = []
    for i, c in enumerate(cameras):
        V, f = c.V, c.f
        if i in layout.cam_pose:
            k = layout.cam_pose[i]
            V = increment(dx[k:k + 6]) @ V
        if i in layout.cam_f:
            f = f * (1.0 + dx[layout.cam_f[i]])
        cams.append(replace(c, V=V, f=f))
    objs = []
    for j, o in enumerate(objects):
        M = o.M
        if j in layout.obj:
            k = layout.obj[j]
            M = M @ increment(dx[k:k + 6])
        objs.append(replace(o, M=M))
    return cams, objs


# ---------------------------------------------------------------- solver

@dataclass
class MatchResult:
    cameras: list[CameraState]
    objects: list[ObjectState]
    covariance: np.ndarray  # (J^T W J)^-1 in the incremental variables
    names: list[str]
    iterations: int
    converged: bool
    cost: float  # weighted sum of squares (eq. 34), with the focal-length priors if any
    rms_px: float  # unweighted RMS residual
    max_px: float
    n_lines: int
    n_points: int

    def sigma(self, name: str) -> float:
        return float(np.sqrt(self.covariance[self.names.index(name), self.names.index(name)]))

    def block(self, prefix: str) -> np.ndarray:
        idx = [k for k, n in enumerate(self.names) if n.startswith(prefix + ".")]
        return self.covariance[np.ix_(idx, idx)]


def solve(cameras: list[CameraState], objects: list[ObjectState], obs: Observations, *, max_iter: int = 50,
          tol: float = 1e-10) -> MatchResult:
    """Weighted Gauss-Newton (eq. 35) over the free blocks; at least as many equations as unknowns are needed."""
    layout = _Layout(cameras, objects)
    n_eq = 2 * (obs.n_lines + obs.n_points)
    if layout.n == 0:
        raise ValueError("nothing to solve: every camera and object is fixed")
    if n_eq < layout.n:
        raise ValueError(f"{n_eq} equations for {layout.n} unknowns: more lines or points are needed")

    def evaluate(cams, objs):
        r, J, W = residuals_and_jacobian(cams, objs, obs, layout)
        Wr = (W @ r[:, :, None])[:, :, 0]
        return r, J, W, float(np.dot(r.ravel(), Wr.ravel())) + prior(cams)[0], Wr

    def normal_matrix(J, W):
        """J^T W J (eq. 40) as one matrix product over the stacked rows."""
        Jf = J.reshape(-1, layout.n)
        return Jf.T @ (W @ J).reshape(-1, layout.n)

    def prior(cams):
        """Cost, normal-matrix and gradient terms of the focal-length priors: a telephoto's focal length and
        distance are nearly interchangeable for a small object, the nominal lens settles it."""
        cost, N, g = 0.0, np.zeros((layout.n, layout.n)), np.zeros(layout.n)
        for i, c in enumerate(cams):
            if i in layout.cam_f and c.f_prior:
                k, s = layout.cam_f[i], c.f_prior * c.f_prior_rel
                r, j = (c.f - c.f_prior) / s, c.f / s
                cost += r * r
                N[k, k] += j * j
                g[k] += j * r
        return cost, N, g

    r, J, W, cost, Wr = evaluate(cameras, objects)
    lam = 0.0
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the iterations taken are read after the loop
        _, Np, gp = prior(cameras)
        N = normal_matrix(J, W) + Np  # eq. 40
        g = J.reshape(-1, layout.n).T @ Wr.ravel() + gp  # eq. 41
        scale = np.sqrt(np.maximum(np.diag(N), 1e-30))
        Ns = N / np.outer(scale, scale)
        while True:
            A = Ns + lam * np.eye(layout.n)
            try:
                dx = -np.linalg.solve(A, g / scale) / scale
            except np.linalg.LinAlgError:
                dx = -np.linalg.lstsq(A, g / scale, rcond=None)[0] / scale
            cams, objs = apply_step(cameras, objects, layout, dx)
            r2, J2, W2, cost2, Wr2 = evaluate(cams, objs)
            if np.isfinite(cost2) and cost2 <= cost * (1 + 1e-12):
                break
            lam = max(lam * 10, 1e-4)
            if lam > 1e8:
                cams, objs, cost2 = cameras, objects, cost
                r2, J2, W2, Wr2 = r, J, W, Wr
                dx = np.zeros(layout.n)
                break
        lam = lam / 10 if lam > 1e-6 else 0.0
        cameras, objects, r, J, W, Wr = cams, objs, r2, J2, W2, Wr2
        small = float(np.max(np.abs(dx * scale))) < 1e-6 or cost - cost2 <= tol * max(cost, 1e-300)
        cost = cost2
        if small:
            converged = True
            break
    N = normal_matrix(J, W) + prior(cameras)[1]
    cov = np.linalg.pinv(N)
    flat = np.abs(r).ravel()
    return MatchResult(cameras, objects, cov, layout.names, it, converged, cost,
                       float(np.sqrt(np.mean(flat**2))), float(flat.max()), obs.n_lines, obs.n_points)


def numeric_jacobian(cameras, objects, obs: Observations, eps: float = 1e-7) -> np.ndarray:
    """Central differences of the stacked residuals over the incremental unknowns (for checking)."""
    layout = _Layout(cameras, objects)
    J = np.zeros((2 * (obs.n_lines + obs.n_points), layout.n))
    for k in range(layout.n):
        d = np.zeros(layout.n)
        d[k] = eps
        rp = residuals_and_jacobian(*apply_step(cameras, objects, layout, d), obs, layout)[0].ravel()
        rm = residuals_and_jacobian(*apply_step(cameras, objects, layout, -d), obs, layout)[0].ravel()
        J[:, k] = (rp - rm) / (2 * eps)
    return J


# ---------------------------------------------------------------- error ellipses (eqs. 51-52)

def error_ellipse(cov: np.ndarray, i: int, j: int, n: int = 64, scale: float = 1.0) -> np.ndarray:
    """Points (n+1, 2) of the 1-sigma ellipse of variables i, j: (x/si)^2 - 2 rho (x/si)(y/sj) + (y/sj)^2 = 1 - rho^2."""
    S = cov[np.ix_([i, j], [i, j])] * scale**2
    vals, vecs = np.linalg.eigh(S)
    t = np.linspace(0, 2 * np.pi, n + 1)
    return (vecs @ (np.sqrt(np.maximum(vals, 0))[:, None] * np.vstack([np.cos(t), np.sin(t)]))).T


def ellipse_summary(cov: np.ndarray, i: int, j: int) -> dict:
    si, sj = np.sqrt(cov[i, i]), np.sqrt(cov[j, j])
    return {"sigma_i": float(si), "sigma_j": float(sj), "rho": float(cov[i, j] / (si * sj)) if si * sj > 0 else 0.0}
