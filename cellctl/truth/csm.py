"""The `truth` section of a simulated csm-positioning run: positioning judged against the physical world.

The routine measures its error as the seed does, in nominal kinematics of the joints; here the terminal
error is the distance between where the white circle physically was at the target pose and where it
physically ended (true kinematics, repeatability noise included), and the mark detectors are compared
with the true projections. Reads drivers.sim, which calibration/ never does.
"""

from __future__ import annotations

import math

import numpy as np

from geometry.irb120 import IRB120_DH

from calibration.routines.base import Devices, FitOutcome


def csm_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    moves = {m.step: m for m in world.moves if m.step is not None}
    white = np.asarray(params.white_mm) * 1e-3

    def physical_white(row) -> tuple[np.ndarray, bool]:
        """Where the white circle was after the move of this row's step; from the true kinematics (no
        repeatability noise) when the move happened before a resume."""
        move = moves.get(row["step"])
        if move is not None:
            return move.rotation @ white + move.translation, True
        q = np.radians([float(row[f"j{i}_deg"]) for i in range(1, 7)])
        R, t = world.true_arm.fixture_pose(q)
        return R @ white + t, False

    ok = [r for r in samples if r.get("status") == "ok" and r.get("feature") == "white"]
    first = {}
    for r in ok:  # one row per step is enough for its pose
        first.setdefault(r["step"], r)
    targets = {r["target"]: physical_white(r)[0] for r in first.values() if r["phase"] == "survey"}
    loops = {}
    for loop in params.loops:
        errors, exact = [], True
        for t, goal in sorted(targets.items()):
            path = sorted((r for r in first.values() if r["target"] == t and
                           (r["phase"] == "approach" or (r["phase"] == "iterate" and r["loop"] == loop))),
                          key=lambda r: r["step"])
            if not path:
                continue
            end, measured = physical_white(path[-1])
            exact &= measured
            errors.append(float(np.linalg.norm(end - goal) * 1e3))
        if errors:
            loops[loop] = {"n": len(errors), "mean_mm": float(np.mean(errors)), "max_mm": float(np.max(errors)),
                           "with_repeatability": exact}
    truth: dict = {"positioning_physical": loops.get(params.primary), "loops_physical": loops}
    # open loop: one move through the calibrated arm, no camera iteration
    ends = [(physical_white(r)[0], targets[r["target"]]) for r in first.values()
            if r["phase"] == "open-loop" and r["target"] in targets]
    if ends:
        errors = [float(np.linalg.norm(end - goal) * 1e3) for end, goal in ends]
        truth["open_loop_physical"] = {"n": len(errors), "mean_mm": float(np.mean(errors)),
                                       "max_mm": float(np.max(errors)), "camera_iterations": 0}

    # detectors against the true projection of each circle centre
    errs = {"chosen": [], "other": []}
    for r in samples:
        if r.get("status") != "ok":
            continue
        frame = world.frame_truth.get((r["camera"], r["frame_id"]))
        if frame is None or frame.step != r["step"]:
            continue
        true_uv = frame.features_px[r["feature"]]
        errs["chosen"].append(math.hypot(r["u_px"] - true_uv[0], r["v_px"] - true_uv[1]))
        if r.get("u_alt_px") is not None and not math.isnan(float(r["u_alt_px"])):
            errs["other"].append(math.hypot(r["u_alt_px"] - true_uv[0], r["v_alt_px"] - true_uv[1]))
    other = "dld" if params.detector == "contour" else "contour"
    truth["detectors"] = {name: {"n": len(e), "rms_px": float(np.sqrt(np.mean(np.square(e)))), "max_px": float(np.max(e))}
                          for name, e in ((params.detector, errs["chosen"]), (other, errs["other"])) if e}

    # the hidden robot and cameras, for the record
    dh_errors = [[(t[0] - n[0]) * 1e3, (t[1] - n[1]) * 1e3, math.degrees(t[3] - n[3])]
                 for t, n in zip(world.true_dh, IRB120_DH)]
    truth["robot"] = {"dh_errors": {"columns": ["d_mm", "a_mm", "joint_zero_deg"], "rows": dh_errors}}
    cams = {}
    for name, cam in world.cameras.items():
        centre = np.asarray(world.config.workspace_centre_mm) * 1e-3
        cams[name] = {"distance_m": float(np.linalg.norm(cam.C - centre)), "f_px": float(cam.fx),
                      "principal_px": [float(cam.cx), float(cam.cy)], "k1": float(cam.k1), "k2": float(cam.k2)}
    axes = [c.R_cw[:, 2] for c in world.cameras.values()]
    if len(axes) >= 2:
        truth["angle_between_axes_deg"] = float(np.degrees(np.arccos(np.clip(axes[0] @ axes[1], -1, 1))))
    truth["cameras"] = cams
    fitted = outcome.model.get("cameras", {})
    for name, m in fitted.items():
        if name in cams:
            cams[name]["fitted_z_r_m"] = m.get("z_r_m")
    return truth

