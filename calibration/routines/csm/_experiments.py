"""csm-positioning's experiments and report tables (seed 002): leave-one-out over the survey poses, the
weighting schemes over k, the closed loops' terminal errors, each beside the seed's own figures.

Pure functions of the sample set; `params` is csm-positioning's and `kin` its nominal kinematics.
"""

from __future__ import annotations

import math

import numpy as np

from calibration.models import csm
from calibration.models.irb120 import Kinematics
from calibration.routines.csm._samples import BLACKS, SampleSet, locate

VW_SCHEMES = ("w1", "w2", "w3", "w4")

# the seed's numbers, shown beside ours
SEED_TABLE_III = {"cam1": (0.065, 0.069, 0.106), "cam2": (0.081, 0.093, 0.137),
                  "white": (0.07, 0.29, 0.15, 0.33), "virtual": (0.12, 0.34, 0.13, 0.36)}
SEED_TABLE_II_MEAN, SEED_TABLE_IV_MEAN = 0.2989, 0.3541
SEED_TABLE_V = {"equal": 0.4691, "w1": 0.2303, "w2": 0.2572, "w3": 0.2206, "w4": 0.2203}
SEED_TABLE_VI = {"equal": 12, "w1": 7, "w2": 8, "w3": 5, "w4": 4}


def loo_errors(data: SampleSet, params, kin: Kinematics, mode: str, scheme: str = "equal", k: float = 1.0,
               target_feature: str = "white") -> np.ndarray:
    """Leave-one-out over the survey poses: the others' samples estimate C, the left-out pose's
    `target_feature` (the virtual point for mode virtual) is located by eq. 10; error in nominal 3D (mm)."""
    survey = data.survey()
    errors = []
    for pose in survey:
        others = [p for p in survey if p is not pose]
        if mode == "virtual":
            tuv = [np.mean([pose.uv[c][n] for n in BLACKS], axis=0) for c in params.cameras]
            truth = kin.points(pose.joints, BLACKS).mean(axis=0)
        else:
            tuv = [pose.uv[c][target_feature] for c in params.cameras]
            truth = kin.point(pose.joints, target_feature)
        est = locate(data, others, tuv, mode, scheme, k, params, kin)
        errors.append(np.linalg.norm(est.target - truth) * 1e3)
    return np.array(errors)


def k_sweep(data: SampleSet, params, kin: Kinematics) -> dict[str, dict[float, float]]:
    """Table V / Figs. 12-15: mean LOO error (white circle) per weighting scheme and k."""
    out = {"equal": {1.0: float(loo_errors(data, params, kin, "white").mean())}}
    for scheme in VW_SCHEMES:
        out[scheme] = {float(k): float(loo_errors(data, params, kin, "white", scheme, k).mean())
                       for k in params.k_values}
    return out


def best_k(sweep: dict[str, dict[float, float]]) -> dict[str, float]:
    """The k of smallest mean LOO error per VW scheme (Table V); among errors equal to rounding (for w1, k only
    scales the weights: every k gives the same estimate), the smallest k, whatever the last bits say."""
    best = {}
    for s in VW_SCHEMES:
        least = min(sweep[s].values())
        best[s] = min(k for k, err in sweep[s].items() if err <= least * (1 + 1e-9))
    return best


LEGEND = ("A loop is mode:scheme. Mode: white, the white circle alone is the feature; three, the three black "
          "circles are three features; virtual, their mean in each image is one feature (the seed's virtual point). "
          "Scheme: the weight ω of each sample in the view-parameter fit (eq. 16), from dis, the sample's estimated "
          "distance to the target (mm): equal, ω = 1; reciprocal, ω = 1/dis (conventional CSM); w1, ω = k/dis "
          "(eq. 12); w2, ω = k + 1/dis (13); w3, ω = 1/dis^k (14); w4, ω = k/dis^k (15). k: the parameter of "
          "w1-w4 (the seed tries 1-4): in w3 and w4 a larger k favours the samples near the target more, in w2 "
          "it evens the weights out, in w1 it only scales them; here the value of k_values with the smallest "
          "mean leave-one-out error of Table V. Errors: the nominal kinematics of the final "
          "joints against the target's (the seed's measure); iterations: moves after the pre-planned approach; "
          "converged: targets whose predicted correction fell below tolerance_mm.")


