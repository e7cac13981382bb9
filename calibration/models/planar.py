"""The planar camera model of seed 001 appendix B: pixels -> plane coordinates.

Distortion correction (eq. B2) about a distortion centre (uc, vc), with the radius
normalised by s = max(W, H) / 2 so the coefficients are of order one:

    ũ = (u - uc) / s,  ṽ = (v - vc) / s,  r² = ũ² + ṽ²
    u' = u + s [ ũ (k2 r² + k4 r⁴ + k6 r⁶) + 2 p1 ũ ṽ + p2 (r² + 2 ũ²) ]
    v' = v + s [ ṽ (k2 r² + k4 r⁴ + k6 r⁶) + p1 (r² + 2 ṽ²) + 2 p2 ũ ṽ ]

(the seed's B2 prints the radial factor as 1 + k2 r² + …, which would count the
pixel twice; the correction is the part beyond 1), then the perspective map (eq. B1):

    x = (a u' + b v' + c) / (g u' + h v' + 1),   y = (d u' + e v' + f) / (g u' + h v' + 1)

The fit, on Hartley-normalised pixels and plane points, minimises the residuals in the
plane (where a robot's noise lives):

- start: the normalised DLT (no distortion), the null vector of the 9x9 A'A;
- solver: Levenberg-Marquardt on the normal equations (at most 15 unknowns), with the
  analytic Jacobian built with the residuals in one vectorised pass. B2 is linear in its
  coefficients, so its basis functions are computed once while the centre stays fixed;
- robust loss (soft_l1 or huber) by iteratively reweighted least squares with the loss's
  Newton curvature, warm-started from the least-squares solution; residuals beyond
  `outlier_sigma` robust sigmas are rejected and the fit repeated until the inlier set
  settles; the final estimate is plain least squares on the inliers;
- model order (`select_model`, on by default): the options give the most terms the fit may
  use; it keeps the free centre and the higher radial terms only where Schwarz's criterion
  (BIC) says the data support them (see "model order" below): with few or noisy samples they
  would fit the noise and make the map worse between the samples;
- covariance: the residual variance times the pseudo-inverse of J'J (scaled to a unit
  diagonal), and J's condition number from J'J's eigenvalues.

Unit-agnostic: the plane coordinates come out in whatever unit they went in.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import lapack

from ..errors import CalibrationInputError

MODEL_NAME = "planar-b1b2"
LOSSES = ("linear", "soft_l1", "huber")


@dataclass(frozen=True)
class PlanarModelOptions:
    radial_terms: int = 2  # k2, k4 (, k6)
    tangential: bool = True  # p1, p2
    fit_centre: bool = True  # uc, vc free; else the image centre
    loss: str = "soft_l1"
    outlier_sigma: float = 4.0  # reject residuals beyond this many robust sigmas
    select_model: bool = True  # the terms above are the most the fit uses: it drops those the data do not support

    def __post_init__(self):
        if self.radial_terms not in (0, 1, 2, 3):
            raise ValueError(f"radial_terms={self.radial_terms!r}; allowed: 0, 1, 2 or 3")
        if self.loss not in LOSSES:
            raise ValueError(f"loss={self.loss!r}; allowed: {', '.join(LOSSES)}")
        if not self.outlier_sigma > 1:
            raise ValueError(f"outlier_sigma={self.outlier_sigma!r}; allowed: a number above 1")
        if self.radial_terms == 0 and not self.tangential:  # no distortion: its centre means nothing
            object.__setattr__(self, "fit_centre", False)

    @property
    def n_params(self) -> int:
        return 8 + 2 * self.fit_centre + self.radial_terms + 2 * self.tangential


@dataclass(frozen=True)
class PlanarMap:
    """A fitted B1+B2 map in pixel and plane units."""

    image_size: tuple[int, int]
    H: np.ndarray  # 3x3, H[2, 2] = 1: (u', v', 1) -> plane, the a..h of eq. B1
    centre: tuple[float, float]  # (uc, vc) px
    scale: float  # s, px
    radial: tuple[float, ...] = ()  # k2, k4, k6
    tangential: tuple[float, float] = (0.0, 0.0)  # p1, p2

    def corrected(self, uv) -> np.ndarray:
        """Eq. B2: distorted pixels -> corrected pixels (u', v')."""
        uv = _points(uv)
        n = (uv - self.centre) / self.scale
        return uv + self.scale * _distortion(n, self.radial, self.tangential)

    def pixel_to_plane(self, uv) -> np.ndarray:
        return _apply_h(self.H, self.corrected(uv))

    def plane_to_pixel(self, xy) -> np.ndarray:
        """Inverse of B1 exactly, then of B2 by fixed-point iteration (the correction is small and smooth)."""
        target = _apply_h(np.linalg.inv(self.H), _points(xy))
        uv = target.copy()
        for _ in range(100):
            step = target - self.corrected(uv)
            uv += step
            if np.max(np.abs(step), initial=0.0) < 1e-11:
                break
        return uv

    def to_dict(self) -> dict:
        a, b, c, d, e, f, g, h = (float(x) for x in self.H.ravel()[:8])
        return {"model": MODEL_NAME, "version": 1, "image_size": list(self.image_size),
                "a": a, "b": b, "c": c, "d": d, "e": e, "f": f, "g": g, "h": h,
                "uc": float(self.centre[0]), "vc": float(self.centre[1]), "s": float(self.scale),
                "radial": [float(k) for k in self.radial], "p1": float(self.tangential[0]),
                "p2": float(self.tangential[1])}

    @classmethod
    def from_dict(cls, d: dict) -> "PlanarMap":
        keys = {"model", "version", "image_size", "a", "b", "c", "d", "e", "f", "g", "h", "uc", "vc", "s",
                "radial", "p1", "p2"}
        if not isinstance(d, dict):
            raise CalibrationInputError(f"a {MODEL_NAME} map must be a JSON object, got {type(d).__name__}")
        missing, unknown = keys - set(d), set(d) - keys
        if missing or unknown:
            raise CalibrationInputError(f"{MODEL_NAME} map: missing keys {sorted(missing)}, unknown keys "
                                        f"{sorted(unknown)}; expected exactly {sorted(keys)}")
        if d["model"] != MODEL_NAME or d["version"] != 1:
            raise CalibrationInputError(f"map is {d['model']!r} version {d['version']!r}; this cellctl reads "
                                        f"{MODEL_NAME!r} version 1")
        try:
            H = np.array([d[k] for k in "abcdefgh"] + [1.0], dtype=float).reshape(3, 3)
            m = cls((int(d["image_size"][0]), int(d["image_size"][1])), H, (float(d["uc"]), float(d["vc"])),
                    float(d["s"]), tuple(float(k) for k in d["radial"]), (float(d["p1"]), float(d["p2"])))
        except (TypeError, ValueError, IndexError) as exc:
            raise CalibrationInputError(f"{MODEL_NAME} map has a non-numeric value: {exc}") from None
        if not (np.all(np.isfinite(H)) and np.isfinite(m.scale) and m.scale > 0 and len(m.radial) <= 3):
            raise CalibrationInputError(f"{MODEL_NAME} map has non-finite values, s <= 0 or more than 3 radial terms")
        return m


@dataclass
class PlanarFit:
    map: PlanarMap
    residuals: np.ndarray  # (N, 2) mapped pixel minus given plane point, for every sample
    inliers: np.ndarray  # (N,) bool
    rejected: list[dict]
    sigma: float  # residual standard deviation per axis, plane units (inliers)
    covariance: np.ndarray  # of the fit's normalised parameters (param_names), not of a..h
    param_names: list[str]
    condition_number: float
    _model: "_Parameterisation" = field(repr=False, default=None)
    _theta: np.ndarray = field(repr=False, default=None)

    @property
    def theta(self) -> np.ndarray:
        """The fitted normalised parameters, for a caller that refines them inside a larger adjustment."""
        return self._theta.copy()

    def pixel_to_plane_with(self, theta, uv) -> np.ndarray:
        return self._model.pixel_to_plane(np.asarray(theta, dtype=float), _points(uv))

    def map_with(self, theta) -> PlanarMap:
        return self._model.to_map(np.asarray(theta, dtype=float))

    def map_std(self, uv) -> np.ndarray:
        """Predicted 1-σ radial uncertainty of the mapped points, from the parameter covariance."""
        return self.uncertainty().std(uv)

    def uncertainty(self) -> "MapUncertainty":
        """What is known of the map's error, to keep with the calibration."""
        dof = max(2 * int(np.sum(self.inliers)) - self._model.options.n_params, 1)
        return MapUncertainty(self._model, self._theta, self.covariance, self.sigma, dof)

    def uncertainty_with(self, theta, covariance, sigma: float, dof: int) -> "MapUncertainty":
        """The same, for parameters a larger adjustment refined (`theta`, with their covariance)."""
        return MapUncertainty(self._model, np.asarray(theta, dtype=float), np.asarray(covariance, dtype=float),
                              float(sigma), int(dof))


