"""Accuracy-targeted plans (issue 31): collect until the predicted verification accuracy meets the target.

A targeted routine's plan is a budget of calibration steps in an information-first order, then its
verification steps. After each calibration step it predicts, from the samples so far and nothing else, the
RMS radial error its verification will measure, as two shares that add in quadrature:

- the floor: what no calibration removes (the arm's repeatability and the measurement's noise), the fit's
  residual sigma per axis, taken at its upper confidence bound (chi-square on the fit's degrees of freedom);
- the model: what the calibration's own uncertainty adds at the verification places, from the fit's
  covariance (scaled by the same bound).

The target (`target_um`) is met when floor and model together, both at their upper bound, are within it.
Without one (the default) the target is today's figure: what the whole budget (today's fixed plan) is
predicted to reach, the model's share shrinking as 1/sqrt(samples), plus `EXCESS` (a routine may ask less). A target below the floor cannot be met: the routine
runs its whole budget and its report says what it reached.

Everything here is a pure function of the samples: a resumed run (cellctl/core/orchestrator.py) replays the
same decisions from its stored samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np
from scipy.stats import chi2

from calibration.routines.base import Chart, Table

CONFIDENCE = 0.95  # of the upper bounds the decision takes
EXCESS = 0.05  # default target: today's predicted figure raised at most this much
MIN_DOF = 6  # fewer residual degrees of freedom: the floor is not known well enough to decide


@dataclass(frozen=True)
class Prediction:
    """The predicted verification figure after `n` calibration samples (µm, RMS radial, upper bounds)."""

    n: int
    floor_um: float
    model_um: float
    # the floor as the whole budget would know it (its residual's degrees of freedom, a tighter upper bound), when
    # the routine says what they are (`prediction(budget_dof=...)`); else today's figure keeps this floor's bound
    budget_floor_um: float | None = None

    @property
    def predicted_um(self) -> float:
        return math.hypot(self.floor_um, self.model_um)

    def today_um(self, budget: int) -> float:
        """What the whole budget of `budget` samples is predicted to reach: the floor as now (at the whole budget's
        bound when known), the calibration's share shrinking as 1/sqrt(samples) (the same design, repeated)."""
        floor = self.floor_um if self.budget_floor_um is None or budget <= self.n else self.budget_floor_um
        return math.hypot(floor, self.model_um * math.sqrt(self.n / max(budget, self.n)))

    def goal_um(self, target_um: float | None, budget: int, excess: float = EXCESS) -> float:
        """The figure to reach: the target, or without one today's figure (the whole budget's) + `excess`."""
        return target_um if target_um is not None else (1.0 + excess) * self.today_um(budget)

    def meets(self, target_um: float | None, budget: int, excess: float = EXCESS) -> bool:
        return self.predicted_um <= self.goal_um(target_um, budget, excess)


def upper_factor(dof: int, confidence: float = CONFIDENCE) -> float:
    """sigma_upper / sigma_hat: the one-sided upper confidence bound of a standard deviation from `dof`."""
    return math.sqrt(dof / chi2.ppf(1.0 - confidence, dof))


def prediction(n: int, sigma_axis: float, dof: int, model_var_radial: float,
               budget_dof: int | None = None) -> Prediction | None:
    """From a fit: `sigma_axis` the residual sigma per axis (m), `model_var_radial` the calibration's own
    mean squared radial error at the verification places (m^2, from its covariance, already scaled by the
    fit's sigma). None while `dof` is too small to decide. `budget_dof`: the residual's degrees of freedom the
    whole budget would have; a small budget's figure is then projected with the floor's bound at those (with
    few degrees of freedom the bound shrinks much as samples come, and today's figure would keep it too wide)."""
    if dof < MIN_DOF or not (math.isfinite(sigma_axis) and math.isfinite(model_var_radial)):
        return None
    k = upper_factor(dof)
    budget_floor = (math.sqrt(2.0) * sigma_axis * upper_factor(budget_dof) * 1e6
                    if budget_dof is not None and budget_dof > dof else None)
    return Prediction(n, math.sqrt(2.0) * sigma_axis * k * 1e6, math.sqrt(max(model_var_radial, 0.0)) * k * 1e6,
                      budget_floor)


def cal_prefixes(rows: Iterable[dict]) -> list[list[dict]]:
    """The calibration rows grouped by step, in step order (the order they were collected in)."""
    by_step: dict[int, list[dict]] = {}
    for r in rows:
        by_step.setdefault(int(r.get("step", len(by_step))), []).append(r)
    return [by_step[k] for k in sorted(by_step)]