def seed_tables(data: SampleSet, samples: list[dict], params, kin: Kinematics, view_fit: csm.Estimate,
                sweep: dict | None) -> tuple[dict, list, list]:
    """Stats, tables and charts of seed 002's Tables II-VI and Figs. 10-15: `view_fit` is the camera-space
    fit of all survey samples (white circle, equal weights); `sweep` the k sweep (None: fewer than 5 survey
    poses). The tables: the run's positioning result (its loops) first, then the seed's in its order."""
    survey = data.survey()
    charts, stats = [], {}
    result_table = table_ii = table_iv = table_v = table_vi = None

    # Table III, rows 2-3: the camera-space fit
    fit_rows, camera_fit = [], {}
    for c, res in zip(params.cameras, view_fit.residual_px):
        ax, ay = np.abs(res).mean(axis=0)
        e = float(np.linalg.norm(res, axis=1).mean())
        camera_fit[c] = {"x_px": float(ax), "y_px": float(ay), "mean_px": e, "rms_px": float(np.sqrt((res ** 2).sum(1).mean()))}
        fit_rows += _with_seed_row([f"camera-space fit, {c} (px)", "cellctl", *_r4(ax, ay), None, _r4(e)[0]],
                                   SEED_TABLE_III.get(c))
    stats["camera_fit"] = camera_fit

    # Table II: LOO with one virtual feature; Table IV: the three black circles separately, white predicted
    blacks = all(all(n in p.uv.get(c, {}) for n in BLACKS for c in params.cameras) for p in survey)
    if blacks and len(survey) >= 5:
        loo_virtual = loo_errors(data, params, kin, "virtual")
        loo_three = loo_errors(data, params, kin, "three")
        stats["loo_3d"] = _err_stats(loo_virtual)
        stats["loo_3d_three"] = _err_stats(loo_three)
        table_ii = _per_point_table("Table II: leave-one-out 3D error, one virtual feature (mm)", loo_virtual,
                                    SEED_TABLE_II_MEAN)
        table_iv = _per_point_table("Table IV: leave-one-out 3D error, three features separately, white circle "
                                    "predicted (mm)", loo_three, SEED_TABLE_IV_MEAN)

    # Table V, Figs. 12-15: weighting schemes over k
    if sweep is not None:
        best = best_k(sweep)
        table_v = {"title": "Table V: smallest mean positioning error per weighting scheme (mm), leave-one-out "
                            "over the survey poses, white circle",
                   "columns": ["scheme", "best k", "cellctl", "seed 002"],
                   "rows": [["equal", "-", sweep["equal"][1.0], SEED_TABLE_V["equal"]]]
                   + [[s, best[s], sweep[s][best[s]], SEED_TABLE_V[s]] for s in VW_SCHEMES]}
        for i, s in enumerate(VW_SCHEMES):
            charts.append({"name": f"fig{12 + i}_{s}_k", "title": f"Fig. {12 + i}: mean error with varying {s}",
                           "x_label": "k", "y_label": "mean error (mm)",
                           "series": {s: [[k, v] for k, v in sorted(sweep[s].items())],
                                      "equal": [[k, sweep["equal"][1.0]] for k in sorted(sweep[s])]}})
        stats["weights"] = {"best_k": best, "mean_mm": {s: sweep[s][best[s]] if s in best else sweep[s][1.0]
                                                        for s in ("equal", *VW_SCHEMES)}}

    # the closed loops: terminal error, iterations, error against iteration
    loops = loop_results(data, params, kin, samples)
    if loops:
        stats["loops"] = {name: {"n": r["n"], "mean_mm": r["mean_mm"], "max_mm": r["max_mm"],
                                 "iterations_mean": r["iterations_mean"], "converged": r["converged"], "k": r["k"]}
                          for name, r in loops.items()}
        if params.primary in loops:
            p = loops[params.primary]
            stats["positioning"] = {"n": p["n"], "mean_mm": p["mean_mm"], "max_mm": p["max_mm"], "loop": params.primary,
                                    "note": "nominal kinematics of the final joints against the target's joints"}
        stats["iterations"] = {("equal" if s == "equal" else s): loops[f"three:{s}"]["iterations_mean"]
                               for s in ("equal", *VW_SCHEMES) if f"three:{s}" in loops}
        for mode, seed_key, label in (("white", "white", "first: white circle"), ("virtual", "virtual", "second: virtual point")):
            name = next((n for n in loops if n.startswith(mode + ":")), None)
            if name:
                r = loops[name]
                fit_rows += _with_seed_row([f"{label} positioning ({name}), 3D (mm)", "cellctl",
                                            *_r4(*r["axis_mean_mm"], r["mean_mm"])], SEED_TABLE_III[seed_key])
        three = {s: loops[f"three:{s}"] for s in ("equal", *VW_SCHEMES) if f"three:{s}" in loops}
        table_vi = {"title": "Table VI: iterations per weighting scheme (three black circles)",
                    "columns": ["scheme", "k", "mean iterations", "converged", "terminal mean (mm)", "seed 002"],
                    "rows": [[s, _k_cell(s, r["k"]), r["iterations_mean"], r["converged"], r["mean_mm"],
                              SEED_TABLE_VI[s]] for s, r in three.items()]}
        result_table = {"title": "Positioning result: terminal error per loop (mm, nominal kinematics)",
                        "columns": ["loop", "k", "targets", "mean", "max", "mean iterations", "converged"],
                        "rows": [[f"{n} (primary)" if n == params.primary else n, _k_cell(n.partition(":")[2], r["k"]),
                                  r["n"], r["mean_mm"], r["max_mm"], r["iterations_mean"], r["converged"]]
                                 for n, r in loops.items()]}
        charts.insert(0, {"name": "positioning_per_target", "title": "terminal positioning error per target",
                          "x_label": "target", "y_label": "error (mm, nominal kinematics)", "log_y": True,
                          "series": {n: r["per_target"] for n, r in loops.items()}})
        for fig, mode in ((10, "white"), (11, "virtual")):
            series = {n: r["curve"] for n, r in loops.items() if n.startswith(mode + ":")}
            if series:
                charts.append({"name": f"fig{fig}_{mode}", "title": f"Fig. {fig}: positioning with the {mode} feature",
                               "x_label": "iteration", "y_label": "mean error (mm)", "series": series, "log_y": True})
        charts.append({"name": "iterations_three", "title": "error against iteration, three features, per scheme",
                       "x_label": "iteration", "y_label": "mean error (mm)", "log_y": True,
                       "series": {n: r["curve"] for n, r in loops.items() if n.startswith("three:")}})
    table_iii = {"title": "Table III: error magnitudes", "columns": ["set", "source", "x", "y", "z", "Euclidean"],
                 "rows": fit_rows,
                 "note": "x, y, z: mean absolute error along each axis; Euclidean: mean distance. Camera rows: the "
                         "camera-space fit of every survey sample of the white circle (px); positioning rows: the "
                         "terminal error of the first loop of that mode (mm)."}
    tables = [t for t in (result_table, table_ii, table_iii, table_iv, table_v, table_vi) if t]
    legend_at = next(t for t in (result_table, table_v, table_vi, table_iii) if t)
    legend_at["note"] = f"{legend_at['note']} {LEGEND}" if legend_at.get("note") else LEGEND
    detectors = detector_agreement(samples)
    if detectors:
        stats["detector_agreement"] = detectors
    return stats, tables, charts


