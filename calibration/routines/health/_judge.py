"""The check's verdict from its samples and the calibrations it checked (see check.py for the measurements).

Residuals are in µm, positions in the commanded frame at alpha_cal (where every calibration maps), each
reading two rows (x, y). A camera's drift T(p) = c + (1 + s) R(theta) (p - c) + t about its area's centre c
changes a reading at p by t + theta J (p - c) + s (p - c). The nozzle's offset change d moves the nozzle by
R(a) d from where the compensation expects it when the tool is turned by a from alpha_cal (at alpha_cal too:
there it looks like a camera shift, the turns tell them apart). Camera 1's shift moves the spheres it centres
for camera 2 by -t. The on-board camera's mount shift turns with the arm: R(alpha - alpha1) t.
"""

from __future__ import annotations

import math

import numpy as np

from calibration.errors import CalibrationInputError
from calibration.models.drift import DriftFit, Group, fit_drift, leave_one_out, refit
from calibration.models.planar import MapUncertainty, PlanarMap
from calibration.models.tool_offset import rot
from calibration.routines.base import FitOutcome, NewVersion
from calibration.stats import error_stats

AREA1, AREA2, BOARD, BOARD_LAY = "area1", "area2", "board", "board-lay"
CAMERA_PARAMETERS = ("dx_um", "dy_um", "rotation_urad", "scale_ppm")
SHIFT_PARAMETERS = NOZZLE_PARAMETERS = ("dx_um", "dy_um")
# what to run when a target's drift does not fit its model, by what reads it
RECALIBRATE = {AREA1: "virtual-grid", "nozzle": "rotation-sweep", AREA2: "virtual-grid-area2",
               BOARD: "onboard-camera"}
PARAMETERS = {"camera": CAMERA_PARAMETERS, "nozzle": NOZZLE_PARAMETERS, "mount": SHIFT_PARAMETERS}
J = np.array([[0.0, -1.0], [1.0, 0.0]])


