"""`iso9283` with `observe: fixed-cameras`: the pose test measured by the fixed cameras of an `arm` calibration (the
IRB 120 cell: two cameras 1.2 m away that watch the four-circle fixture). iso9283.py hands its plan, collection and
measurement over to this module; the standard's maths and its report stay there.

The instrument is the cameras of the active `arm` calibration (`arm-kinematics --param observe=fixed-cameras`):
that run calibrates both cameras together with the arm, in the frame its calibrated arm moves in, and stores the
fixture's drawing. No other calibration of these cameras exists on such a cell, and the ISO test has to command and
measure in one frame. So the test runs after `arm-kinematics`; "before" is the same test with `moves: controller`
(the arm as its controller moves it, the calibration's correction left out) and "after" with the calibration in
force (the `arm-acceptance-stereo` sequence runs both).

A visit: the approach, the linear move onto the pose, `frames` frames from every camera. In each frame the four
circles are found (calibration/vision/csm_markers.py, as arm-kinematics finds them); the fixture's pose is the one that
projects the drawing's circles onto them in every camera at once, through the calibration's lenses and poses, the
centre of each circle's image ellipse predicted as arm-kinematics predicts it (the ellipse's centre is not the
circle's: a few hundredths of a pixel, 10-20 µm here), each circle's centre the mean over the camera's frames (the
arm stands still: the sensor's noise, not the arm's, is averaged). It starts from the circles triangulated and the
drawing laid onto them. The arm's kinematics take no part: the measurement is the cameras'. The row's flange_*
columns are what the controller reports, the fixture frame on this cell.

Before anything moves the plan refuses, naming the pose: a pose (or its approach) the arm's controller refuses, or
one where a camera would not see every circle (through the calibration's cameras: inside the image by `margin_px`,
the plate at most `view_angle_deg` from face-on).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from drivers.interfaces import ChecksTargets, MotionRejected

from calibration.errors import CalibrationInputError, VisionError
from calibration.models import arm_kinematics_stereo as msk
from calibration.models import hand_eye as he
from calibration.routines.base import Devices
from calibration.routines.six_axis._arm_stereo import circle_centres, sees_fixture
from calibration.routines.six_axis.hand_eye import flange_target

TARGET = "arm"


def check_targets(params, calibrations: dict[str, dict]) -> dict:
    """The active `arm` calibration, if it can measure: made by fixed cameras, with the cameras asked for and the
    fixture's drawing; else CalibrationInputError saying what to run."""
    model = calibrations.get(TARGET)
    if model is None:
        raise CalibrationInputError("observe=fixed-cameras: no active calibration of 'arm'; iso9283 measures with "
                                    "the cameras arm-kinematics calibrates: run arm-kinematics --param "
                                    "observe=fixed-cameras first")
    if model.get("observe") != "fixed-cameras":
        raise CalibrationInputError(f"observe=fixed-cameras: the active arm calibration (id "
                                    f"{model.get('calibration_id')}) was made with observe={model.get('observe')!r}; "
                                    "it holds no fixed cameras to measure with")
    if "fixture" not in model:
        raise CalibrationInputError(f"observe=fixed-cameras: the active arm calibration (id "
                                    f"{model.get('calibration_id')}) keeps no fixture drawing (made before iso9283 "
                                    "measured by stereo); run arm-kinematics again")
    unknown = [c for c in params.cameras if c not in model["cameras"]]
    if len(set(params.cameras)) != len(params.cameras):
        raise CalibrationInputError(f"cameras: {', '.join(params.cameras)} names a camera twice; name each of "
                                    f"{', '.join(model['cameras'])} once")
    if unknown or len(params.cameras) < 2:
        raise CalibrationInputError(f"cameras: {', '.join(params.cameras)}; the arm calibration (id "
                                    f"{model.get('calibration_id')}) calibrated {', '.join(model['cameras'])}: name "
                                    "two or more of those")
    return model


def fixture_of(model: dict) -> msk.Fixture:
    """The drawing the calibration was made with; its mount is the controller's (unused: the cameras measure)."""
    f = model["fixture"]
    return msk.Fixture(np.eye(4), np.asarray(f["points_mm"], dtype=float) * 1e-3, f["diameter_mm"] * 0.5e-3)


def cameras_of(model: dict, names) -> list[msk.Camera]:
    return [msk.Camera.from_dict(n, model["cameras"][n]) for n in names]