def curve(cal_rows: Sequence[dict], predict: Callable[[list[dict]], Prediction | None],
          points: int = 60) -> list[Prediction]:
    """The prediction after each calibration step (at most `points` of them, always the last)."""
    steps = cal_prefixes(cal_rows)
    if not steps:
        return []
    stride = max(1, len(steps) // points)
    picks = sorted(set(range(stride - 1, len(steps), stride)) | {len(steps) - 1})
    out = []
    for k in picks:
        p = predict([r for group in steps[: k + 1] for r in group])
        if p is not None:
            out.append(p)
    return out


def stopping_report(name: str, points: list[Prediction], target_um: float | None, budget: int,
                    excess: float = EXCESS) -> tuple[dict, Table, Chart]:
    """Where the collection stopped and why: (stats entry, report table, chart of prediction vs samples)."""
    last = points[-1] if points else None
    met = last is not None and last.meets(target_um, budget, excess)
    goal = last.goal_um(target_um, budget, excess) if last else target_um
    target_text = (f"{target_um:g} µm" if target_um is not None
                   else f"today's figure + {excess:.0%}: {goal:.2f} µm" if goal else "today's figure")
    if last is None:
        reason = "too few samples to predict the verification accuracy"
    elif met:
        reason = (f"target met after {last.n} calibration samples: predicted {last.predicted_um:.2f} µm RMS "
                  f"(floor {last.floor_um:.2f}, calibration {last.model_um:.2f}, {CONFIDENCE:.0%} upper bounds), "
                  f"target {target_text}")
    else:
        reason = (f"target NOT met: the budget of {budget} calibration samples is spent; it reached "
                  f"{last.predicted_um:.2f} µm RMS (floor {last.floor_um:.2f}, calibration {last.model_um:.2f}), "
                  f"target {target_text}")
    stats = {"met": met, "target_um": target_um, "goal_um": goal, "samples": last.n if last else 0,
             "budget": budget, "reason": reason,
             **({"predicted_um": last.predicted_um, "floor_um": last.floor_um, "model_um": last.model_um}
                if last else {})}
    table = Table(title="Accuracy target: where collection stopped",
                  columns=["calibration samples", "predicted (µm RMS)", "floor", "calibration share"],
                  rows=[[p.n, round(p.predicted_um, 3), round(p.floor_um, 3), round(p.model_um, 3)]
                        for p in points[-min(len(points), 8):]], note=reason)
    series = {"predicted (upper bound)": [[p.n, p.predicted_um] for p in points],
              "floor (repeatability, noise)": [[p.n, p.floor_um] for p in points]}
    if points:
        series["target" if target_um is not None else f"today's figure + {excess:.0%}"] = [
            [p.n, p.goal_um(target_um, budget, excess)] for p in points]
    chart = Chart(name=f"{name}_predicted_accuracy", title="Predicted verification accuracy against samples",
                  x_label="calibration samples", y_label="predicted RMS radial error (µm)", series=series)
    return stats, table, chart


def greedy_circle_order(angles: Sequence[float]) -> list[float]:
    """The angles (rad) in a space-filling order: each next one the farthest (on the circle) from those taken;
    starts at the first, ties go to the earlier."""
    left = list(angles)
    if not left:
        return []
    order = [left.pop(0)]
    while left:
        gap = [min(abs(math.remainder(a - b, 2 * math.pi)) for b in order) for a in left]
        order.append(left.pop(int(np.argmax(gap))))
    return order


def nearest_neighbour_order(points: np.ndarray, start: np.ndarray, cost: Callable[[np.ndarray, np.ndarray], np.ndarray]
                            ) -> list[int]:
    """Indices of `points` in the order a nearest-neighbour tour from `start` visits them (`cost(a, many)`:
    the cost of going from a to each of many)."""
    left = list(range(len(points)))
    order, here = [], np.asarray(start, dtype=float)
    while left:
        k = left[int(np.argmin(cost(here, points[left])))]
        order.append(k)
        left.remove(k)
        here = points[k]
    return order


def farthest_point_order(points: np.ndarray, start: Sequence[int] = (0,)) -> list[int]:
    """Indices of `points` (n, d) in a space-filling order: `start` as given, then each next one the farthest from
    those taken (maximin); ties go to the earlier. A plan's first few points then already span its whole region."""
    pts = np.asarray(points, dtype=float).reshape(len(points), -1)
    if not len(pts):
        return []
    order = list(start) or [0]
    gap = np.min([np.linalg.norm(pts - pts[k], axis=1) for k in order], axis=0)
    gap[order] = -1.0
    while len(order) < len(pts):
        k = int(np.argmax(gap))  # the first of equal gaps
        order.append(k)
        gap = np.minimum(gap, np.linalg.norm(pts - pts[k], axis=1))
        gap[order] = -1.0
    return order
