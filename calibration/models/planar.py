"""The planar camera model of seed 001 appendix B: pixels -> plane coordinates.

Distortion correction (eq. B2) about a distortion centre (uc, vc), with the radius
normalised by s = max(W, H) / 2 so the coefficients are of order one:

    ũ = (u - uc) / s,  ṽ = (v - vc) / s,  r² = ũ² + ṽ²
    u' = u + s [ ũ (k2 r² + k4 r⁴ + k6 r⁶) + 2 p1 ũ ṽ + p2 (r² + 2 ũ²) ]
    v' = v + s [ ṽ (k2 r² + k4 r⁴ + k6 r⁶) + p1 (r² + 2 ṽ²) + 2 p2 ũ ṽ ]

(the seed's B2 prints the radial factor as 1 + k2 r² + …, which would count the
pixel twice; the correction is the part beyond 1), then the perspective map (eq. B1):

    x = (a u' + b v' + c) / (g u' + h v' + 1),   y = (d u' + e v' + f) / (g u' + h v' + 1)

Fitted by a normalised DLT, then nonlinear least squares in the plane (where a
robot's noise lives) on Hartley-normalised coordinates, with a robust loss,
outlier rejection and the parameter covariance. Unit-agnostic: the plane
coordinates come out in whatever unit they went in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

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
    width, height = _image_size(image_size)
    model = _Parameterisation(uv, xy, (width, height), options)
    theta = model.initial()
    inliers = np.ones(len(uv), dtype=bool)
    sigma = 1.0
    for _ in range(6):  # fit, reject beyond k robust sigmas, refit until the inlier set settles
        theta = model.solve(theta, inliers, "linear")
        # sigma from the median over ALL samples: robust to the outliers themselves, and it does not
        # shrink as samples are rejected (which would cascade into rejecting good ones)
        sigma = model.robust_sigma(theta, np.ones(len(uv), dtype=bool))
        if options.loss != "linear":
            theta = model.solve(theta, inliers, options.loss, f_scale=sigma)
            sigma = model.robust_sigma(theta, np.ones(len(uv), dtype=bool))
        norms = np.linalg.norm(model.residuals(theta), axis=1) / model.plane_scale
        keep = norms <= options.outlier_sigma * sigma
        if keep.sum() < model.min_points or np.array_equal(keep, inliers):
            break
        inliers = keep
    theta = model.solve(theta, inliers, "linear")  # final: plain least squares on clean data
    residuals = model.residuals(theta)
    n_in = int(inliers.sum())
    dof = max(2 * n_in - options.n_params, 1)
    sigma_n = float(np.sqrt(np.sum((residuals[inliers] / model.plane_scale) ** 2) / dof))
    J = model.jacobian(theta)[np.repeat(inliers, 2)]
    JtJ = J.T @ J
    singular = np.linalg.svd(J, compute_uv=False)
    covariance = sigma_n**2 * np.linalg.pinv(JtJ, rcond=1e-12)
    norms = np.linalg.norm(residuals, axis=1)
    rejected = [{"index": int(i), "residual": residuals[i].tolist(),
                 "reason": f"outlier: residual {norms[i] / model.plane_scale / sigma:.1f} robust sigma, "
                           f"beyond the limit of {options.outlier_sigma:g}"}
                for i in np.nonzero(~inliers)[0]]
    return PlanarFit(model.to_map(theta), residuals, inliers, rejected, sigma_n * model.plane_scale,
                     covariance, model.names, float(singular[0] / max(singular[-1], 1e-300)), model, theta)


# -- the fit's parameterisation -------------------------------------------------


class _Parameterisation:
    """Normalised parameters: H_n acts on Hartley-normalised corrected pixels and plane points."""

    def __init__(self, uv, xy, size, options: PlanarModelOptions, normalisation=None):
        """`normalisation`: (Tp, Tw) of an earlier fit, to evaluate its parameters without its samples."""
        self.uv, self.xy, self.size, self.options = uv, xy, size, options
        self.centre0 = np.array([(size[0] - 1) / 2, (size[1] - 1) / 2])
        self.scale = max(size) / 2
        self.Tp, self.Tw = normalisation if normalisation is not None else (_hartley(uv), _hartley(xy))
        self.plane_scale = 1.0 / self.Tw[0, 0]  # plane units per normalised unit
        self.names = [f"h{i}" for i in range(8)]
        if options.fit_centre:
            self.names += ["uc/s", "vc/s"]
        self.names += [f"k{2 * (i + 1)}" for i in range(options.radial_terms)]
        if options.tangential:
            self.names += ["p1", "p2"]
        self.min_points = (options.n_params + 4 + 1) // 2

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

    def pixel_to_plane(self, theta, uv):
        H, centre, radial, tangential = self.unpack(theta)
        n = (uv - centre) / self.scale
        corrected = uv + self.scale * _distortion(n, radial, tangential)
        return _apply_h(np.linalg.inv(self.Tw) @ H @ self.Tp, corrected)

    def residuals(self, theta):
        return self.pixel_to_plane(theta, self.uv) - self.xy

    def robust_sigma(self, theta, mask) -> float:
        """Per-axis sigma in normalised plane units from the median absolute residual, corrected for the
        degrees of freedom the fit takes (residuals are smaller than the noise by sqrt(1 - p/n))."""
        r = self.residuals(theta)[mask] / self.plane_scale
        shrink = np.sqrt(max(1 - self.options.n_params / r.size, 0.1))
        return max(1.4826 * float(np.median(np.abs(r))) / shrink, 1e-12)

    def initial(self):
        """Normalised DLT, no distortion."""
        p = _apply_h(self.Tp, self.uv)
        w = _apply_h(self.Tw, self.xy)
        u, v, x, y = p[:, 0], p[:, 1], w[:, 0], w[:, 1]
        one, zero = np.ones_like(u), np.zeros_like(u)
        A = np.empty((2 * len(u), 9))
        A[0::2] = np.column_stack([u, v, one, zero, zero, zero, -x * u, -x * v, -x])
        A[1::2] = np.column_stack([zero, zero, zero, u, v, one, -y * u, -y * v, -y])
        h = np.linalg.svd(A, full_matrices=False)[2][-1]
        if abs(h[8]) < 1e-12:
            raise CalibrationInputError("the points admit no perspective map (degenerate geometry)")
        extra = self.options.n_params - 8
        return np.concatenate([h[:8] / h[8], np.zeros(extra)])

    def jacobian(self, theta, uv=None):
        """d(normalised plane residual)/d(theta), analytic: (2N, n_params), rows x0, y0, x1, y1, ..."""
        uv = self.uv if uv is None else uv
        o = self.options
        H, centre, radial, (p1, p2) = self.unpack(theta)
        n = (uv - centre) / self.scale
        u, v = n[:, 0], n[:, 1]
        r2 = u * u + v * v
        corrected = uv + self.scale * _distortion(n, radial, (p1, p2))
        p = _apply_affine(self.Tp, corrected)  # normalised corrected pixel
        q = p @ H[:, :2].T + H[:, 2]
        x = q[:, :2] / q[:, 2:3]
        w = q[:, 2]
        cols = []
        # homography entries h0..h7 (h8 = 1)
        for j in range(8):
            row, col = divmod(j, 3)
            pj = p[:, col] if col < 2 else np.ones(len(p))
            d = np.zeros((len(p), 2))
            if row < 2:
                d[:, row] = pj / w
            else:
                d = -x * (pj / w)[:, None]
            cols.append(d)
        # distortion parameters act through the corrected pixel: dx/du' = (H[r, :2] - x H[2, :2]) / w * k
        k = self.Tp[0, 0]
        dxdc = np.stack([(H[0, :2][None, :] - x[:, :1] * H[2, :2][None, :]),
                         (H[1, :2][None, :] - x[:, 1:2] * H[2, :2][None, :])], axis=1) * (k / w)[:, None, None]

        def through(du, dv):  # d(corrected)/d(param) -> d(x)/d(param)
            return np.einsum("nij,nj->ni", dxdc, np.column_stack([du, dv]) * self.scale)

        factor = np.zeros_like(r2)
        slope = np.zeros_like(r2)  # d factor / d r²
        for i, ki in enumerate(radial):
            factor += ki * r2 ** (i + 1)
            slope += ki * (i + 1) * r2**i
        if o.fit_centre:  # uc = uc0 + s * c_u: d(ũ)/d(c_u) = -1
            dDu_du = factor + 2 * u * u * slope + 2 * p1 * v + 6 * p2 * u
            dDu_dv = 2 * u * v * slope + 2 * p1 * u + 2 * p2 * v
            dDv_du = dDu_dv
            dDv_dv = factor + 2 * v * v * slope + 6 * p1 * v + 2 * p2 * u
            cols.append(through(-dDu_du, -dDv_du))
            cols.append(through(-dDu_dv, -dDv_dv))
        for i in range(o.radial_terms):
            power = r2 ** (i + 1)
            cols.append(through(u * power, v * power))
        if o.tangential:
            cols.append(through(2 * u * v, r2 + 2 * v * v))
            cols.append(through(r2 + 2 * u * u, 2 * u * v))
        return np.stack([c.ravel() for c in cols], axis=1)

    def solve(self, theta, mask, loss, f_scale=1.0):
        rows = np.repeat(mask, 2)

        def fun(t):
            return (self.residuals(t)[mask] / self.plane_scale).ravel()

        result = least_squares(fun, theta, jac=lambda t: self.jacobian(t)[rows], method="trf", loss=loss,
                               f_scale=f_scale, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=500)
        return result.x

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
    for name, arr in (("pixel", uv), ("plane", xy)):
        bad = np.nonzero(~np.all(np.isfinite(arr), axis=1))[0]
        if bad.size:
            raise CalibrationInputError(f"{name} coordinates of sample {int(bad[0])} are not finite (NaN or inf)")
    needed = max(4, (options.n_params + 4 + 1) // 2)
    if len(uv) < needed:
        raise CalibrationInputError(f"{len(uv)} points given; the model with {options.n_params} parameters needs at "
                                    f"least {needed} (fewer radial terms or no tangential terms need fewer)")
    _, first = np.unique(np.round(uv, 6), axis=0, return_index=True)
    if first.size < len(uv):
        dup = sorted(set(range(len(uv))) - set(first.tolist()))[0]
        raise CalibrationInputError(f"sample {dup} repeats the pixel of another sample; every point must be distinct")
    for name, arr in (("pixel", uv), ("plane", xy)):
        s = np.linalg.svd(arr - arr.mean(axis=0), compute_uv=False)
        if s[1] < 1e-3 * s[0]:
            raise CalibrationInputError(f"the {name} points are collinear (or nearly): they must span an area, "
                                        "e.g. a grid of at least 3 x 3")
    return uv, xy
