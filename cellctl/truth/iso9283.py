"""The `truth` section of a simulated iso9283 run: AP and RP as a perfect camera would have measured them, as the
calibrated camera would have on noise-free images, and the arm's accuracy in its own base frame.

The routine measures the flange in the frame its hand-eye calibration defines: T = Y_fit @ inv(T_camera_board) @
inv(X_fit). To judge that measurement, truth must be in that very frame: the calibration's Y is the cell frame. A
perfect camera sees T_camera_board = inv(T_flange @ X_true) @ Y_true, with T_flange where the arm truly put the
flange (the world's record of the visit's move, its repeatability noise included), X_true the camera's true mount and
Y_true the board's true pose; through the calibration the run used, that is

    T_true_seen = Y_fit @ inv(Y_true) @ T_flange @ X_true @ inv(X_fit)

(times T_flange_tcp when the poses are of a TCP on the flange). `ap_mm`, `rp_mm` (per pose and the worst) are the same
ISO 9283 math on those poses: measured minus truth is what the camera adds, its images and its calibrated lens.

`ap_image_mm`, `rp_image_mm` split that in two: the same PnP and the same calibration (lens, board scale, X, Y) fed the
true pixels of the board's corners in each frame (no sensor noise, no rendering or detection error). Measured minus
these is what the images add; these minus `ap_mm` / `rp_mm` what the calibration's lens and board scale, fitted
together with X and Y on the same arm, get wrong (they absorb part of the arm's error, which `ap_mm` keeps).

`ap_base_mm`, `rp_base_mm`: the raw true TCP poses against the commanded ones in the true base frame: the arm's
accuracy in its own frame (its geometry errors, which its controller cannot see), for information. It differs from
`ap_mm` by what the hand-eye calibration absorbed of those errors into X and Y; a camera on the wrist sees the base
frame only through a calibration made with the same arm, so no run of this routine can measure it.

`rp_model_mm`: the simulated arm's RP over many cycles (its Gaussian repeatability, 3-D: 3.62 sigma).

Reads drivers.sim (through the world it is given), which calibration/ never does.
"""

from __future__ import annotations

import math

import numpy as np

from calibration.errors import VisionError
from calibration.models import arm_kinematics_stereo as msk
from calibration.models import iso9283 as iso
from calibration.models.hand_eye import pose_from_dict
from calibration.routines.base import Devices, FitOutcome
from calibration.routines.six_axis import _iso_stereo as stereo_
from calibration.routines.six_axis.iso9283 import flange_from_corners
from calibration.vision.charuco import Corners

from cellctl.truth.arm_stereo import circles, matrix_of, seen_by_every_camera, triangulated, working_volume

POSE_KEYS = ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")
# the distance of 3-D isotropic Gaussian noise of sigma per axis from its mean (Maxwell): mean 2 sqrt(2/pi) sigma, SD
# sqrt(3 - 8/pi) sigma, so RPl = (2 sqrt(2/pi) + 3 sqrt(3 - 8/pi)) sigma = 3.62 sigma for many cycles
MAXWELL_RP = 2 * math.sqrt(2 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi)


def iso9283_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    if params.observe == "fixed-cameras":
        return fixed_cameras_truth(world, devices, params, samples, outcome)
    model = devices.calibrations[f"hand-eye:{params.camera}"]
    X_fit, Y_fit = pose_from_dict(model["hand_eye"]), pose_from_dict(model["world"])
    sim_name = getattr(devices.cameras[params.camera], "sim_name", params.camera)
    board = model["board"]
    boards = [b for b in world.boards.values() if b.config.first_marker == int(board.get("first_marker", 0))
              and tuple(b.config.squares) == tuple(board["squares"])]
    if len(boards) != 1:
        raise LookupError(f"no board of {board['squares']} squares from marker {board.get('first_marker', 0)} in the "
                          "world")
    X_true, Y_true = world.mount_now(sim_name), world.mount_now(boards[0].name)
    frame = Y_fit @ np.linalg.inv(Y_true)
    to_camera = X_true @ np.linalg.inv(X_fit)
    tcp = np.eye(4)
    tcp[:3, 3] = np.asarray(params.tcp_mm) * 1e-3  # the TCP the poses are of (the flange by default)
    seen, base, imaged, commanded = {}, {}, {}, {}
    for r in sorted((r for r in samples if r.get("status") == "ok"), key=lambda r: int(r["step"])):
        moves = [m for m in world.moves if m.step == int(r["step"])]
        if not moves:
            continue
        flange = moves[-1].flange  # the visit's last move: onto the pose (its approach came first)
        name = str(r["pose"])
        seen.setdefault(name, []).append(frame @ flange @ to_camera @ tcp)
        base.setdefault(name, []).append(flange @ tcp)
        commanded.setdefault(name, []).append(pose_from_dict({k: r[f"cmd_{k}"] for k in POSE_KEYS}))
        ideal = world.frame_truth.get((sim_name, int(r["frame_id"])))
        if ideal is not None and boards[0].name in ideal.corners_px:  # the frame's true corner pixels, if kept
            ids, uv = ideal.corners_px[boards[0].name]
            try:
                imaged.setdefault(name, []).append(flange_from_corners(Corners(ids, uv, 0), model)[0] @ tcp)
            except VisionError:  # too few or ambiguous even without noise: left out (then no image figure)
                pass
    return figures(commanded, seen, imaged, outcome, world, base)


