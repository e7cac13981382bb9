"""csm-positioning's experiments and report tables (seed 002): leave-one-out over the survey poses, the
weighting schemes over k, the closed loops' terminal errors, each beside the seed's own figures.

Pure functions of the sample set; `params` is csm-positioning's and `kin` its nominal kinematics.
"""

from __future__ import annotations

import math

import numpy as np

from ..models import csm
from ..models.irb120 import Kinematics
from .csm_samples import BLACKS, SampleSet, locate

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


def seed_tables(data: SampleSet, samples: list[dict], params, kin: Kinematics, view_fit: csm.Estimate,
                sweep: dict | None) -> tuple[dict, list, list]:
    """Stats, tables and charts of seed 002's Tables II-VI and Figs. 10-15: `view_fit` is the camera-space
    fit of all survey samples (white circle, equal weights); `sweep` the k sweep (None: fewer than 5 survey
    poses)."""
    survey = data.survey()
    tables, charts, stats = [], [], {}

    # Table III, rows 2-3: the camera-space fit
    fit_rows, camera_fit = [], {}
    for c, res in zip(params.cameras, view_fit.residual_px):
        ax, ay = np.abs(res).mean(axis=0)
        e = float(np.linalg.norm(res, axis=1).mean())
        camera_fit[c] = {"x_px": float(ax), "y_px": float(ay), "mean_px": e, "rms_px": float(np.sqrt((res ** 2).sum(1).mean()))}
        seed = SEED_TABLE_III.get(c, ("-", "-", "-"))
        fit_rows.append([f"camera-space fit, {c} (px)", ax, ay, "-", e, f"{seed[0]} / {seed[1]} / - / {seed[2]}"])
    stats["camera_fit"] = camera_fit

    # Table II: LOO with one virtual feature; Table IV: the three black circles separately, white predicted
    blacks = all(all(n in p.uv.get(c, {}) for n in BLACKS for c in params.cameras) for p in survey)
    if blacks and len(survey) >= 5:
        loo_virtual = loo_errors(data, params, kin, "virtual")
        loo_three = loo_errors(data, params, kin, "three")
        stats["loo_3d"] = _err_stats(loo_virtual)
        stats["loo_3d_three"] = _err_stats(loo_three)
        tables.append(_per_point_table("Table II: leave-one-out 3D error, one virtual feature (mm)", loo_virtual,
                                       SEED_TABLE_II_MEAN))
        tables.append(_per_point_table("Table IV: leave-one-out 3D error, three features separately, white circle "
                                       "predicted (mm)", loo_three, SEED_TABLE_IV_MEAN))

    # Table V, Figs. 12-15: weighting schemes over k
    if sweep is not None:
        best = best_k(sweep)
        tables.append({"title": "Table V: smallest mean positioning error per weighting scheme (mm), leave-one-out "
                                "over the survey poses, white circle",
                       "columns": ["scheme", "best k", "cellctl", "seed 002"],
                       "rows": [["equal", "-", sweep["equal"][1.0], SEED_TABLE_V["equal"]]]
                       + [[s, best[s], sweep[s][best[s]], SEED_TABLE_V[s]] for s in VW_SCHEMES]})
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
                s = SEED_TABLE_III[seed_key]
                fit_rows.append([f"{label} positioning ({name}), 3D (mm)", *r["axis_mean_mm"], r["mean_mm"],
                                 " / ".join(map(str, s))])
        tables.append({"title": "Table VI: iterations per weighting scheme (three black circles)",
                       "columns": ["scheme", "k", "mean iterations", "converged", "terminal mean (mm)", "seed 002"],
                       "rows": [[s, loops[f"three:{s}"]["k"], loops[f"three:{s}"]["iterations_mean"],
                                 loops[f"three:{s}"]["converged"], loops[f"three:{s}"]["mean_mm"], SEED_TABLE_VI[s]]
                                for s in ("equal", *VW_SCHEMES) if f"three:{s}" in loops]})
        tables.append({"title": "Terminal positioning error per loop (mm, nominal kinematics)",
                       "columns": ["loop", "k", "n", "mean", "max", "mean iterations", "converged"],
                       "rows": [[n, r["k"], r["n"], r["mean_mm"], r["max_mm"], r["iterations_mean"], r["converged"]]
                                for n, r in loops.items()]})
        for fig, mode in ((10, "white"), (11, "virtual")):
            series = {n: r["curve"] for n, r in loops.items() if n.startswith(mode + ":")}
            if series:
                charts.append({"name": f"fig{fig}_{mode}", "title": f"Fig. {fig}: positioning with the {mode} feature",
                               "x_label": "iteration", "y_label": "mean error (mm)", "series": series, "log_y": True})
        charts.append({"name": "iterations_three", "title": "error against iteration, three features, per scheme",
                       "x_label": "iteration", "y_label": "mean error (mm)", "log_y": True,
                       "series": {n: r["curve"] for n, r in loops.items() if n.startswith("three:")}})
    tables.insert(0, {"title": "Table III: error magnitudes", "columns": ["set", "x", "y", "z", "Euclidean",
                                                                         "seed 002 (x / y / z / Euclidean)"],
                      "rows": fit_rows})
    detectors = detector_agreement(samples)
    if detectors:
        stats["detector_agreement"] = detectors
    return stats, tables, charts


def loop_results(data: SampleSet, params, kin: Kinematics, samples: list[dict]) -> dict:
    """Per loop: terminal error of the white circle (nominal kinematics of the final joints against the
    target's), moves made, how many converged, the k used, the mean error against iteration."""
    out = {}
    iterate = [p for p in data.poses if p.phase == "iterate"]
    loops = [l for l in params.loops if any(p.loop == l for p in iterate)]
    for loop in loops:
        errors, axes, iterations, curves = [], [], [], []
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
                     "curve": [[i, float(v)] for i, v in enumerate(np.mean(curves, axis=0))]}
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
    rows = [[f"point {i + 1}", float(e)] for i, e in enumerate(errors)]
    rows.append(["mean", float(np.mean(errors))])
    return {"title": title, "columns": ["point", "error (mm)"], "rows": rows,
            "note": f"seed 002: mean {seed_mean} mm over 21 points"}