@dataclass(frozen=True)
class MapUncertainty:
    """A fitted map's error as its fit knows it: the covariance of the mapped points at any pixels (the map is
    off by the same amount for every feature seen there) and the residual sigma of one sample, with its degrees
    of freedom. Kept in the calibration's model (`to_dict`), so a later check can tell drift from noise."""

    _model: "_Parameterisation" = field(repr=False)
    theta: np.ndarray
    covariance: np.ndarray  # of theta, in normalised units
    sigma: float  # one sample's residual, per axis, plane units
    dof: int  # of sigma

    def jacobian(self, uv) -> np.ndarray:
        """(2N, n_params) change of the mapped points (rows x0, y0, x1, ...) per unit of each parameter."""
        return self._model.jacobian(self.theta, _points(uv)) * self._model.plane_scale

    def point_covariance(self, uv) -> np.ndarray:
        """(2N, 2N) covariance of the mapped points (rows x0, y0, x1, y1, ...), plane units squared."""
        J = self.jacobian(uv)
        return J @ self.covariance @ J.T

    def std(self, uv) -> np.ndarray:
        """1-σ radial uncertainty of each mapped point."""
        J = self._model.jacobian(self.theta, _points(uv)) * self._model.plane_scale
        var = np.einsum("ij,jk,ik->i", J, self.covariance, J).reshape(-1, 2)
        return np.sqrt(np.clip(var.sum(axis=1), 0, None))

    def to_dict(self) -> dict:
        m = self._model
        return {"image_size": list(m.size), "Tp": m.Tp.tolist(), "Tw": m.Tw.tolist(), "names": list(m.names),
                "theta": self.theta.tolist(), "covariance": self.covariance.tolist(), "sigma": self.sigma,
                "dof": self.dof}

    @classmethod
    def from_dict(cls, d: dict) -> "MapUncertainty":
        try:
            names = list(d["names"])
            options = PlanarModelOptions(radial_terms=sum(n.startswith("k") for n in names), tangential="p1" in names,
                                         fit_centre="uc/s" in names)
            model = _Parameterisation(None, None, _image_size(d["image_size"]), options,
                                      (np.array(d["Tp"], dtype=float), np.array(d["Tw"], dtype=float)))
            theta, cov = np.array(d["theta"], dtype=float), np.array(d["covariance"], dtype=float)
            sigma, dof = float(d["sigma"]), int(d["dof"])
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationInputError(f"map uncertainty record is incomplete or not numeric ({exc}); it needs "
                                        "image_size, Tp, Tw, names, theta, covariance, sigma, dof") from None
        if model.names != names or theta.shape != (len(names),) or cov.shape != (len(names),) * 2:
            raise CalibrationInputError(f"map uncertainty record: parameters {names} do not match theta "
                                        f"{theta.shape} and covariance {cov.shape}")
        return cls(model, theta, cov, sigma, dof)