def judge(samples: list[dict], params, calibrations: dict[str, dict]) -> FitOutcome:
    ok = [r for r in samples if r.get("status") == "ok"]
    area1 = [r for r in ok if r["set"] == AREA1]
    area2 = [r for r in ok if r["set"] == AREA2]
    board = [r for r in ok if r["set"] == BOARD]
    cam1 = _camera(samples, AREA1)
    cam2 = _camera(samples, AREA2)
    cam3 = _camera(samples, BOARD)
    turned = any(abs(float(r["turn_deg"])) > 1e-9 for r in area1)
    tool = params.tool
    asked = None if params.targets is None else [t.strip() for t in params.targets.split(",") if t.strip()]
    home = {}
    if area1:
        home[cam1] = AREA1
        if turned:
            home[tool] = AREA1
    if area2:
        home[cam2] = AREA2
    if board:
        home[cam3] = BOARD
    targets = [t for t in home if asked is None or t in asked]
    if not targets:
        raise CalibrationInputError("calibration-check: no target was read (every reading failed, or nothing was asked)")

    # the on-board camera looks at the same spheres from the same place at every turn: its map's rotation and
    # scale change would only move where each sphere seems to lie, which is unknown anyway; its shift turns with
    # the arm and shows
    kinds = {t: ("nozzle" if t == tool else "mount" if home[t] == BOARD else "camera") for t in home}
    names = [f"{t}.{p}" for t in home for p in PARAMETERS[kinds[t]]]
    centres = {**({cam1: _centre(area1)} if area1 else {}), **({cam2: _centre(area2)} if area2 else {})}
    groups = []
    if area1:
        groups.append(_area1_group(area1, calibrations, cam1, tool if turned else None))
    if area2:
        groups.append(_area2_group(area2, calibrations, cam2, cam1 if area1 else None))
    if board:
        group, centres[cam3] = _board_group(board, calibrations, cam3)
        groups.append(group)
        names += [n for n in group.design if n.startswith(SPHERE)]  # where each laid sphere lies: not a drift
    fit = fit_drift(groups, names, _blocks(names, kinds))
    p_values = {t: _target_p(fit, t) for t in targets}

    tests = len(targets) + len(fit.misfit)
    threshold = params.false_alarm / tests
    misfit = {g for g, t in fit.misfit.items() if t.p_value < threshold}
    drifted = [t for t in targets if p_values[t] < threshold or home[t] in misfit]
    actions, versions, touch_up = {}, {}, {}
    fitting = [t for t in drifted if home[t] not in misfit]
    if fitting:
        kept = _touch_up_parameters(fit, fitting, kinds, threshold)
        for target in fitting:
            errors = leave_one_out(groups, kept, home[target])
            touch_up[target] = error_stats(np.linalg.norm(errors, axis=1) * 1e-6)
            touch_up[target]["parameters"] = [n.split(".", 1)[1] for n in kept if n.startswith(f"{target}.")]
            if params.update:
                versions[target] = _new_version(target, kinds[target], calibrations[target], fit, kept, groups,
                                                touch_up[target], centres.get(target))
    for t in targets:
        if t not in drifted:
            actions[t] = "ok"
        elif home[t] in misfit or t not in fitting:
            actions[t] = f"recalibrate: the drift does not fit its model; run {_routine_for(t, kinds, home)}"
        else:
            actions[t] = "touched up" if t in versions else "touch-up: run calibration-check with update=true"

    drift = {t: _drift_figures(fit, t, kinds[t]) for t in targets}
    test = {t: {"p_value": p_values[t], "drifted": t in drifted,
                **{part: {"p_value": fit.tests[b].p_value, "F": fit.tests[b].statistic, "dof": list(fit.tests[b].dof)}
                   for b, part in _parts(t, kinds[t])}} for t in targets}
    test.update(p_value=p_values, alpha=params.false_alarm, threshold=threshold, tests=tests)
    stats = {"drift": drift, "test": test,
             "fit": {g: {"p_value": m.p_value, "F": m.statistic, "dof": list(m.dof), "scale": fit.scale[g]}
                     for g, m in fit.misfit.items()},
             "readings": {g.name: error_stats(np.linalg.norm(g.residuals.reshape(-1, 2), axis=1) * 1e-6)
                          for g in groups},
             "touch_up": touch_up}
    summary = {"verdict": "drift" if drifted else "ok", "drifted": drifted, "actions": actions,
               "checked": {t: calibrations[t].get("calibration_id") for t in targets}, "updated": {}}
    rejected = [{"step": r.get("step"), "reason": r.get("message") or r.get("status")}
                for r in samples if r.get("status") != "ok"]
    model = {"kind": "check", "targets": targets, "parameters": names}
    return FitOutcome(model, stats, rejected, tables=_tables(targets, drift, test, actions, touch_up,
                                                             summary["checked"]),
                      summary=summary, calibrations=versions)


def _camera(samples, which: str) -> str | None:
    names = {r.get("camera") for r in samples if r.get("set") == which} - {None, ""}
    if len(names) > 1:
        raise CalibrationInputError(f"calibration-check: {which} readings from several cameras ({', '.join(sorted(names))})")
    return names.pop() if names else None


