"""The `truth` section of a simulated arm calibration: the models against the true arm over the working volume.

The judged quantity is what the calibration is for: where the tool (the wrist camera) is relative to the board the
cell works on, T_board_camera(q), at 50 arm configurations drawn through the working volume (not the calibration's
poses, nor only near them), each model's prediction against the true arm's. Reads drivers.sim, which calibration/
never does.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from geometry.kinematic_table import KinematicTable
from geometry.transforms import inverse

from calibration.models.arm_kinematics import budget_scales
from calibration.models.hand_eye import _pair_residuals, _perturbed, pose_from_dict, transform_error
from calibration.routines.base import Devices, FitOutcome
from calibration.routines.six_axis._arm_poses import _clear

UNSEEN = 50
VOLUME_SEED = 28


def working_volume(table: KinematicTable, n: int = UNSEEN, seed: int = VOLUME_SEED, reach: float = 0.85) -> np.ndarray:
    """n joint configurations with the tool down-ish over the whole table side of the arm, elbow up, clear of the
    table: base +/-90 deg about the board's side, shoulder and elbow through their working ranges, the wrist
    anywhere."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        q = np.radians([rng.uniform(90, 270), rng.uniform(-160, -20), rng.uniform(20, 160), rng.uniform(-200, 20),
                        rng.uniform(-150, -30), rng.uniform(-180, 180)])
        if table.within_limits(q) is None and _clear(q, reach):
            out.append(q)
    return np.array(out)


def _errors(table: KinematicTable, X, Y, Q, truth) -> np.ndarray:
    return np.array([transform_error(inverse(Y) @ table.forward(q) @ X, t) for q, t in zip(Q, truth)])


def arm_kinematics_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    model = outcome.model
    camera = world.cameras[getattr(devices.cameras[params.camera], "sim_name", params.camera)]
    board = next(b for b in world.boards.values() if b.config.mount == "table")
    nominal = KinematicTable.from_dict(model["nominal"])
    Q = working_volume(nominal)
    truth = [inverse(board.pose) @ world.true_arm.flange(q) @ camera.mount for q in Q]
    models = {"before": (nominal, model["before"]["tool"], model["before"]["world"]),
              "after": (KinematicTable.from_dict(model["table"]), model["tool"], model["world"]),
              **{name: (KinematicTable.from_dict(model[name]["table"]), model[name]["tool"], model[name]["world"])
                 for name in ("sequential", "sequential_hand_eye") if name in model}}
    out: dict = {"unseen_poses": len(Q), "board_scale_error_pct": (board.scale - 1) * 100}
    for name, (table, X, Y) in models.items():
        e = _errors(table, pose_from_dict(X), pose_from_dict(Y), Q, truth)
        out[f"position_error_{name}_mean_mm"] = float(e[:, 0].mean() * 1e3)
        out[f"position_error_{name}_max_mm"] = float(e[:, 0].max() * 1e3)
        out[f"orientation_error_{name}_mean_deg"] = float(np.degrees(e[:, 1]).mean())
    out["improvement"] = out["position_error_before_mean_mm"] / max(out["position_error_after_mean_mm"], 1e-9)
    for name in ("sequential", "sequential_hand_eye"):
        if f"position_error_{name}_mean_mm" in out:
            out[f"{name}_over_simultaneous"] = (out[f"position_error_{name}_mean_mm"]
                                                / max(out["position_error_after_mean_mm"], 1e-9))
    out.update(_sigma_honesty(model, nominal, world, board, camera))
    return out


def _sigma_honesty(model: dict, nominal: KinematicTable, world, board, camera) -> dict:
    """Each identified deviation's error over its sigma. Its true value is that of the same parameterisation (the
    deviations the run fixed stay at nominal, X and Y free) fitted to the true arm without noise over many
    configurations: what a perfect run would have found, every deviation the views cannot see absorbed as the
    real fit absorbs it."""
    names = nominal.parameter_names()
    identified = list(model["identified"])
    free = np.array([names.index(n) for n in identified])
    scales = budget_scales(nominal)[free]
    Q = working_volume(nominal, 200, VOLUME_SEED + 1)
    F_true = np.array([world.true_arm.flange(q) for q in Q])
    X0, Y0 = pose_from_dict(model["tool"]), pose_from_dict(model["world"])
    B = np.array([inverse(inverse(board.pose) @ F @ camera.mount) for F in F_true])  # T_camera_board, true

    def residuals(p):
        v = nominal.vector()
        v[free] += p[12:] * scales
        r = _pair_residuals(_perturbed(X0, p[:6]), _perturbed(Y0, p[6:12]), nominal.with_vector(v).forward_batch(Q),
                            B, "eye-in-hand")
        return np.hstack([r[:, :3] / 1e-6, r[:, 3:] / 1e-6]).ravel()

    p = least_squares(residuals, np.zeros(12 + len(free)), method="lm", x_scale="jac").x
    return error_over_sigma(model, dict(zip(identified, p[12:] * scales)))


def error_over_sigma(model: dict, true_values: dict[str, float]) -> dict:
    """Each identified deviation's error against its true value (m or rad) over its reported sigma, and their median
    (the model stores mm and deg)."""
    z = {}
    for n, true in true_values.items():
        unit = 1e-3 if n.split("_")[0] in ("a", "d") else math.pi / 180
        z[n] = abs(model["deviations"][n] * unit - true) / (model["sigma"][n] * unit)
    return {"error_over_sigma": z, "error_over_sigma_median": float(np.median(list(z.values())))}