def figures(commanded: dict, seen: dict, imaged: dict, outcome: FitOutcome, world, base: dict | None = None) -> dict:
    """AP and RP per pose of the true poses `seen` (and of `imaged`, `base`) against `commanded`, and what the
    camera added (measured less truth)."""
    truth: dict = {"ap_mm": {}, "rp_mm": {}, "ap_base_mm": {}, "rp_base_mm": {}, "ap_image_mm": {},
                   "rp_image_mm": {}, "orientation": {}}
    for name in sorted(seen):
        if len(seen[name]) < 2:
            continue
        a = iso.pose_accuracy(np.array(commanded[name]), np.array(seen[name]))
        r = iso.pose_repeatability(np.array(seen[name]))
        truth["ap_mm"][name] = a.ap_p * 1e3
        truth["rp_mm"][name] = r.rp_l * 1e3
        if base:
            truth["ap_base_mm"][name] = iso.pose_accuracy(np.array(commanded[name]), np.array(base[name])).ap_p * 1e3
            truth["rp_base_mm"][name] = iso.pose_repeatability(np.array(base[name])).rp_l * 1e3
        if len(imaged.get(name, ())) == len(seen[name]):
            truth["ap_image_mm"][name] = iso.pose_accuracy(np.array(commanded[name]), np.array(imaged[name])).ap_p * 1e3
            truth["rp_image_mm"][name] = iso.pose_repeatability(np.array(imaged[name])).rp_l * 1e3
        truth["orientation"][name] = {"ap_abc_deg": [math.degrees(v) for v in a.ap_abc],
                                      "rp_abc_deg": [math.degrees(v) for v in r.rp_abc]}
    for key in ("ap_mm", "rp_mm", "ap_base_mm", "rp_base_mm", "ap_image_mm", "rp_image_mm"):
        if truth[key]:
            truth[key]["worst"] = max(truth[key].values())
    measured = outcome.stats
    for key in ("ap_mm", "rp_mm"):  # what the camera added: measured less truth, per pose
        truth[f"{key[:2]}_error_mm"] = {k: measured[key][k] - v for k, v in truth[key].items()
                                        if k in measured.get(key, {})}
    sigma = world.config.robot.repeatability_mm
    truth["rp_model_mm"] = MAXWELL_RP * sigma  # the simulated arm's RP over many cycles
    truth["repeatability_sigma_mm"] = sigma
    return truth


def fixed_cameras_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The fixed cameras' frame is their calibration's: a perfect instrument in that frame sees the true fixture
    pose T through G, the rigid map of the true base frame onto it. G is fitted once over the working volume
    (cellctl/truth/arm_stereo.py's 50 poses, those every camera sees), the true circles against the same circles
    triangulated through the calibration's cameras from their true pixels: fixed before any visit is looked at, so
    it absorbs no pose's AP. `ap_mm`, `rp_mm`: the visits' true fixture poses (the world's record of each visit's
    last move, its repeatability noise included) through G; `ap_image_mm`, `rp_image_mm`: the routine's own
    measurement fed each frame's true circle centres (no sensor noise, no detection error)."""
    model = devices.calibrations[stereo_.TARGET]
    fixture = stereo_.fixture_of(model)
    cameras = stereo_.cameras_of(model, params.cameras)
    Q = working_volume(world)
    T_volume = np.array([matrix_of(*world.true_arm.fixture_pose(q)) for q in Q])
    T_volume = T_volume[seen_by_every_camera(world, devices, params, T_volume, fixture)]
    true_circles = circles(T_volume, fixture)
    seen_circles = circles(triangulated(world, devices, params, cameras, fixture, T_volume), fixture)
    G = msk.rigid_fit(true_circles, seen_circles)
    tcp = params.tcp()
    sims = [getattr(devices.cameras[c], "sim_name", c) for c in params.cameras]
    names = ("white", *(f"black{i}" for i in range(1, len(fixture.points))))
    seen, imaged, commanded = {}, {}, {}
    for r in sorted((r for r in samples if r.get("status") == "ok"), key=lambda r: int(r["step"])):
        moves = [m for m in world.moves if m.step == int(r["step"])]
        if not moves:
            continue
        name = str(r["pose"])
        seen.setdefault(name, []).append(G @ matrix_of(moves[-1].rotation, moves[-1].translation) @ tcp)
        commanded.setdefault(name, []).append(pose_from_dict({k: r[f"cmd_{k}"] for k in POSE_KEYS}))
        ids = str(r["frame_id"]).split(",")  # each camera's frames in turn; the arm stood still: its first one
        ideal = [world.frame_truth.get((sim, int(ids[c * len(ids) // len(sims)]))) for c, sim in enumerate(sims)]
        if all(f is not None for f in ideal):
            uv = np.array([f.features_px[n] for f in ideal for n in names], dtype=float)
            camera_of = np.repeat(np.arange(len(ideal)), len(names))
            point_of = np.tile(np.arange(len(names)), len(ideal))
            T = stereo_.fixture_pose(model, params.cameras, uv, camera_of, point_of, centre_model="point")[0]
            imaged.setdefault(name, []).append(T @ tcp)
    truth = figures(commanded, seen, imaged, outcome, world)
    left = true_circles @ G[:3, :3].T + G[:3, 3] - seen_circles  # what a rigid map leaves: the cameras' distortion
    truth["frame"] = {"volume_poses": len(T_volume),
                      "registration_rms_mm": float(np.sqrt(np.mean(np.sum(left ** 2, axis=1))) * 1e3)}
    return truth
