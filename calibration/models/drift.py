"""Has a calibration drifted? A linear drift model tested against what the calibrations predict.

A check measures things whose readings the active calibrations predict: the residual y (measured minus
predicted) of every measurement. Under "nothing drifted" y is noise with the covariance the calibrations
themselves give (one sample's residual sigma, the map's covariance at the pixels seen, the tool offset's),
computed from a sigma estimated with `dof` degrees of freedom. A drift adds A beta: each target's small model
(a camera: shift, rotation, scale; a nozzle: its offset change), linear in beta.

    beta_hat = (A' S^-1 A)^-1 A' S^-1 y          generalised least squares, all groups at once

Measurements fall into groups (those one calibration's sigma scales). Each group's scale is refined with its
own residuals, pooled with the calibration's (the check's samples are noise samples too), and the tests use
the F distribution with the pooled degrees of freedom, so an uncertain sigma (twelve spheres calibrate camera
2) widens the test rather than raising false alarms:

- a target drifted: the Wald statistic of its block of beta, F(p, dof) under "nothing drifted";
- a group fits the drift model: its residual after the fit against the calibration's sigma, F(n - p, dof).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import fdtrc  # the F distribution's tail (scipy.stats, 0.3 s to import, for one call)


@dataclass
class Group:
    """Measurements that one calibration's noise scales. Rows are scalar (x0, y0, x1, y1, ... for points)."""

    name: str
    residuals: np.ndarray  # (n,) measured minus predicted
    covariance: np.ndarray  # (n, n) under "nothing drifted", at the calibration's sigma
    design: dict[str, np.ndarray]  # drift parameter -> (n,) its column (the reading change per unit)
    dof: int  # of the sigma the covariance was computed with
    home: tuple[str, ...] = ()  # the targets whose parameters this group determines (for the dof count)
    # a part the group's own residuals cannot scale: what a calibration's errors add that the fit absorbs (the
    # readings cannot show it, so it must not shrink when they are quiet). None: nothing of the kind.
    inherited: np.ndarray | None = None

    def __post_init__(self):
        self.residuals = np.asarray(self.residuals, dtype=float)
        self.covariance = np.asarray(self.covariance, dtype=float)
        n = self.residuals.shape[0]
        self.inherited = np.zeros((n, n)) if self.inherited is None else np.asarray(self.inherited, dtype=float)
        if (self.covariance.shape != (n, n) or self.inherited.shape != (n, n)
                or any(np.shape(c) != (n,) for c in self.design.values())):
            raise ValueError(f"group {self.name}: {n} residuals, covariance {self.covariance.shape}, columns "
                             f"{ {k: np.shape(c) for k, c in self.design.items()} }")


@dataclass
class TargetTest:
    statistic: float  # F
    dof: tuple[int, int]
    p_value: float


@dataclass
class DriftFit:
    names: list[str]  # "target.parameter"
    values: np.ndarray
    covariance: np.ndarray
    tests: dict[str, TargetTest]  # per target
    misfit: dict[str, TargetTest]  # per group
    scale: dict[str, float] = field(default_factory=dict)  # per group: pooled variance / calibration's

    def of(self, target: str) -> dict[str, tuple[float, float]]:
        """parameter -> (estimate, standard deviation) of one target."""
        return {n.split(".", 1)[1]: (float(self.values[i]), float(np.sqrt(self.covariance[i, i])))
                for i, n in enumerate(self.names) if n.split(".", 1)[0] == target}


def target_of(parameter: str) -> str:
    return parameter.split(".", 1)[0]


def _stack(groups: list[Group], names: list[str], scale: dict[str, float]):
    y = np.concatenate([g.residuals for g in groups])
    A = np.vstack([np.column_stack([g.design.get(n, np.zeros(len(g.residuals))) for n in names])
                   if names else np.zeros((len(g.residuals), 0)) for g in groups])
    n = len(y)
    S = np.zeros((n, n))
    at = 0
    for g in groups:
        k = len(g.residuals)
        S[at:at + k, at:at + k] = g.covariance * scale[g.name] + g.inherited
        at += k
    return y, A, S


def gls(y, A, S):
    """beta, its covariance and the whitened residual per row, by Cholesky whitening (S is positive definite)."""
    L = np.linalg.cholesky(S)
    Aw = np.linalg.solve(L, A)
    yw = np.linalg.solve(L, y)
    if A.shape[1] == 0:
        return np.zeros(0), np.zeros((0, 0)), yw
    Q, R = np.linalg.qr(Aw)
    beta = np.linalg.solve(R, Q.T @ yw)
    Rinv = np.linalg.inv(R)
    return beta, Rinv @ Rinv.T, yw - Aw @ beta