def _r4(*values) -> list[float]:
    return [round(float(v), 4) for v in values]


def _with_seed_row(row: list, seed: tuple | None) -> list[list]:
    """A Table III row, and the seed's figures for it below (x, y, Euclidean for a camera; x, y, z, Euclidean)."""
    if seed is None:
        return [row]
    figures = [seed[0], seed[1], None, seed[2]] if len(seed) == 3 else list(seed)
    return [row, ["", "seed 002", *figures]]


def _k_cell(scheme: str, k):
    """The k a loop used, for the schemes that have one (equal and reciprocal do not)."""
    return k if scheme in VW_SCHEMES else "-"


def loop_results(data: SampleSet, params, kin: Kinematics, samples: list[dict]) -> dict:
    """Per loop: terminal error of the white circle (nominal kinematics of the final joints against the
    target's), moves made, how many converged, the k used, the mean error against iteration."""
    out = {}
    iterate = [p for p in data.poses if p.phase == "iterate"]
    loops = [name for name in params.loops if any(p.loop == name for p in iterate)]
    for loop in loops:
        errors, axes, iterations, curves, targets = [], [], [], [], []
        for t, target in sorted(data.by_target.items()):
            goal = kin.point(target.joints, "white")
            approach = [p for p in data.poses if p.target == t and p.phase == "approach"]
            own = sorted((p for p in iterate if p.target == t and p.loop == loop), key=lambda p: p.step)
            if not approach:
                continue
            path = [max(approach, key=lambda p: p.step)] + own
            errs = [np.linalg.norm(kin.point(p.joints, "white") - goal) * 1e3 for p in path]
            final = kin.point(path[-1].joints, "white") - goal
            errors.append(errs[-1])
            targets.append(t)
            axes.append(np.abs(final) * 1e3)
            iterations.append(len(own))
            curves.append(errs + [errs[-1]] * (params.max_iterations + 1 - len(errs)))
        if not errors:
            continue
        rows = [r for r in samples if r.get("phase") == "iterate" and r.get("loop") == loop]
        converged = len({r["target"] for r in rows if r.get("status") == "converged"})
        ks = sorted({float(r["k"]) for r in rows if r.get("k") is not None})
        out[loop] = {"n": len(errors), "mean_mm": float(np.mean(errors)), "max_mm": float(np.max(errors)),
                     "axis_mean_mm": [float(v) for v in np.mean(axes, axis=0)],
                     "iterations_mean": float(np.mean(iterations)),
                     "converged": converged, "k": ks[0] if len(ks) == 1 else ks,
                     "curve": [[i, float(v)] for i, v in enumerate(np.mean(curves, axis=0))],
                     "per_target": [[t, float(e)] for t, e in zip(targets, errors)]}
    return out


