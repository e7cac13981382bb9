"""The planar B1+B2 fit's parameterisation and its solver (calibration/models/planar.py says what the fit does):
normalised parameters, residuals and the analytic Jacobian in one vectorised pass, and a Levenberg-Marquardt on
the normal equations with iteratively reweighted robust losses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from calibration.errors import CalibrationInputError


@dataclass
class State:
    """A parameter vector with what the solver needs there, evaluated once. Parameter-major, so that each
    Jacobian column is contiguous and built in one operation."""

    theta: np.ndarray
    r: np.ndarray  # (2, N) residuals x, y of each sample, normalised plane units
    J: np.ndarray  # (n_params, 2, N) d r / d theta

    def rows(self, mask):
        """The transposed Jacobian (n_params, 2n) and the residuals (2n,) of the samples in mask."""
        if mask.all():
            return self.J.reshape(self.theta.size, -1), self.r.ravel()
        return self.J[:, :, mask].reshape(self.theta.size, -1), self.r[:, mask].ravel()


def parameter_names(options) -> list[str]:
    names = [f"h{i}" for i in range(8)]
    if options.fit_centre:
        names += ["uc/s", "vc/s"]
    names += [f"k{2 * (i + 1)}" for i in range(options.radial_terms)]
    if options.tangential:
        names += ["p1", "p2"]
    return names


class Parameterisation:
    """Normalised parameters: H_n acts on Hartley-normalised corrected pixels and plane points."""

    def __init__(self, uv, xy, size, options, normalisation=None):
        """`normalisation`: (Tp, Tw) of an earlier fit, to evaluate its parameters without its samples."""
        self.uv, self.xy, self.size, self.options = uv, xy, size, options
        self.centre0 = np.array([(size[0] - 1) / 2, (size[1] - 1) / 2])
        self.scale = max(size) / 2
        self.Tp, self.Tw = normalisation if normalisation is not None else (hartley(uv), hartley(xy))
        self.plane_scale = 1.0 / self.Tw[0, 0]  # plane units per normalised unit
        if xy is not None:  # the samples as contiguous columns; the plane points normalised
            self.columns = uv[:, 0].copy(), uv[:, 1].copy()
            self.target = apply_affine(self.Tw, xy).T.copy()
        self.names = parameter_names(options)
        self.min_points = (options.n_params + 4 + 1) // 2
        self._basis = None  # (centre, basis) of the samples

    def unpack(self, theta):
        o = self.options
        H = np.append(theta[:8], 1.0).reshape(3, 3)
        i = 8
        centre = self.centre0
        if o.fit_centre:
            centre = self.centre0 + theta[8:10] * self.scale
            i = 10
        radial = tuple(theta[i : i + o.radial_terms])
        i += o.radial_terms
        tangential = tuple(theta[i : i + 2]) if o.tangential else (0.0, 0.0)
        return H, centre, radial, tangential

    def basis(self, centre, uv=None):
        """ũ, ṽ, the powers r², r⁴, ... and B2's correction per unit of each coefficient k2, ..., p1, p2, as
        (2, n_coefficients, N): the correction is linear in its coefficients, and this basis depends only on
        the pixels and the centre. For the samples it is kept while the centre stays (as it does unless fitted)."""
        key = (float(centre[0]), float(centre[1]))
        if uv is None and self._basis is not None and self._basis[0] == key:
            return self._basis[1]
        o, s = self.options, self.scale
        U, V = self.columns if uv is None else (uv[:, 0], uv[:, 1])
        u, v = (U - key[0]) / s, (V - key[1]) / s
        r2 = u * u + v * v
        powers = [r2]
        for _ in range(o.radial_terms - 1):
            powers.append(powers[-1] * r2)
        B = np.empty((2, o.radial_terms + 2 * o.tangential, len(u)))
        for i in range(o.radial_terms):
            B[0, i], B[1, i] = u * powers[i], v * powers[i]
        if o.tangential:
            j = o.radial_terms
            B[0, j] = B[1, j + 1] = 2 * u * v
            B[1, j] = r2 + 2 * v * v
            B[0, j + 1] = r2 + 2 * u * u
        basis = u, v, powers, B
        if uv is None:
            self._basis = key, basis
        return basis

    def evaluate(self, theta, uv=None, jacobian=True, centre_columns=True):
        """The mapped points x, y (N,) in normalised plane units and, if asked, their analytic Jacobian
        (n_params, 2, N), in one pass: the intermediate terms serve both. On 1-D columns, which numpy
        handles faster than (N, 2) arrays. `centre_columns=False` leaves the centre's columns zero, for a
        fit that holds the centre."""
        o, s, h = self.options, self.scale, theta
        first = 8 + 2 * o.fit_centre  # the first coefficient of the correction
        centre = self.centre0 + theta[8:10] * s if o.fit_centre else self.centre0
        u, v, powers, B = self.basis(centre, uv)
        k = self.Tp[0, 0]  # Hartley: an isotropic scale, then a shift
        ks = k * s
        shift = centre * k + self.Tp[:2, 2]
        if B.shape[1]:
            D = theta[first:] @ B  # eq. B2's correction, normalised, (2, N)
            pu, pv = (u + D[0]) * ks + shift[0], (v + D[1]) * ks + shift[1]  # normalised corrected pixel
        else:
            pu, pv = u * ks + shift[0], v * ks + shift[1]
        iw = 1.0 / (h[6] * pu + h[7] * pv + 1.0)
        x = (h[0] * pu + h[1] * pv + h[2]) * iw
        y = (h[3] * pu + h[4] * pv + h[5]) * iw
        if not jacobian:
            return x, y, None
        J = np.empty((o.n_params, 2, len(u)))  # [parameter, x or y, sample]
        # homography entries h0..h7 (h8 = 1): x = (h0 pu + h1 pv + h2) / w, w = h6 pu + h7 pv + 1
        J[0, 0], J[1, 0], J[2, 0] = pu * iw, pv * iw, iw
        J[3:6, 0] = 0.0
        J[0:3, 1] = 0.0
        J[3:6, 1] = J[0:3, 0]
        J[6:8, 0] = -x * J[0:2, 0]
        J[6:8, 1] = -y * J[0:2, 0]
        if o.n_params == 8:
            return x, y, J
        # the distortion parameters act through the corrected pixel c: dx/dθ = dx/dc · s dD/dθ, with
        # dx/dc = (H[0, :2] - x H[2, :2]) k / w (likewise y): a 2x2 matrix per sample
        f = ks * iw
        mxu, mxv = (h[0] - x * h[6]) * f, (h[1] - x * h[7]) * f
        myu, myv = (h[3] - y * h[6]) * f, (h[4] - y * h[7]) * f
        J[first:, 0] = mxu * B[0] + mxv * B[1]  # dD/dθ of each coefficient: its basis function
        J[first:, 1] = myu * B[0] + myv * B[1]
        if o.fit_centre and not centre_columns:
            J[8:10] = 0.0
        elif o.fit_centre:  # uc = uc0 + s θ: dũ/dθ = -1, so dD/dθ = -dD/dũ (and likewise for v)
            radial = theta[10 : 10 + o.radial_terms]
            p1, p2 = theta[10 + o.radial_terms :] if o.tangential else (0.0, 0.0)
            factor = slope = 0.0  # k2 r² + k4 r⁴ + ... and its derivative in r²
            for i, k_i in enumerate(radial):
                factor = factor + k_i * powers[i]
                slope = slope + (i + 1) * k_i * (powers[i - 1] if i else 1.0)
            uu, vv, uv_ = u * u, v * v, u * v
            gu = -(factor + 2 * uu * slope + 2 * p1 * v + 6 * p2 * u), -(2 * uv_ * slope + 2 * p1 * u + 2 * p2 * v)
            gv = gu[1], -(factor + 2 * vv * slope + 6 * p1 * v + 2 * p2 * u)  # dDu/dṽ = dDv/dũ
            for j, (du, dv) in enumerate((gu, gv), 8):
                J[j, 0], J[j, 1] = mxu * du + mxv * dv, myu * du + myv * dv
        return x, y, J

    def state(self, theta, centre_columns=True) -> State:
        x, y, J = self.evaluate(theta, centre_columns=centre_columns)
        r = np.empty((2, len(x)))
        np.subtract(x, self.target[0], out=r[0])
        np.subtract(y, self.target[1], out=r[1])
        return State(theta, r, J)

    def pixel_to_plane(self, theta, uv):
        x, y, _ = self.evaluate(theta, uv, jacobian=False)
        return np.column_stack([x - self.Tw[0, 2], y - self.Tw[1, 2]]) * self.plane_scale

    def jacobian(self, theta, uv=None):
        """d(normalised plane point)/d(theta), analytic: (2N, n_params), rows x0, y0, x1, y1, ..."""
        return self.evaluate(theta, uv)[2].T.reshape(-1, self.options.n_params)

    def robust_sigma(self, r, n_params) -> float:
        """Per-axis sigma in normalised plane units from the median absolute residual, corrected for the
        degrees of freedom the fit takes (residuals are smaller than the noise by sqrt(1 - p/n))."""
        shrink = np.sqrt(max(1 - n_params / r.size, 0.1))
        a = np.sort(np.abs(r), axis=None)  # the median, without np.median's overhead
        median = 0.5 * float(a[(a.size - 1) // 2] + a[a.size // 2])
        return max(1.4826 * median / shrink, 1e-12)

    def initial(self):
        """Normalised DLT, no distortion: the null vector of A, from the 9x9 A'A (cheaper than A's SVD)."""
        p = apply_affine(self.Tp, self.uv)
        u, v, (x, y) = p[:, 0], p[:, 1], self.target
        A = np.zeros((9, 2, len(u)))  # transposed, as the Jacobian
        A[0, 0], A[1, 0], A[2, 0] = u, v, 1.0
        A[3, 1], A[4, 1], A[5, 1] = u, v, 1.0
        A[6:9, 0] = -x * A[0:3, 0]
        A[6:9, 1] = -y * A[3:6, 1]
        A = A.reshape(9, -1)
        h = np.linalg.eigh(A @ A.T)[1][:, 0]
        if abs(h[8]) < 1e-12:
            raise CalibrationInputError("the points admit no perspective map (degenerate geometry)")
        extra = self.options.n_params - 8
        return np.concatenate([h[:8] / h[8], np.zeros(extra)])

    def solve(self, state: State, mask, free, loss, f_scale=1.0, xtol=1e-12, ftol=1e-10, max_iter=500,
              centre_columns=None) -> State:
        """Levenberg-Marquardt on the normal equations (at most 15 unknowns) over the samples in `mask`, moving
        the `free` parameters, from a state already evaluated. A robust loss rho(z), z = (r / f_scale)², by
        iteratively reweighted least squares with Newton's curvature of the loss: the gradient weights each
        residual by rho'(z), the normal matrix by rho'(z) + 2 z rho''(z) (plain reweighting converges only
        linearly). Stops when a step changes no parameter by more than xtol (relative) or would lower the
        cost by less than ftol of it (for least squares, 1e-10 leaves the map within 1e-5 of the noise).
        `centre_columns`: whether the states evaluated carry the centre's columns (by default if it moves)."""
        # a weight of 0 or 1 per residual (x of every sample, then y); 1.0 when every sample is in
        m = 1.0 if mask.all() else np.tile(mask, 2).astype(float)
        f2 = f_scale**2

        def cost_and_weights(st):  # the cost, and the weights of the gradient and of the normal matrix
            r = st.r.ravel()
            if loss == "linear":
                return float(r @ (m * r)), m, m
            z = r * r / f2
            if loss == "soft_l1":  # rho = 2 (sqrt(1 + z) - 1)
                root = np.sqrt(1 + z)
                return 2 * f2 * float(np.sum(m * (root - 1))), m / root, m / (root * root * root)
            outer = z > 1  # huber: rho = z inside, 2 sqrt(z) - 1 outside (where its curvature is zero)
            root = np.sqrt(np.where(outer, z, 1.0))
            return f2 * float(np.sum(m * np.where(outer, 2 * root - 1, z))), m / root, m * ~outer

        cost, wg, wa = cost_and_weights(state)
        lam, nu = 1e-6, 2.0  # start as Gauss-Newton: the problem is nearly linear near a DLT start
        if centre_columns is None:  # the centre's columns, when it moves
            centre_columns = not self.options.fit_centre or bool(free[8])
        for _ in range(max_iter):
            J = state.J.reshape(state.theta.size, -1)
            J = J if free.all() else J[free]
            A, g = (J if np.isscalar(wa) else J * wa) @ J.T, J @ (wg * state.r.ravel())
            d = np.diag(A)
            d = np.maximum(d, 1e-12 * d.max())  # Marquardt's scaling; the floor for a column still zero
            magnitude = np.abs(state.theta).max() + xtol
            while True:
                _, step, info = lapack.dposv(A + np.diag(lam * d), -g)  # Cholesky: A + lam D is positive definite
                if not info:  # (unless rounding made it not: then damp more)
                    # the decrease of the cost the quadratic model expects (gradient 2g, Hessian 2A), with
                    # step' A step = -g' step - lam step' D step
                    predicted = lam * (d @ (step * step)) - g @ step
                    if np.abs(step).max() <= xtol * magnitude or predicted <= ftol * cost:
                        return state  # converged (the state returned is the one evaluated)
                    theta = state.theta.copy()
                    theta[free] += step
                    trial = self.state(theta, centre_columns)
                    trial_cost, trial_wg, trial_wa = cost_and_weights(trial)
                    gain = (cost - trial_cost) / predicted  # how well the model predicted the step
                    if gain > 0:
                        state, cost, wg, wa = trial, trial_cost, trial_wg, trial_wa
                        # Nielsen's update: damp less the better the prediction (fewer rejected steps in a
                        # curved valley than dividing by 10)
                        lam, nu = max(lam * max(1 / 3, 1 - (2 * gain - 1) ** 3), 1e-12), 2.0
                        break
                lam, nu = lam * nu, nu * 2  # rejected: damp more, faster each time
                if lam > 1e12:  # no step lowers the cost: at the minimum, to rounding
                    return state
        return state




