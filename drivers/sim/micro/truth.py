"""Ground truth questions about the simulated world, for tests and the `truth` section of sim reports.

Calibration code must never import this module.
"""

from __future__ import annotations

import numpy as np

from drivers.sim.micro.world import World


def true_command_for_pixel(world: World, camera: str, uv, z: float, alpha: float, feature_offset=(0.0, 0.0)) -> np.ndarray:
    """The commanded (x, y) at rotation alpha that puts the feature exactly where pixel uv looks, in the
    plane at height z. The feature is the nozzle tip, or a held sphere `feature_offset` off its axis.

    No repeatability noise: this is the map a perfect calibration would find.
    """
    feature = world.camera_now(camera).backproject_to_plane(uv, z)[:, :2]
    axis = feature - np.asarray(feature_offset) - world.tip_offset(alpha)
    return world.robot.commanded_xy(axis)


def true_feature_pixel(world: World, camera: str, frame_id: int, step: int | None = None,
                       near=None) -> np.ndarray | None:
    """Where a feature of that frame truly projected: the first, or the one nearest the pixel `near`
    (None if this world did not take the frame)."""
    truth = world.frame_truth.get((camera, int(frame_id)))
    if truth is None or not truth.features_px or (step is not None and truth.step != step):
        return None
    if near is None:
        return truth.features_px[0]
    pts = np.array(truth.features_px)
    return pts[int(np.argmin(np.linalg.norm(pts - np.asarray(near), axis=1)))]


def camera_summary(world: World, camera: str) -> dict:
    cam = world.cameras[camera]
    tilt = np.degrees(np.arccos(abs(cam.R_cw[2, 2])))
    return {"fx_px": cam.fx, "cx_px": cam.cx, "cy_px": cam.cy, "k1": cam.k1, "k2": cam.k2,
            "p1": cam.p1, "p2": cam.p2, "tilt_deg": float(tilt), "mirror": cam.mirror}