def fit_drift(groups: list[Group], names: list[str], blocks: dict[str, list[str]] | None = None) -> DriftFit:
    """The drift parameters `names` ("target.parameter") from every group at once, and the tests: one per block
    of parameters (default: one per target), its home group the one of the target of its first parameter."""
    groups = [g for g in groups if len(g.residuals)]
    home_params = {g.name: sum(target_of(n) in g.home for n in names) for g in groups}
    scale = {g.name: 1.0 for g in groups}
    for _ in range(2):  # the fit with the pooled scales, then the scales from its residuals: twice settles
        y, A, S = _stack(groups, names, scale)
        beta, cov, white = gls(y, A, S)
        rss, own_dof = _group_rss(groups, white, scale, home_params)
        scale = {g.name: (g.dof + rss[g.name]) / (g.dof + own_dof[g.name]) for g in groups}
    y, A, S = _stack(groups, names, scale)
    beta, cov, white = gls(y, A, S)
    pooled = {g.name: g.dof + own_dof[g.name] for g in groups}
    inherited = _inherited_share(groups, A, S, cov)

    if blocks is None:
        blocks = {}
        for n in names:
            blocks.setdefault(target_of(n), []).append(n)
    tests = {}
    for name, members in blocks.items():
        idx = [names.index(n) for n in members]
        block = beta[idx]
        chi2 = float(block @ np.linalg.solve(cov[np.ix_(idx, idx)], block))
        home = next((g for g in groups if target_of(members[0]) in g.home), groups[0])
        d = (len(idx), _effective_dof(inherited[idx], pooled[home.name], home.dof))
        tests[name] = TargetTest(chi2 / len(idx), d, float(fdtrc(*d, chi2 / len(idx))))
    misfit = {}
    for g in groups:
        if own_dof[g.name] > 0:
            f = rss[g.name] / own_dof[g.name]  # at the calibration's scale (rss was computed before rescaling)
            d = (own_dof[g.name], g.dof)
            misfit[g.name] = TargetTest(f, d, float(fdtrc(*d, f)))
    return DriftFit(list(names), beta, cov, tests, misfit, scale)


def _inherited_share(groups, A, S, cov) -> np.ndarray:
    """Per parameter, the share of its variance that comes from the groups' inherited covariance."""
    n = len(S)
    inherited = np.zeros((n, n))
    at = 0
    for g in groups:
        k = len(g.residuals)
        inherited[at:at + k, at:at + k] = g.inherited
        at += k
    if not inherited.any() or A.shape[1] == 0:
        return np.zeros(A.shape[1])
    K = cov @ A.T @ np.linalg.inv(S)  # the GLS estimator: beta = K y
    return np.clip(np.einsum("ij,jk,ik->i", K, inherited, K) / np.diag(cov), 0.0, 1.0)


def _effective_dof(share: np.ndarray, noise_dof: float, inherited_dof: float) -> float:
    """Welch-Satterthwaite: a variance made of an inherited part, known from the calibration's `inherited_dof`,
    and a part the pooled scale knows from `noise_dof`, is known from about this many degrees of freedom."""
    f = float(np.mean(share)) if len(share) else 0.0
    if f <= 0.0:
        return noise_dof
    return 1.0 / (f ** 2 / max(inherited_dof, 1) + (1 - f) ** 2 / max(noise_dof, 1))


def refit(groups: list[Group], names: list[str], scale: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """The estimate and covariance of a reduced set of parameters (a touch-up's), at given group scales."""
    beta, cov, _ = gls(*_stack([g for g in groups if len(g.residuals)], names, scale))
    return beta, cov


def _group_rss(groups, white, scale, home_params):
    """Each group's whitened residual sum of squares at the calibration's scale, and its own degrees of freedom."""
    rss, dof, at = {}, {}, 0
    for g in groups:
        k = len(g.residuals)
        rss[g.name] = float(np.sum(white[at:at + k] ** 2) * scale[g.name])
        dof[g.name] = max(k - home_params[g.name], 0)
        at += k
    return rss, dof


def leave_one_out(groups: list[Group], names: list[str], group: str, rows_per_point: int = 2) -> np.ndarray:
    """For each point of `group` (`rows_per_point` rows), the residual left when the drift estimated from every
    other point is applied: how a corrected calibration reads a point its correction never saw."""
    target = next(g for g in groups if g.name == group)
    scale = {g.name: 1.0 for g in groups}
    errors = []
    for start in range(0, len(target.residuals), rows_per_point):
        keep = np.ones(len(target.residuals), dtype=bool)
        keep[start:start + rows_per_point] = False
        reduced = [g if g is not target else Group(g.name, g.residuals[keep], g.covariance[np.ix_(keep, keep)],
                                                   {n: c[keep] for n, c in g.design.items()}, g.dof, g.home,
                                                   g.inherited[np.ix_(keep, keep)])
                   for g in groups]
        y, A, S = _stack(reduced, names, scale)
        beta = gls(y, A, S)[0]
        rows = slice(start, start + rows_per_point)
        predicted = np.column_stack([target.design.get(n, np.zeros(len(target.residuals)))[rows] for n in names]) \
            if names else np.zeros((rows_per_point, 0))
        errors.append(target.residuals[rows] - predicted @ beta)
    return np.array(errors)
