"""The `truth` section of a simulated `arm-kinematics` run, either observation: the wrist camera's (cellctl/truth/
arm.py) or the fixed cameras' (here), which the routine's `observe` says.

Fixed cameras (the IRB 120 cell): the judged quantity is where the fixture frame is, at 50 arm configurations drawn
through the working volume (the fixture anywhere in the 0.6 m cube about the workspace centre the cameras aim at,
its plate within 60 deg of facing them, any joints within the limits: not the calibration's poses), each model's
prediction against the true arm (`world.true_arm`, with the fixture's true `world.tool_m`):

- in camera 1's frame (the keys issue 28 names): T_cam1_fixture(q) = T_cam1_base @ T_base_flange(q) @
  T_flange_fixture, the model's camera 1 and arm against the true ones. The gauge (what the cameras' poses absorb)
  does not count; camera 1's own frame does: its turn is hardly told from its principal point and decentring, so
  a part of this error is common to every pose (`position_offset_*_mm`, the mean error vector's length);
- in the measured frame (`measured_*`): the true fixture as the model's own cameras triangulate its circles (no
  noise) against the model's arm: what a move guided by these cameras would miss by (poses every camera sees);
- in the arm's frame (`arm_frame_*`): the model's fixture poses registered rigidly onto the true ones (the base's
  pose removed, lengths kept): the arm's own geometry.

`error_over_sigma_median` as cellctl/truth/arm.py computes it: each identified deviation against the value the
same parameterisation takes on the true arm without noise (the base's pose and the mount free). Reads drivers.sim,
which calibration/ never does.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from geometry.irb120 import IRB120_LIMITS_DEG
from geometry.kinematic_table import KinematicTable

from calibration.models import arm_kinematics_stereo as msk
from calibration.models.arm_kinematics import budget_scales
from calibration.models.hand_eye import _perturbed, transform_error
from calibration.routines.base import Devices, FitOutcome

from cellctl.truth import arm

UNSEEN = 50
VOLUME_SEED = 28
HALF_FIELD_M = 0.3
FLOOR_M = 0.05
FACING_DEG = 60.0
MODELS = ("before", "after", "sequential")


def arm_kinematics_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    if getattr(params, "observe", "wrist-board") != "fixed-cameras":
        return arm.arm_kinematics_truth(world, devices, params, samples, outcome)
    return fixed_cameras_truth(world, devices, params, samples, outcome)


def matrix_of(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def true_camera(camera) -> np.ndarray:
    """T_camera_base of a simulated camera (world -> camera: p_c = R_cw^T (p - C))."""
    return matrix_of(camera.R_cw.T, -camera.R_cw.T @ camera.C)


def working_volume(world, n: int = UNSEEN, seed: int = VOLUME_SEED) -> np.ndarray:
    """n joint configurations, uniform within the joint limits (joint 6 within +/-180 deg), that put the fixture
    in the cube about the workspace centre, above the floor, its plate within FACING_DEG of facing the cameras."""
    rng = np.random.default_rng(seed)
    centre = np.asarray(world.config.workspace_centre_mm) * 1e-3
    eyes = [c.C for _, c in sorted(world.cameras.items())]
    lo, hi = np.radians(np.array(IRB120_LIMITS_DEG, dtype=float)).T
    lo[5], hi[5] = -math.pi, math.pi
    out = []
    while len(out) < n:
        q = rng.uniform(lo, hi)
        R, t = world.nominal_arm.fixture_pose(q)
        if np.any(np.abs(t - centre) > HALF_FIELD_M) or t[2] < FLOOR_M:
            continue
        facing = sum((e - t) / np.linalg.norm(e - t) for e in eyes)
        if -R[:, 2] @ facing < math.cos(math.radians(FACING_DEG)) * np.linalg.norm(facing):
            continue
        out.append(q)
    return np.array(out)


def _stats(e: np.ndarray, key: str) -> dict:
    return {f"position_error_{key}_mean_mm": float(e[:, 0].mean() * 1e3),
            f"position_error_{key}_max_mm": float(e[:, 0].max() * 1e3),
            f"orientation_error_{key}_mean_deg": float(np.degrees(e[:, 1]).mean())}


def fixed_cameras_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    model = outcome.model
    fixture = params.fixture()
    first = params.cameras[0]
    cam1 = world.cameras[getattr(devices.cameras[first], "sim_name", first)]
    V1 = true_camera(cam1)
    nominal = KinematicTable.from_dict(model["nominal"])
    Q = working_volume(world)
    T_true = np.array([matrix_of(*world.true_arm.fixture_pose(q)) for q in Q])  # T_base_fixture
    models = {"before": msk.StereoModel.from_dict(model["before"]), "after": msk.StereoModel.from_dict(model),
              "sequential": msk.StereoModel.from_dict(model["sequential"])}
    seen = seen_by_every_camera(world, devices, params, T_true, fixture)
    out: dict = {"unseen_poses": len(Q), "unseen_poses_seen_by_every_camera": int(seen.sum())}
    for name, m in models.items():
        T_model = m.fixture_poses(Q)
        pred = m.cameras[0].T_camera_base[None] @ T_model
        true = V1[None] @ T_true
        e = np.array([transform_error(p, t) for p, t in zip(pred, true)])
        out.update(_stats(e, name))
        out[f"position_offset_{name}_mm"] = float(np.linalg.norm((pred[:, :3, 3] - true[:, :3, 3]).mean(axis=0)) * 1e3)
        out.update({f"measured_{k}": v for k, v in _stats(_measured(world, devices, params, m, fixture, Q[seen],
                                                                    T_true[seen]), name).items()})
        out.update({f"arm_frame_{k}": v for k, v in _stats(_registered(T_model, T_true, fixture), name).items()})
    for prefix in ("", "measured_", "arm_frame_"):
        after = max(out[f"{prefix}position_error_after_mean_mm"], 1e-9)
        out[f"{prefix}improvement"] = out[f"{prefix}position_error_before_mean_mm"] / after
        out[f"{prefix}simultaneous_over_sequential"] = out[f"{prefix}position_error_sequential_mean_mm"] / after
    out["camera1_lens_error_px"] = _lens_errors(models["after"].cameras[0].lens, cam1)
    out.update(_sigma_honesty(model, nominal, world, fixture))
    return out


def seen_by_every_camera(world, devices, params, T_true: np.ndarray, fixture: msk.Fixture) -> np.ndarray:
    """Which poses put every circle inside every camera's image (the measured frame needs them seen)."""
    ok = np.ones(len(T_true), dtype=bool)
    for name in params.cameras:
        camera = world.cameras[getattr(devices.cameras[name], "sim_name", name)]
        for k, T in enumerate(T_true):
            uv = camera.project(fixture.points @ T[:3, :3].T + T[:3, 3])
            inside = np.all(uv >= 0) and np.all(uv[:, 0] <= camera.width - 1) and np.all(uv[:, 1] <= camera.height - 1)
            ok[k] &= bool(inside)
    return ok