def fit_planar_map(uv, xy, image_size, options: PlanarModelOptions = PlanarModelOptions()) -> PlanarFit:
    uv, xy = _validate(uv, xy, options)
    model = _Parameterisation(uv, xy, _image_size(image_size), options)
    every = np.ones(len(uv), dtype=bool)
    state = model.state(model.initial(), centre_columns=False)  # no distortion yet: the centre's columns are zero
    free = np.ones(len(model.names), dtype=bool)  # the parameters the fit moves; the others stay at zero
    linear = None  # the plain least-squares solution for the current inliers and free parameters, once solved
    if options.select_model and options.fit_centre:
        state, free, linear = _centre_if_supported(model, state, every)
    inliers = every
    for _ in range(6):  # fit, reject beyond k robust sigmas, refit until the inlier set settles
        state = linear = linear if linear is not None else model.solve(state, inliers, free, "linear")
        # sigma from the median over ALL samples: robust to the outliers themselves, and it does not
        # shrink as samples are rejected (which would cascade into rejecting good ones)
        sigma = model.robust_sigma(state.r, free.sum())
        if options.loss != "linear":  # it only decides the inliers: ftol 1e-5 leaves a residual ~0.003 sigma off
            state = model.solve(state, inliers, free, options.loss, f_scale=sigma, xtol=1e-6, ftol=1e-5)
            sigma = model.robust_sigma(state.r, free.sum())
        keep = np.hypot(state.r[0], state.r[1]) <= options.outlier_sigma * sigma
        if keep.sum() < model.min_points or np.array_equal(keep, inliers):
            break
        inliers, linear = keep, None
    # final: plain least squares on clean data (already solved if the last round kept the inlier set)
    state = linear if linear is not None else model.solve(state, inliers, free, "linear")
    if options.select_model:
        state, free = _drop_unsupported_terms(model, state, free, inliers)
    return _result(model, state, free, inliers, sigma)


