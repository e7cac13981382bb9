"""The `truth` section of a simulated run: the fit judged against the hidden world.

Only runs on a simulated cell; reads drivers.sim, which calibration/ never does.
"""

from __future__ import annotations

import math

import numpy as np

from drivers.sim.micro.truth import camera_summary, true_command_for_pixel, true_feature_pixel

from calibration.models.planar import PlanarMap
from calibration.models.tool_offset import rot
from calibration.routines.base import Devices, FitOutcome
from calibration.routines.health.repeatability import fit_repeatability

from cellctl.truth.six_axis import hand_eye_check_truth


def virtual_grid_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The fitted map against the true one for the bare nozzle, in the focal plane."""
    return _planar_truth(world, devices, params, samples, outcome, devices.area(params.area).z, (0.0, 0.0))


def area2_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The fitted map against the true one for a sphere of nominal size resting on the substrate."""
    z = world.config.floor_z_mm * 1e-3 + params.sphere_diameter_mm / 2 * 1e-3
    return _planar_truth(world, devices, params, samples, outcome, z, (0.0, 0.0))


def hybrid_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The composite map against the true one: for the held sphere (its centre height and centring error), or
    for a sphere of nominal size resting on the substrate."""
    if params.registration == "placed-spheres":
        return area2_truth(world, devices, params, samples, outcome)
    if world.held is None:
        return {}
    truth = _planar_truth(world, devices, params, samples, outcome, float(world.held.centre[2]), world.held_offset)
    laid = world.dot_grids.get(params.fixture)
    if laid is not None:
        truth["grid_plane_offset_um"] = float((laid.centre[2] - world.held.centre[2]) * 1e6)
    truth["sphere_centring_um"] = (np.asarray(world.held_offset) * 1e6).tolist()
    return truth


def _planar_truth(world, devices, params, samples, outcome, z, feature_offset) -> dict:
    area = devices.area(params.area)
    camera = devices.camera(area.camera)
    sim_name = getattr(camera, "sim_name", area.camera)
    fitted = PlanarMap.from_dict(outcome.model["map"])
    ok = [r for r in samples if r.get("status") == "ok" and r.get("x_mm") is not None]
    ver = [r for r in ok if r["set"] == "ver"] or ok
    uv = np.array([[r["u_px"], r["v_px"]] for r in ver], dtype=float)
    true_xy = true_command_for_pixel(world, sim_name, uv, z, area.alpha_cal, feature_offset)
    mapping = np.linalg.norm(fitted.pixel_to_plane(uv) - true_xy, axis=1) * 1e6

    centroid_err = []
    for r in ok:
        true_px = true_feature_pixel(world, sim_name, r["frame_id"], r["step"], near=(r["u_px"], r["v_px"]))
        if true_px is not None:
            centroid_err.append(np.hypot(r["u_px"] - true_px[0], r["v_px"] - true_px[1]))
    centroid_err = np.array(centroid_err)
    return {
        "mapping_n": int(mapping.size),
        "mapping_mean_um": float(mapping.mean()),
        "mapping_max_um": float(mapping.max()),
        "mapping_rms_um": float(np.sqrt(np.mean(mapping**2))),
        "centroid_n": int(centroid_err.size),
        "centroid_rms_px": float(np.sqrt(np.mean(centroid_err**2))) if centroid_err.size else None,
        "centroid_max_px": float(centroid_err.max()) if centroid_err.size else None,
        "camera": camera_summary(world, sim_name),
        "nozzle_offset_um": (world.robot.nozzle_offset * 1e6).tolist(),
    }


def rotation_sweep_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The true nozzle offset at alpha_cal, against the fitted one."""
    import math

    area = devices.area(params.area)
    true = world.tip_offset(area.alpha_cal) * 1e6
    model = outcome.model
    return {"dx_um": float(true[0]), "dy_um": float(true[1]),
            "dx_error_um": model["dx_um"] - float(true[0]), "dy_error_um": model["dy_um"] - float(true[1]),
            "r_um": float(math.hypot(*true))}