def _measured(world, devices, params, m: msk.StereoModel, fixture: msk.Fixture, Q, T_true) -> np.ndarray:
    """(n, 2): the true fixture as the model's cameras measure it (`triangulated`) against the model's arm."""
    if not len(Q):
        return np.full((1, 2), np.nan)
    T_model = m.fixture_poses(Q)
    measured = triangulated(world, devices, params, m.cameras, fixture, T_true)
    return np.array([transform_error(a, b) for a, b in zip(T_model, measured)])


def triangulated(world, devices, params, cameras: list[msk.Camera], fixture: msk.Fixture, T_true) -> np.ndarray:
    """(n, 4, 4): the true fixture poses T_true as `cameras` (a model's, in params.cameras' order) see them: its
    circles' centres projected through the true cameras (no noise), triangulated through these, the drawing fitted
    to them."""
    rows = []
    for c, name in enumerate(params.cameras):
        camera = world.cameras[getattr(devices.cameras[name], "sim_name", name)]
        for k, T in enumerate(T_true):
            for i, uv in enumerate(camera.project(fixture.points @ T[:3, :3].T + T[:3, 3])):
                rows.append((k, c, i, uv))
    k, c, i, uv = (np.array([r[j] for r in rows]) for j in range(4))
    n = len(T_true)
    obs = msk.Observations([str(j) for j in range(n)], np.zeros((n, 6)), tuple(params.cameras), {}, k, c, i, uv)
    X = msk.triangulate(cameras, obs)
    return np.array([msk.rigid_fit(fixture.points, X[j]) for j in range(n)])


def circles(T: np.ndarray, fixture: msk.Fixture) -> np.ndarray:
    """(n x circles, 3): the fixture's circles at each of the poses T (n, 4, 4)."""
    return (np.einsum("nij,kj->nki", T[:, :3, :3], fixture.points) + T[:, None, :3, 3]).reshape(-1, 3)


def _registered(T_model: np.ndarray, T_true: np.ndarray, fixture: msk.Fixture) -> np.ndarray:
    """(n, 2): the model's fixture poses after the rigid transform that lays its circles best onto the true ones."""
    G = msk.rigid_fit(circles(T_model, fixture), circles(T_true, fixture))
    return np.array([transform_error(G @ a, b) for a, b in zip(T_model, T_true)])


def _lens_errors(lens, camera) -> dict:
    return {k: float(getattr(lens, k) - getattr(camera, k)) for k in ("fx", "fy", "cx", "cy")}


def _sigma_honesty(model: dict, nominal: KinematicTable, world, fixture: msk.Fixture) -> dict:
    """Each identified deviation's error over its sigma, against the same parameterisation (the deviations the run
    fixed at nominal, the base's pose and the mount free) fitted to the true arm's fixture poses without noise."""
    names = nominal.parameter_names()
    identified = list(model["identified"])
    free = np.array([names.index(n) for n in identified], dtype=int)
    scales = budget_scales(nominal)[free]
    Q = working_volume(world, 200, VOLUME_SEED + 1)
    T_true = np.array([matrix_of(*world.true_arm.fixture_pose(q)) for q in Q])

    def residuals(p):
        v = nominal.vector()
        v[free] += p[12:] * scales
        T = _perturbed(np.eye(4), p[:6])[None] @ nominal.with_vector(v).forward_batch(Q) @ _perturbed(fixture.mount,
                                                                                                        p[6:12])
        R = np.einsum("nji,njk->nik", T[:, :3, :3], T_true[:, :3, :3])
        w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1) / 2
        return np.hstack([w / 1e-6, (T[:, :3, 3] - T_true[:, :3, 3]) / 1e-6]).ravel()

    p = least_squares(residuals, np.zeros(12 + len(free)), method="lm", x_scale="jac").x
    return arm.error_over_sigma(model, dict(zip(identified, p[12:] * scales)))