# -- model order ------------------------------------------------------------------
# Terms the data cannot support fit the noise, and the map gets worse between the samples. A free centre is
# the worst case: a shift of the k2 term is exactly a change of p1, p2 and H, so the centre is told only by
# k4 (k6); with those small it wanders hundreds of pixels along an almost flat valley of the cost, adding
# more than its two parameters' worth of noise (and making the fit slow). So the options give the most the
# fit may use, and it keeps a group of parameters only when Schwarz's criterion (BIC) supports it: when it
# lowers the residual sum of squares by more than ln(n_obs) residual variances per parameter. Exact samples
# keep every term they need; noisy ones keep a term once its effect stands out of the noise.


def _centre_if_supported(model: "_Parameterisation", state: "_State", mask):
    """Fit with the centre at the image centre, then free it if the score test passes BIC: the decrease of
    the residual sum of squares the full model, linearised there, predicts. Returns the state, the free
    parameters and, if the centre stays fixed, the state as their least-squares solution."""
    centre = np.array([name in ("uc/s", "vc/s") for name in model.names])
    state = model.solve(state, mask, ~centre, "linear", centre_columns=True)  # the test needs them
    J, r = state.rows(mask)
    g = J @ r  # the full model's gradient: zero but for the centre at this optimum
    decrease = float(g @ _pinv(J @ J.T) @ g)
    var = float(r @ r) / max(r.size - int((~centre).sum()), 1)
    if decrease > 2 * np.log(r.size) * var:
        return state, np.ones(len(model.names), dtype=bool), None
    return state, ~centre, state


def _drop_unsupported_terms(model: "_Parameterisation", state: "_State", free, inliers):
    """The smallest of the nested models (fixed centre, then fewer radial terms) that BIC prefers. Each one's
    rise of the residual sum of squares is predicted from this fit (linearised: the Wald statistic); the
    chosen one is refitted from its linearised optimum and its rise checked."""
    J, r = state.rows(inliers)
    J = J[free]
    var = max(float(r @ r) / max(r.size - int(free.sum()), 1), 1e-300)  # of one observation
    cov = _pinv(J @ J.T)  # unscaled covariance of the free parameters
    theta = state.theta[free]
    penalty = np.log(r.size)
    best, best_score = None, 0.0
    for candidate in _nested(model.names, free):
        drop = ~candidate[free]  # among the free parameters
        t = theta[drop]
        rise = float(t @ _solve_psd(cov[np.ix_(drop, drop)], t))  # Wald: predicted rise of the RSS
        score = penalty * drop.sum() - rise / var
        if score > best_score:
            best, best_score = (candidate, drop), score
    if best is None:
        return state, free
    candidate, drop = best
    start = np.zeros_like(state.theta)  # the dropped parameters at zero, the kept ones absorbing them
    start[candidate] = theta[~drop] - cov[np.ix_(~drop, drop)] @ _solve_psd(cov[np.ix_(drop, drop)], theta[drop])
    refit = model.solve(model.state(start), inliers, candidate, "linear")
    if np.sum(refit.r[:, inliers] ** 2) - r @ r >= penalty * drop.sum() * var:  # the linearisation was too hopeful
        return state, free
    return refit, candidate


def _nested(names, free) -> list[np.ndarray]:
    """The smaller models selection may choose, as masks of free parameters, each inside the one before: the
    centre fixed at the image centre, then the highest radial terms dropped one by one (k2 stays). p1 and p2
    stay as the options say (BIC would drop them at a few hundred samples, where they still matter)."""
    out, f = [], free.copy()
    centre = np.array([name in ("uc/s", "vc/s") for name in names])
    if (f & centre).any():
        f = f & ~centre
        out.append(f)
    radial = [i for i, name in enumerate(names) if name.startswith("k") and f[i]]
    for i in radial[:0:-1]:
        f = f.copy()
        f[i] = False
        out.append(f)
    return out