def distortion(n, radial, tangential):
    """B2's correction on normalised coordinates n = (ũ, ṽ)."""
    u, v = n[:, 0], n[:, 1]
    r2 = u * u + v * v
    factor = np.zeros_like(r2)
    power = r2.copy()
    for k in radial:
        factor += k * power
        power = power * r2
    p1, p2 = tangential
    du = u * factor + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    dv = v * factor + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
    return np.column_stack([du, dv])


def apply_h(H, p):
    q = p @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:3]


def apply_affine(T, p):
    return p @ T[:2, :2].T + T[:2, 2]


def hartley(p):
    """Translate to the centroid and scale to a mean distance of sqrt(2)."""
    c = p.mean(axis=0)
    d = np.mean(np.linalg.norm(p - c, axis=1))
    k = np.sqrt(2) / d
    return np.array([[k, 0, -k * c[0]], [0, k, -k * c[1]], [0, 0, 1.0]])


def points(p) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    return p.reshape(1, 2) if p.shape == (2,) else p


def solve_psd(A, b):
    """A⁺ b for a symmetric positive semi-definite A: by Cholesky, or the pseudo-inverse if A is singular."""
    _, x, info = lapack.dposv(A, b)
    return x if not info else pinv(A) @ b


def pinv(A):
    """Pseudo-inverse of a symmetric positive semi-definite A = J'J, from its eigenvalues after scaling it to a
    unit diagonal (the parameters' units differ by orders of magnitude); directions below 1e-12 of the
    largest eigenvalue count as undetermined."""
    d = np.sqrt(np.diag(A))
    d[d == 0] = 1.0
    values, vectors = np.linalg.eigh(A / np.outer(d, d))
    good = values > 1e-12 * values[-1]
    return (vectors[:, good] / values[good]) @ vectors[:, good].T / np.outer(d, d)