def onboard_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """D as the calibration can know it: what eq. (4) gives on noise-free measurements of this cell.

    The arm's scale and skew errors put its rotation axis off the reported gripper position by an amount
    that changes with the position, (A - I) P + o, and the spheres land off the commanded points by
    (A - I) c + o plus the tool offset; no single D fits every pose. The true D here is the least-squares
    one over the same views, each weighted by the spheres it saw, as the fit weights them. `d_mean_*`:
    the plain average of the axis offset over the views minus the landing offset (differs by ~2 µm)."""
    views = [r for r in samples if r["set"] == "pose" and r.get("status") == "ok"]
    placed = [r for r in samples if r["set"] == "place"]
    commanded = np.array([[r["x_mm"], r["y_mm"]] for r in placed]) * 1e-3
    landing = np.mean([world.robot.actual_xy(c) - c for c in commanded], axis=0) + world.tip_offset(0.0)
    poses = sorted({int(r["pose"]) for r in views})
    first = {k: next(r for r in views if int(r["pose"]) == k) for k in poses}
    P = {k: np.array([first[k]["x_mm"], first[k]["y_mm"]]) * 1e-3 for k in poses}
    off = {k: world.robot.actual_xy(P[k]) - P[k] for k in poses}  # axis minus reported position
    lhs, rhs = [], []
    for r in views:
        k = int(r["pose"])
        if k == poses[0]:
            continue
        R = rot(math.radians(first[k]["alpha_deg"] - first[poses[0]]["alpha_deg"]))
        lhs.append(np.eye(2) - R)
        rhs.append(off[k] - R @ off[poses[0]] - (np.eye(2) - R) @ landing)
    d = np.linalg.lstsq(np.vstack(lhs), np.concatenate(rhs), rcond=None)[0] * 1e6
    d_mean = (np.mean(list(off.values()), axis=0) - landing) * 1e6
    model = outcome.model
    return {"d_x_um": float(d[0]), "d_y_um": float(d[1]),
            "d_x_error_um": model["d_x_um"] - float(d[0]), "d_y_error_um": model["d_y_um"] - float(d[1]),
            "d_mean_x_um": float(d_mean[0]), "d_mean_y_um": float(d_mean[1])}


def place_test_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """Where the spheres truly landed against their targets (no camera in between)."""
    area = devices.area(params.area)
    centres = np.array([s.centre[:2] for s in world.spheres])
    landed = world.robot.commanded_xy(centres - world.tip_offset(area.alpha_cal))  # in the commanded frame
    errors = []
    for r in samples:
        if r.get("status") == "ok":
            target = np.array([r["target_x_mm"], r["target_y_mm"]]) * 1e-3
            errors.append(np.min(np.linalg.norm(landed - target, axis=1)) * 1e6)
    return {"placement_mean_um": float(np.mean(errors)), "placement_max_um": float(np.max(errors))} if errors else {}


def repeatability_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The simulated robot's pose repeatability, and the one of where the nozzle truly went (no camera).

    Each attained position is off its mean by Gaussian noise of sigma per horizontal axis, so its distance l
    from the mean follows a Rayleigh distribution: mean sigma sqrt(pi/2), SD sigma sqrt(2 - pi/2), and
    RP = sigma (sqrt(pi/2) + 3 sqrt(2 - pi/2)) = 3.22 sigma. `rp_attained_*`: RP of the true nozzle
    positions of these very visits (their true pixels through the true camera), what a perfect camera sees."""
    sigma = world.config.robot.repeatability_xy_um
    rp = sigma * (math.sqrt(math.pi / 2) + 3 * math.sqrt(2 - math.pi / 2))
    area = devices.area(params.area)
    sim_name = getattr(devices.camera(area.camera), "sim_name", area.camera)
    attained = []
    for r in samples:
        true_px = (true_feature_pixel(world, sim_name, r["frame_id"], r["step"], near=(r["u_px"], r["v_px"]))
                   if r.get("status") == "ok" else None)
        if true_px is not None:
            xy = true_command_for_pixel(world, sim_name, [true_px], area.z, area.alpha_cal)[0] * 1e3
            attained.append(dict(r, meas_x_mm=xy[0], meas_y_mm=xy[1]))
    true_rp = fit_repeatability(attained, params.drift_cycles).stats["repeatability"]
    measured = outcome.stats["repeatability"]
    return {"sigma_xy_um": sigma, "rp_um": rp, "rp_attained_um": true_rp["rp_um"],
            "rp_attained_mean_um": true_rp["rp_mean_um"],
            "rp_mean_error_pct": 100 * (measured["rp_mean_um"] / rp - 1)}


def check_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The drift the world applied, in the check's terms: a camera's map shift (and rotation, scale) about its view
    centre, the nozzle's offset change turned to alpha_cal (where its calibration holds it)."""
    if any(t.startswith("hand-eye:") for t in outcome.model.get("targets", [])):
        return hand_eye_check_truth(world, devices, params, samples, outcome)
    drift = world.config.drift
    now = world.clock.now()
    truth = {}
    for target in outcome.model.get("targets", []):
        if target == params.tool:
            knob = drift.nozzle if drift.in_force(drift.nozzle, now) else None
            change = np.asarray(knob.offset_change_um if knob else (0.0, 0.0))
            d = rot(devices.area(params.area).alpha_cal) @ change
            truth[target] = {"dx_um": float(d[0]), "dy_um": float(d[1])}
            continue
        sim_name = getattr(devices.camera(target), "sim_name", target)
        knob = drift.cameras.get(sim_name)
        knob = knob if drift.in_force(knob, now) else None
        truth[target] = {"dx_um": knob.map_shift_um[0] if knob else 0.0, "dy_um": knob.map_shift_um[1] if knob else 0.0,
                         "rotation_urad": knob.rotation_urad if knob else 0.0, "scale_ppm": knob.scale_ppm if knob else 0.0}
    truth["drifted"] = [t for t, d in truth.items() if any(abs(v) > 0 for v in d.values())]
    return truth