def _result(model: "_Parameterisation", state: "_State", free, inliers, sigma_robust: float) -> PlanarFit:
    """The fit's outputs at the final least-squares state: residuals, sigma, covariance, rejected samples, for
    the model of the free parameters."""
    if not free.all():  # the model selection kept: the same normalisation, fewer parameters
        names = [name for name, f in zip(model.names, free) if f]
        o = model.options
        model = model.reduced(replace(o, fit_centre=o.fit_centre and "uc/s" in names,
                                      radial_terms=sum(name.startswith("k") for name in names)))
        state = _State(state.theta[free], state.r, state.J[free])
    theta, scale = state.theta, model.plane_scale
    residuals = np.ascontiguousarray(state.r.T) * scale
    J, r = state.rows(inliers)
    dof = max(r.size - theta.size, 1)
    sigma_n = float(np.sqrt(r @ r / dof))
    A = J @ J.T
    extremes = np.linalg.eigvalsh(A)[[0, -1]]  # J's condition number from J'J (resolved up to about 1e8)
    condition = float(np.sqrt(extremes[1] / max(extremes[0], extremes[1] * 1e-32)))
    norms = np.hypot(state.r[0], state.r[1])
    rejected = [{"index": int(i), "residual": residuals[i].tolist(),
                 "reason": f"outlier: residual {norms[i] / sigma_robust:.1f} robust sigma, "
                           f"beyond the limit of {model.options.outlier_sigma:g}"}
                for i in np.nonzero(~inliers)[0]]
    return PlanarFit(model.to_map(theta), residuals, inliers, rejected, sigma_n * scale, sigma_n**2 * _pinv(A),
                     model.names, condition, model, theta)


def _solve_psd(A, b):
    """A⁺ b for a symmetric positive semi-definite A: by Cholesky, or the pseudo-inverse if A is singular."""
    _, x, info = lapack.dposv(A, b)
    return x if not info else _pinv(A) @ b


def _pinv(A):
    """Pseudo-inverse of a symmetric positive semi-definite A = J'J, from its eigenvalues after scaling it to a
    unit diagonal (the parameters' units differ by orders of magnitude); directions below 1e-12 of the
    largest eigenvalue count as undetermined."""
    d = np.sqrt(np.diag(A))
    d[d == 0] = 1.0
    values, vectors = np.linalg.eigh(A / np.outer(d, d))
    good = values > 1e-12 * values[-1]
    return (vectors[:, good] / values[good]) @ vectors[:, good].T / np.outer(d, d)


# -- the fit's parameterisation -------------------------------------------------


@dataclass
class _State:
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


def _names(options: PlanarModelOptions) -> list[str]:
    names = [f"h{i}" for i in range(8)]
    if options.fit_centre:
        names += ["uc/s", "vc/s"]
    names += [f"k{2 * (i + 1)}" for i in range(options.radial_terms)]
    if options.tangential:
        names += ["p1", "p2"]
    return names


class _Parameterisation:
    """Normalised parameters: H_n acts on Hartley-normalised corrected pixels and plane points."""

    def __init__(self, uv, xy, size, options: PlanarModelOptions, normalisation=None):
        """`normalisation`: (Tp, Tw) of an earlier fit, to evaluate its parameters without its samples."""
        self.uv, self.xy, self.size, self.options = uv, xy, size, options
        self.centre0 = np.array([(size[0] - 1) / 2, (size[1] - 1) / 2])
        self.scale = max(size) / 2
        self.Tp, self.Tw = normalisation if normalisation is not None else (_hartley(uv), _hartley(xy))
        self.plane_scale = 1.0 / self.Tw[0, 0]  # plane units per normalised unit
        if xy is not None:  # the samples as contiguous columns; the plane points normalised
            self.columns = uv[:, 0].copy(), uv[:, 1].copy()
            self.target = _apply_affine(self.Tw, xy).T.copy()
        self.names = _names(options)
        self.min_points = (options.n_params + 4 + 1) // 2
        self._basis = None  # (centre, basis) of the samples

    def reduced(self, options: PlanarModelOptions) -> "_Parameterisation":
        """The same samples and normalisation with fewer parameters."""
        other = copy.copy(self)
        other.options, other.names = options, _names(options)
        other.min_points = (options.n_params + 4 + 1) // 2
        other._basis = None
        return other

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

    def state(self, theta, centre_columns=True) -> _State:
        x, y, J = self.evaluate(theta, centre_columns=centre_columns)
        r = np.empty((2, len(x)))
        np.subtract(x, self.target[0], out=r[0])
        np.subtract(y, self.target[1], out=r[1])
        return _State(theta, r, J)

    def pixel_to_plane(self, theta, uv):
        x, y, _ = self.evaluate(theta, uv, jacobian=False)
        return np.column_stack([x - self.Tw[0, 2], y - self.Tw[1, 2]]) * self.plane_scale

    def residuals(self, theta):
        """Mapped pixel minus given plane point, plane units."""
        return self.pixel_to_plane(theta, self.uv) - self.xy

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
        p = _apply_affine(self.Tp, self.uv)
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

    def solve(self, state: _State, mask, free, loss, f_scale=1.0, xtol=1e-12, ftol=1e-10, max_iter=500,
              centre_columns=None) -> _State:
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

    def to_map(self, theta) -> PlanarMap:
        H, centre, radial, tangential = self.unpack(theta)
        full = np.linalg.inv(self.Tw) @ H @ self.Tp
        return PlanarMap(self.size, full / full[2, 2], (float(centre[0]), float(centre[1])), self.scale,
                         tuple(float(k) for k in radial), (float(tangential[0]), float(tangential[1])))