def detector_agreement(samples: list[dict]) -> dict | None:
    d = np.array([[r["u_px"] - r["u_alt_px"], r["v_px"] - r["v_alt_px"]] for r in samples
                  if r.get("status") == "ok" and r.get("u_alt_px") is not None
                  and not math.isnan(float(r["u_alt_px"]))])
    if not len(d):
        return None
    n = np.linalg.norm(d, axis=1)
    return {"n": len(d), "rms_px": float(np.sqrt((n ** 2).mean())), "max_px": float(n.max())}


def _err_stats(errors_mm) -> dict:
    e = np.asarray(errors_mm, dtype=float)
    return {"n": int(e.size), "mean_mm": float(e.mean()), "max_mm": float(e.max()), "rms_mm": float(np.sqrt((e ** 2).mean()))}


def _per_point_table(title: str, errors, seed_mean: float) -> dict:
    """The error of each left-out point, five to a row as the seed prints them, the mean and the seed's mean."""
    mean = round(float(np.mean(errors)), 4)
    errors = [round(float(e), 4) for e in errors]
    rows = [[f"points {i + 1}-{min(i + 5, len(errors))}" if i + 1 < len(errors) else f"point {i + 1}",
             *errors[i:i + 5], *[""] * (5 - len(errors[i:i + 5]))] for i in range(0, len(errors), 5)]
    rows.append(["mean", mean, "", "", "", ""])
    rows.append(["seed 002 mean", seed_mean, "", "", "", ""])
    return {"title": title, "columns": ["points", "error (mm)", "", "", "", ""], "rows": rows}