def _readings(rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(targets mm (N, 2), residuals µm (2N,), pixels (N, 2))."""
    target = np.array([[r["target_x_mm"], r["target_y_mm"]] for r in rows], dtype=float)
    measured = np.array([[r["meas_x_mm"], r["meas_y_mm"]] for r in rows], dtype=float)
    uv = np.array([[r["u_px"], r["v_px"]] for r in rows], dtype=float)
    return target, ((measured - target) * 1e3).ravel(), uv


def _centre(rows) -> np.ndarray:
    return np.array([float(rows[0]["centre_x_mm"]), float(rows[0]["centre_y_mm"])])


def _uncertainty(model: dict, target: str) -> MapUncertainty:
    if "uncertainty" not in model:
        raise CalibrationInputError(f"calibration-check: the calibration of {target} keeps no map uncertainty; recalibrate it")
    return MapUncertainty.from_dict(model["uncertainty"])


def _camera_noise(model: dict, target: str, uv: np.ndarray) -> tuple[np.ndarray, int]:
    """A camera's readings' covariance under "nothing drifted" (µm²) and the dof of its sigma: one reading's
    residual sigma, the map's covariance at the pixels, and a touch-up's own uncertainty if it was touched up."""
    u = _uncertainty(model, target)
    n = len(uv)
    cov = (u.sigma * 1e6) ** 2 * np.eye(2 * n) + u.point_covariance(uv) * 1e12
    return cov, u.dof


def _camera_columns(target: str, points_mm: np.ndarray, centre_mm: np.ndarray) -> dict:
    """The reading change per unit of each drift parameter of a camera, at these points."""
    n = len(points_mm)
    rel = points_mm - centre_mm  # mm: µrad x mm = 1e-3 µm
    per_point = {"dx_um": np.tile([1.0, 0.0], (n, 1)), "dy_um": np.tile([0.0, 1.0], (n, 1)),
                 "rotation_urad": rel @ J.T * 1e-3, "scale_ppm": rel * 1e-3}
    return {f"{target}.{name}": column.ravel() for name, column in per_point.items()}


def _correction_covariance(model: dict, target: str, points_mm: np.ndarray) -> np.ndarray:
    """What a touch-up's own estimate adds to the readings' covariance (zero for a calibration never touched up)."""
    correction = model.get("drift_correction")
    if not correction:
        return np.zeros((2 * len(points_mm),) * 2)
    cols = _camera_columns(target, points_mm, np.array(correction["centre_mm"]))
    A = np.column_stack([cols[f"{target}.{p}"] for p in CAMERA_PARAMETERS])
    return A @ np.array(correction["covariance"]) @ A.T


def _area1_group(rows, calibrations, cam1: str, tool: str | None) -> Group:
    target, y, uv = _readings(rows)
    model = calibrations[cam1]
    cov, dof = _camera_noise(model, cam1, uv)
    cov = cov + _correction_covariance(model, cam1, target)
    centre = _centre(rows)
    design = _camera_columns(cam1, target, centre)
    home = (cam1,)
    if tool is not None:
        turns = np.radians([float(r["turn_deg"]) for r in rows])
        # the nozzle, changed by d, sits R(a) d from where the compensation expects it, at alpha_cal too
        B = [rot(a) for a in turns]
        design[f"{tool}.dx_um"] = np.array([b[:, 0] for b in B]).ravel()
        design[f"{tool}.dy_um"] = np.array([b[:, 1] for b in B]).ravel()
        nozzle = calibrations[tool]
        tool_cov = np.diag([nozzle.get("dx_std_um", 0.0) ** 2, nozzle.get("dy_std_um", 0.0) ** 2])
        Bs = np.vstack([b - np.eye(2) for b in B])  # the fitted offset's own error moves the nozzle by (R(a) - I) e
        cov = cov + Bs @ tool_cov @ Bs.T
        home = (cam1, tool)
    return Group(AREA1, y, cov, design, dof, home)


def _area2_group(rows, calibrations, cam2: str, cam1: str | None) -> Group:
    target, y, uv = _readings(rows)
    model = calibrations[cam2]
    cov, dof = _camera_noise(model, cam2, uv)
    cov = cov + _correction_covariance(model, cam2, target)
    design = _camera_columns(cam2, target, _centre(rows))
    if cam1 is not None:  # camera 1 measured each sphere's offset on the nozzle: its shift moves the sphere back
        n = len(rows)
        design[f"{cam1}.dx_um"] = -np.tile([1.0, 0.0], n)
        design[f"{cam1}.dy_um"] = -np.tile([0.0, 1.0], n)
    return Group(AREA2, y, cov, design, dof, (cam2,))


def _parts(target: str, kind: str) -> list[tuple[str, str]]:
    """(test block, its name in the result) of a target: a camera's shift and its rotation-and-scale are tested
    apart, so a shift is not diluted by two poorly determined parameters (12 spheres see a rotation badly)."""
    if kind == "camera":
        return [(f"{target}:shift", "shift"), (f"{target}:rotation-scale", "rotation_scale")]
    return [(target, "shift")]


def _blocks(names: list[str], kinds: dict) -> dict[str, list[str]]:
    blocks = {}
    for t, kind in kinds.items():
        if kind == "camera":
            blocks[f"{t}:shift"] = [f"{t}.dx_um", f"{t}.dy_um"]
            blocks[f"{t}:rotation-scale"] = [f"{t}.rotation_urad", f"{t}.scale_ppm"]
        else:
            blocks[t] = [f"{t}.{p}" for p in PARAMETERS[kind]]
    return blocks


def _target_p(fit: DriftFit, target: str) -> float:
    """A target's p-value over its tests (Bonferroni: the smallest, times their number)."""
    ps = [t.p_value for name, t in fit.tests.items() if name == target or name.startswith(f"{target}:")]
    return min(1.0, len(ps) * min(ps))


SPHERE = "laid-sphere-"


def _board_group(rows, calibrations, cam3: str) -> tuple[Group, np.ndarray]:
    """The on-board camera's readings of the laid spheres: where eq. (5) puts each, against where it was laid.

    Each sphere's true rest position is a free parameter (it rests a few µm off where it was laid), so only the
    way the readings turn with the view tells: a mount shift t turns with the arm (R t), the sphere does not.
    Noise: the arm's repeatability at a view, common to every sphere of that view; each sphere's own; the map's
    covariance turned with the view; D's, through (I - R)."""
    model = calibrations[cam3]
    if "view_sigma_um" not in model:
        raise CalibrationInputError(f"calibration-check: the calibration of {cam3} keeps no uncertainty (made without the joint "
                                    "adjustment, or before the check existed); recalibrate it with onboard-camera")
    target, y, uv = _readings(rows)
    u = _uncertainty(model, cam3)
    alpha1 = math.radians(model["alpha1_deg"])
    R = [rot(math.radians(float(r["turn_deg"])) - alpha1) for r in rows]
    n = len(rows)
    Rb = np.zeros((2 * n, 2 * n))  # block diagonal of the views' rotations
    IR = np.zeros((2 * n, 2))
    for i, Ri in enumerate(R):
        Rb[2 * i:2 * i + 2, 2 * i:2 * i + 2] = Ri
        IR[2 * i:2 * i + 2] = np.eye(2) - Ri
    Jm = Rb @ u.jacobian(uv) * 1e6  # µm per map parameter, turned to the robot frame
    cross = np.array(model["d_map_covariance"])  # map parameters x D (µm)
    # the calibration's own errors (map, D): the sphere positions absorb part of them, so the readings cannot
    # tell their size; they are inherited, not scaled by what this check's residuals say
    inherited = Jm @ u.covariance @ Jm.T + IR @ _d_covariance(model) @ IR.T
    inherited += Jm @ cross @ IR.T + IR @ cross.T @ Jm.T
    views = np.array([r["frame_id"] for r in rows])
    same_view = np.kron((views[:, None] == views[None, :]).astype(float), np.eye(2))
    cov = model["view_sigma_um"] ** 2 * same_view + max(model["sphere_sigma_um"], 0.1) ** 2 * np.eye(2 * n)
    map_ = PlanarMap.from_dict(model["map"])
    seen = map_.pixel_to_plane(uv) * 1e3  # mm, in the camera's frame at pose 1
    centre = map_.pixel_to_plane([(np.array(map_.image_size) - 1) / 2])[0] * 1e3
    local = _camera_columns(cam3, seen, centre)
    design = {f"{cam3}.{p}": Rb @ local[f"{cam3}.{p}"] for p in SHIFT_PARAMETERS}  # the shift turns with the arm
    spheres = sorted({int(r["sphere"]) for r in rows})
    for k in spheres:
        mine = np.array([int(r["sphere"]) == k for r in rows])
        design[f"{SPHERE}{k}.x_um"] = np.kron(mine, [1.0, 0.0])
        design[f"{SPHERE}{k}.y_um"] = np.kron(mine, [0.0, 1.0])
    home = (cam3, *(f"{SPHERE}{k}" for k in spheres))
    return Group(BOARD, y, cov, design, model.get("view_dof", u.dof), home, inherited), centre


def _d_covariance(model: dict) -> np.ndarray:
    """D's covariance (µm²), as the joint adjustment found it with the views' common noise (onboard_camera)."""
    return np.array(model["d_covariance_um2"])


def _touch_up_parameters(fit: DriftFit, targets: list[str], kinds: dict, threshold: float) -> list[str]:
    """What a touch-up corrects: each drifted target's shift (or offset change), and a camera's rotation and
    scale only when they are significant themselves (otherwise their noise would only cost accuracy)."""
    kept = [n for n in fit.names if n.startswith(SPHERE)]  # always estimated with the drift, never a correction
    for t in targets:
        if kinds[t] == "nozzle":
            kept += [f"{t}.{p}" for p in NOZZLE_PARAMETERS]
            continue
        kept += [f"{t}.dx_um", f"{t}.dy_um"]
        if kinds[t] == "camera" and fit.tests[f"{t}:rotation-scale"].p_value < threshold:
            kept += [f"{t}.rotation_urad", f"{t}.scale_ppm"]
    return kept


def _new_version(target: str, kind: str, model: dict, fit: DriftFit, kept: list[str], groups, verification: dict,
                 centre_mm: np.ndarray | None) -> NewVersion:
    """The active calibration corrected by the estimate (from the touch-up's parameters alone)."""
    beta, cov = refit(groups, kept, fit.scale)
    own = {n.split(".", 1)[1]: i for i, n in enumerate(kept) if n.startswith(f"{target}.")}
    stats = {"verification": {k: v for k, v in verification.items() if k != "parameters"},
             "touch_up": {p: float(beta[i]) for p, i in own.items()}}
    new = {k: v for k, v in model.items() if k != "calibration_id"}
    if kind == "nozzle":  # the cameras' maps still expect the nozzle as it was: keep that as the reference
        for p in NOZZLE_PARAMETERS:
            i = own[p]
            new.setdefault(f"reference_{p}", model[p])
            new[p] = model[p] + float(beta[i])
            new[p.replace("_um", "_std_um")] = math.hypot(model.get(p.replace("_um", "_std_um"), 0.0),
                                                           math.sqrt(cov[i, i]))
        new["r_um"] = math.hypot(new["dx_um"], new["dy_um"])
        return NewVersion(new, stats, model.get("calibration_id"))
    full = np.zeros(4)
    full_cov = np.zeros((4, 4))
    pos = [CAMERA_PARAMETERS.index(p) for p in own]
    full[pos] = beta[list(own.values())]
    full_cov[np.ix_(pos, pos)] = cov[np.ix_(list(own.values()), list(own.values()))]
    centre = np.asarray(centre_mm, dtype=float)
    new["map"], new["uncertainty"] = _corrected_map(model, full, centre)
    earlier = model.get("drift_correction") or {}
    new["drift_correction"] = {"centre_mm": centre.tolist(), "estimate": dict(zip(CAMERA_PARAMETERS, full.tolist())),
                               "covariance": (full_cov + np.array(earlier.get("covariance", np.zeros((4, 4))))).tolist(),
                               "parent": model.get("calibration_id")}
    return NewVersion(new, stats, model.get("calibration_id"))


def _corrected_map(model: dict, drift: np.ndarray, centre_mm: np.ndarray) -> tuple[dict, dict]:
    """The map that reads p where the drifted camera's old map reads T(p): S^-1 after the old map, S the drift."""
    dx, dy, theta, s = drift[0] * 1e-6, drift[1] * 1e-6, drift[2] * 1e-6, drift[3] * 1e-6
    c = np.asarray(centre_mm) * 1e-3
    M = (1 + s) * rot(theta)
    S = np.eye(3)
    S[:2, :2] = M
    S[:2, 2] = c + [dx, dy] - M @ c
    back = np.linalg.inv(S)
    old = PlanarMap.from_dict(model["map"])
    H = back @ old.H
    corrected = PlanarMap(old.image_size, H / H[2, 2], old.centre, old.scale, old.radial, old.tangential, old.region)
    return corrected.to_dict(), _corrected_uncertainty(model["uncertainty"], back)


def _corrected_uncertainty(record: dict, back: np.ndarray) -> dict:
    """The map uncertainty record of the corrected map: its normalised homography turned by Tw S^-1 Tw^-1 (an
    affine map, so the parameters move linearly and their covariance with them)."""
    Tw = np.array(record["Tw"])
    M = Tw @ back @ np.linalg.inv(Tw)
    K = np.kron(M, np.eye(3))  # row-major vec(M H) = (M kron I) vec(H)
    theta = np.array(record["theta"])
    h = np.append(theta[:8], 1.0)
    h_new = K @ h
    G = np.eye(len(theta))
    G[:8, :8] = K[:8, :8] / h_new[8]
    new_theta = theta.copy()
    new_theta[:8] = h_new[:8] / h_new[8]
    cov = np.array(record["covariance"])
    return dict(record, theta=new_theta.tolist(), covariance=(G @ cov @ G.T).tolist())


def _routine_for(target: str, kinds: dict, home: dict) -> str:
    return RECALIBRATE["nozzle"] if kinds[target] == "nozzle" else RECALIBRATE[home[target]]


def _drift_figures(fit: DriftFit, target: str, kind: str) -> dict:
    est = fit.of(target)
    out = {}
    for p in PARAMETERS[kind]:
        value, std = est[p]
        unit = p.rsplit("_", 1)[1]
        out[p] = value
        out[f"{p.rsplit('_', 1)[0]}_std_{unit}"] = std
    return out


def _tables(targets, drift, test, actions, touch_up, checked) -> list[dict]:
    rows = []
    for t in targets:
        d = drift[t]
        rows.append([t, checked.get(t), f"{test[t]['p_value']:.3g}", "drift" if test[t]["drifted"] else "ok",
                     f"{d['dx_um']:.2f} ± {d['dx_std_um']:.2f}", f"{d['dy_um']:.2f} ± {d['dy_std_um']:.2f}",
                     f"{d['rotation_urad']:.0f} ± {d['rotation_std_urad']:.0f}" if "rotation_urad" in d else None,
                     f"{d['scale_ppm']:.0f} ± {d['scale_std_ppm']:.0f}" if "scale_ppm" in d else None, actions[t]])
    verdict = {"title": "Do the calibrations still hold? (drift estimate ± 1 σ)",
               "columns": ["target", "calibration", "p-value", "verdict", "dx (µm)", "dy (µm)", "rotation (µrad)",
                           "scale (ppm)", "action"],
               "rows": rows,
               "note": f"Drift when p < {test['threshold']:.3g}: a false-alarm rate of {test['alpha']:g} for the whole "
                       f"check, shared by its {test['tests']} tests (each target, and each group's fit of the model). "
                       "A camera's dx, dy: how far its map now reads from where it did; the nozzle's: its offset change."}
    tables = [verdict]
    if touch_up:
        tables.append({"title": "Touch-up, verified by leave-one-out (µm)",
                       "columns": ["target", "corrects", "mean", "max", "RMS", "n"],
                       "rows": [[t, ", ".join(v["parameters"]), round(v["mean_um"], 2), round(v["max_um"], 2),
                                 round(v["rms_um"], 2), v["n"]] for t, v in touch_up.items()],
                       "note": "Each reading judged by the correction estimated from all the other readings."})
    return tables