# -- helpers ------------------------------------------------------------------------


def _distortion(n, radial, tangential):
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


def _apply_h(H, p):
    q = p @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:3]


def _apply_affine(T, p):
    return p @ T[:2, :2].T + T[:2, 2]


def _hartley(p):
    """Translate to the centroid and scale to a mean distance of sqrt(2)."""
    c = p.mean(axis=0)
    d = np.mean(np.linalg.norm(p - c, axis=1))
    k = np.sqrt(2) / d
    return np.array([[k, 0, -k * c[0]], [0, k, -k * c[1]], [0, 0, 1.0]])


def _numeric_jacobian(fun, theta, rel=1e-6):
    f0 = fun(theta)
    J = np.empty((f0.size, theta.size))
    for j in range(theta.size):
        step = rel * max(1.0, abs(theta[j]))
        t = theta.copy()
        t[j] += step
        f1 = fun(t)
        t[j] -= 2 * step
        J[:, j] = (f1 - fun(t)) / (2 * step)
    return J


def _points(p) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    return p.reshape(1, 2) if p.shape == (2,) else p


def _image_size(size) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in size)
    except (TypeError, ValueError):
        raise CalibrationInputError(f"image_size must be (width, height) in pixels, got {size!r}") from None
    if w <= 0 or h <= 0:
        raise CalibrationInputError(f"image_size must be positive, got {size!r}")
    return w, h


def _validate(uv, xy, options):
    uv, xy = np.asarray(uv, dtype=float), np.asarray(xy, dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2 or xy.shape != uv.shape:
        raise CalibrationInputError(f"pixels and plane points must both be (N, 2) arrays, got {uv.shape} and {xy.shape}")
    if not (np.isfinite(uv).all() and np.isfinite(xy).all()):  # name the first sample that is not
        for name, arr in (("pixel", uv), ("plane", xy)):
            bad = np.nonzero(~np.all(np.isfinite(arr), axis=1))[0]
            if bad.size:
                raise CalibrationInputError(f"{name} coordinates of sample {int(bad[0])} are not finite (NaN or inf)")
    needed = max(4, (options.n_params + 4 + 1) // 2)
    if len(uv) < needed:
        raise CalibrationInputError(f"{len(uv)} points given; the model with {options.n_params} parameters needs at "
                                    f"least {needed} (fewer radial terms or no tangential terms need fewer)")
    key = np.round(uv, 6)
    order = np.lexsort((key[:, 1], key[:, 0]))  # stable: equal pixels stay in sample order
    repeats = np.all(key[order[1:]] == key[order[:-1]], axis=1)
    if repeats.any():
        dup = int(order[1:][repeats].min())  # the first sample that repeats an earlier one
        raise CalibrationInputError(f"sample {dup} repeats the pixel of another sample; every point must be distinct")
    for name, arr in (("pixel", uv), ("plane", xy)):
        centred = arr - arr.mean(axis=0)
        spread = np.linalg.eigvalsh(centred.T @ centred)  # the squared singular values, ascending
        if spread[0] < 1e-6 * spread[1]:
            raise CalibrationInputError(f"the {name} points are collinear (or nearly): they must span an area, "
                                        "e.g. a grid of at least 3 x 3")
    return uv, xy