# -- plan ------------------------------------------------------------------------------------------------------------
def check_plan(params, devices: Devices) -> None:
    """Every pose and its approach seen and reachable (module docstring), else CalibrationInputError naming it.
    Reach is the controller's own check (through the arm calibration when the moves go through it), made from where
    the arm stands when the run is planned; an arm that cannot check a target has each move checked as it is sent."""
    for name in params.cameras:
        devices.camera(name)  # an unknown camera, named, before anything else
    model = check_targets(params, devices.calibrations)
    cameras, fixture = cameras_of(model, params.cameras), fixture_of(model)
    view_angle = math.radians(params.view_angle_deg)
    for name, T in params.flange_poses().items():
        for what, F in ((name, T), (f"{name}'s approach", params.approach(T))):
            where = ", ".join(f"{v * 1e3:.1f}" for v in F[:3, 3])
            if not sees_fixture(cameras, fixture, F, view_angle, params.margin_px):
                raise CalibrationInputError(
                    f"{what}: the fixture at ({where}) mm would not show every circle to every camera "
                    f"({', '.join(params.cameras)}: inside the image by {params.margin_px:g} px, at most "
                    f"{params.view_angle_deg:g} deg from face-on), predicted through the arm calibration (id "
                    f"{model.get('calibration_id')}); move centre_mm toward where the cameras look, shrink cube_mm "
                    "or turn tool_rotation_deg to face them; nothing moved")
            if not isinstance(devices.arm, ChecksTargets):
                continue
            try:
                devices.arm.check_target(flange_target(F[:3, :3], F[:3, 3]))
            except MotionRejected as exc:
                why = str(exc).removesuffix("; nothing moved")
                raise CalibrationInputError(f"{what}: the fixture at ({where}) mm: {why}; move centre_mm or shrink "
                                            "cube_mm; nothing moved") from None


# -- collect ---------------------------------------------------------------------------------------------------------
def measure(params, devices: Devices) -> tuple[dict, list]:
    """One visit's frames and what they show: the fixture's pose (base frame, the calibration's) with the circles
    used and the reprojection RMS, or the reason it was not measured."""
    model = devices.calibration(TARGET, "iso9283")
    frames, uv, camera_of, point_of = [], [], [], []
    points = model["fixture"]["points_mm"]
    white, black = points[0][:2], [p[:2] for p in points[1:]]
    problems = []
    for c, name in enumerate(params.cameras):
        seen = []
        for _ in range(params.frames):
            frame = devices.camera(name).capture()
            frames.append(frame)
            try:
                seen.append(circle_centres(frame.image, white, black))
            except VisionError as exc:
                problems.append(f"{name} frame {frame.frame_id}: {exc}")
        if len(seen) < params.frames:
            continue
        for i, centre in enumerate(np.mean(seen, axis=0)):  # the sensor's noise down by sqrt(frames)
            uv.append(centre)
            camera_of.append(c)
            point_of.append(i)
    ids = ",".join(str(f.frame_id) for f in frames)
    if not problems:
        try:
            T, rms = fixture_pose(model, params.cameras, np.array(uv), np.array(camera_of), np.array(point_of))
            return {"frame_id": ids, "status": "ok", "corners": len(uv), "rms_px": rms, "pose": T}, frames
        except VisionError as exc:
            problems.append(str(exc))
    return {"frame_id": ids, "status": "refused", "message": "; ".join(problems)}, frames  # kept, with the reason


def fixture_pose(model: dict, names, uv: np.ndarray, camera_of: np.ndarray, point_of: np.ndarray,
                 centre_model: str | None = None) -> tuple[np.ndarray, float]:
    """T_base_fixture that projects the drawing's circles onto the centres `uv` (camera_of indexes `names`) through
    the calibration's cameras, and the RMS of what is left (px). `centre_model`: the calibration's by default."""
    cameras, fixture = cameras_of(model, names), fixture_of(model)
    centre_model = centre_model or model.get("centre_model", "point")
    obs = msk.Observations(["visit"], np.zeros((1, 6)), tuple(names), {}, np.zeros(len(uv), dtype=int), camera_of,
                           point_of, uv)
    X = msk.triangulate(cameras, obs)[0]
    seen = np.isfinite(X[:, 0])
    if seen.sum() < 3:
        raise VisionError(f"{int(seen.sum())} circles seen by two cameras or more: a pose needs 3")
    T0 = msk.rigid_fit(fixture.points[seen], X[seen])

    def residuals(p):
        T = he._perturbed(T0, p)
        out = np.empty_like(uv)
        for c, camera in enumerate(cameras):
            rows = np.flatnonzero(camera_of == c)
            poses = np.repeat((camera.T_camera_base @ T)[None], len(rows), axis=0)
            out[rows] = msk.image_centres(camera.lens, poses, fixture.points[point_of[rows]], fixture.radius,
                                          centre_model)
        return (out - uv).ravel()

    fit = least_squares(residuals, np.zeros(6), method="lm", x_scale=np.array([1e-3] * 3 + [1e-4] * 3))
    return he._perturbed(T0, fit.x), float(math.sqrt(np.mean(fit.fun ** 2)))

