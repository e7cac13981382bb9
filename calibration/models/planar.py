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
- solver (planar_solver.py): Levenberg-Marquardt on the normal equations (at most 15 unknowns), with the
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

from dataclasses import dataclass, field, replace

import numpy as np

from calibration.errors import CalibrationInputError
from calibration.models.planar_solver import Parameterisation, State, apply_h, distortion, pinv, points, solve_psd

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
    # the calibrated region: the convex hull (px, counter-clockwise) of the pixels the fit used; beyond it the map
    # extrapolates. None: not known (a map made before it was kept)
    region: tuple[tuple[float, float], ...] | None = None

    def on_image(self, uv) -> np.ndarray:
        """Per pixel: on the image (pixel centres at whole numbers, so each edge lies half a pixel out)."""
        uv = points(uv)
        w, h = self.image_size
        return (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)

    def off_image(self, u: float, v: float, whose: str) -> str:
        """What to say of pixel (u, v) that is not on the image (`whose`: "cam1's", "the calibration's")."""
        w, h = self.image_size
        return (f"pixel ({u:g}, {v:g}) is outside {whose} {w} x {h} image: allowed u_px -0.5 to {w - 0.5:g}, "
                f"v_px -0.5 to {h - 0.5:g}")

    def in_region(self, uv) -> np.ndarray | None:
        """Per pixel: inside the calibrated region (or on its edge); None if the map keeps no region."""
        if self.region is None:
            return None
        return inside_hull(np.array(self.region, dtype=float), points(uv))

    def corrected(self, uv) -> np.ndarray:
        """Eq. B2: distorted pixels -> corrected pixels (u', v')."""
        uv = points(uv)
        n = (uv - self.centre) / self.scale
        return uv + self.scale * distortion(n, self.radial, self.tangential)

    def pixel_to_plane(self, uv) -> np.ndarray:
        return apply_h(self.H, self.corrected(uv))

    def plane_to_pixel(self, xy) -> np.ndarray:
        """Inverse of B1 exactly, then of B2 by fixed-point iteration (the correction is small and smooth)."""
        target = apply_h(np.linalg.inv(self.H), points(xy))
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
                "p2": float(self.tangential[1]),
                **({"region_px": [[float(u), float(v)] for u, v in self.region]} if self.region is not None else {})}

    @classmethod
    def from_dict(cls, d: dict) -> "PlanarMap":
        keys = {"model", "version", "image_size", "a", "b", "c", "d", "e", "f", "g", "h", "uc", "vc", "s",
                "radial", "p1", "p2"}
        if not isinstance(d, dict):
            raise CalibrationInputError(f"a {MODEL_NAME} map must be a JSON object, got {type(d).__name__}")
        missing, unknown = keys - set(d), set(d) - keys - {"region_px"}  # region_px: optional (older maps lack it)
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
            region = np.array(d["region_px"], dtype=float) if "region_px" in d else None
        except (TypeError, ValueError, IndexError) as exc:
            raise CalibrationInputError(f"{MODEL_NAME} map has a non-numeric value: {exc}") from None
        if not (np.all(np.isfinite(H)) and np.isfinite(m.scale) and m.scale > 0 and len(m.radial) <= 3):
            raise CalibrationInputError(f"{MODEL_NAME} map has non-finite values, s <= 0 or more than 3 radial terms")
        if region is not None:
            if region.ndim != 2 or region.shape[0] < 3 or region.shape[1] != 2 or not np.all(np.isfinite(region)):
                raise CalibrationInputError(f"{MODEL_NAME} map: region_px must be 3 or more finite [u, v] pixels")
            m = replace(m, region=tuple((float(u), float(v)) for u, v in region))
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
    _model: "Parameterisation" = field(repr=False, default=None)
    _theta: np.ndarray = field(repr=False, default=None)

    @property
    def theta(self) -> np.ndarray:
        """The fitted normalised parameters, for a caller that refines them inside a larger adjustment."""
        return self._theta.copy()

    def pixel_to_plane_with(self, theta, uv) -> np.ndarray:
        return self._model.pixel_to_plane(np.asarray(theta, dtype=float), points(uv))

    def map_with(self, theta, pixels=None) -> PlanarMap:
        """The map of refined parameters; its calibrated region: the hull of `pixels` (all the refinement used),
        else this fit's."""
        region = self.map.region
        if pixels is not None and len(h := hull(points(pixels))) >= 3:
            region = tuple(map(tuple, h.tolist()))
        return replace(_map_of(self._model, np.asarray(theta, dtype=float)), region=region)

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

    _model: "Parameterisation" = field(repr=False)
    theta: np.ndarray
    covariance: np.ndarray  # of theta, in normalised units
    sigma: float  # one sample's residual, per axis, plane units
    dof: int  # of sigma

    def jacobian(self, uv) -> np.ndarray:
        """(2N, n_params) change of the mapped points (rows x0, y0, x1, ...) per unit of each parameter."""
        return self._model.jacobian(self.theta, points(uv)) * self._model.plane_scale

    def point_covariance(self, uv) -> np.ndarray:
        """(2N, 2N) covariance of the mapped points (rows x0, y0, x1, y1, ...), plane units squared."""
        J = self.jacobian(uv)
        return J @ self.covariance @ J.T

    def std(self, uv) -> np.ndarray:
        """1-σ radial uncertainty of each mapped point."""
        J = self._model.jacobian(self.theta, points(uv)) * self._model.plane_scale
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
            model = Parameterisation(None, None, _image_size(d["image_size"]), options,
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
    model = Parameterisation(uv, xy, _image_size(image_size), options)
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


def _centre_if_supported(model: "Parameterisation", state: "State", mask):
    """Fit with the centre at the image centre, then free it if the score test passes BIC: the decrease of
    the residual sum of squares the full model, linearised there, predicts. Returns the state, the free
    parameters and, if the centre stays fixed, the state as their least-squares solution."""
    centre = np.array([name in ("uc/s", "vc/s") for name in model.names])
    state = model.solve(state, mask, ~centre, "linear", centre_columns=True)  # the test needs them
    J, r = state.rows(mask)
    g = J @ r  # the full model's gradient: zero but for the centre at this optimum
    decrease = float(g @ pinv(J @ J.T) @ g)
    var = float(r @ r) / max(r.size - int((~centre).sum()), 1)
    if decrease > 2 * np.log(r.size) * var:
        return state, np.ones(len(model.names), dtype=bool), None
    return state, ~centre, state


def _drop_unsupported_terms(model: "Parameterisation", state: "State", free, inliers):
    """The smallest of the nested models (fixed centre, then fewer radial terms) that BIC prefers. Each one's
    rise of the residual sum of squares is predicted from this fit (linearised: the Wald statistic); the
    chosen one is refitted from its linearised optimum and its rise checked."""
    J, r = state.rows(inliers)
    J = J[free]
    var = max(float(r @ r) / max(r.size - int(free.sum()), 1), 1e-300)  # of one observation
    cov = pinv(J @ J.T)  # unscaled covariance of the free parameters
    theta = state.theta[free]
    penalty = np.log(r.size)
    best, best_score = None, 0.0
    for candidate in _nested(model.names, free):
        drop = ~candidate[free]  # among the free parameters
        t = theta[drop]
        rise = float(t @ solve_psd(cov[np.ix_(drop, drop)], t))  # Wald: predicted rise of the RSS
        score = penalty * drop.sum() - rise / var
        if score > best_score:
            best, best_score = (candidate, drop), score
    if best is None:
        return state, free
    candidate, drop = best
    start = np.zeros_like(state.theta)  # the dropped parameters at zero, the kept ones absorbing them
    start[candidate] = theta[~drop] - cov[np.ix_(~drop, drop)] @ solve_psd(cov[np.ix_(drop, drop)], theta[drop])
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


def _result(model: "Parameterisation", state: "State", free, inliers, sigma_robust: float) -> PlanarFit:
    """The fit's outputs at the final least-squares state: residuals, sigma, covariance, rejected samples, for
    the model of the free parameters."""
    if not free.all():  # the model selection kept: the same normalisation, fewer parameters
        names = [name for name, f in zip(model.names, free) if f]
        o = model.options
        model = Parameterisation(model.uv, model.xy, model.size,
                                 replace(o, fit_centre=o.fit_centre and "uc/s" in names,
                                         radial_terms=sum(name.startswith("k") for name in names)),
                                 (model.Tp, model.Tw))
        state = State(state.theta[free], state.r, state.J[free])
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
    region = hull(model.uv[inliers])
    region = tuple(map(tuple, region.tolist())) if len(region) >= 3 else None  # inliers on a line: no region
    return PlanarFit(replace(_map_of(model, theta), region=region), residuals, inliers, rejected, sigma_n * scale,
                     sigma_n**2 * pinv(A), model.names, condition, model, theta)


def _map_of(model: Parameterisation, theta) -> PlanarMap:
    """The map of the model's normalised parameters, in pixel and plane units."""
    H, centre, radial, tangential = model.unpack(theta)
    full = np.linalg.inv(model.Tw) @ H @ model.Tp
    return PlanarMap(model.size, full / full[2, 2], (float(centre[0]), float(centre[1])), model.scale,
                     tuple(float(k) for k in radial), (float(tangential[0]), float(tangential[1])))


def hull(uv: np.ndarray) -> np.ndarray:
    """The convex hull of pixels, counter-clockwise (Andrew's monotone chain), without collinear points."""
    pts = np.unique(np.asarray(uv, dtype=float), axis=0)  # sorted by u, then v
    if len(pts) < 3:
        return pts

    def chain(points):
        out: list = []
        for p in points:
            while len(out) >= 2 and _cross(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(chain(pts) + chain(pts[::-1]))


def inside_hull(vertices: np.ndarray, uv: np.ndarray, tolerance_px: float = 1e-6) -> np.ndarray:
    """Per point: inside the convex polygon `vertices` (counter-clockwise) or within `tolerance_px` of it."""
    a, b = vertices, np.roll(vertices, -1, axis=0)
    edge = b - a
    length = np.maximum(np.hypot(edge[:, 0], edge[:, 1]), 1e-300)
    # signed distance of each point to the left of each edge (positive: inside)
    left = (edge[None, :, 0] * (uv[:, None, 1] - a[None, :, 1])
            - edge[None, :, 1] * (uv[:, None, 0] - a[None, :, 0])) / length
    return np.all(left >= -tolerance_px, axis=1)


def _cross(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


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
