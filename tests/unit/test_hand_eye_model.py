"""The hand-eye adjustment on synthetic images and pose pairs (no simulator): accurate, better than OpenCV's
closed forms on the same data, honest about outliers, and refusing motion that cannot identify X."""

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.charuco import BoardDrawing

from calibration.errors import CalibrationInputError
from calibration.models import hand_eye as he

BOARD = he.Board(BoardDrawing((12, 9), 0.02, 0.015).corners())
LENS = he.Intrinsics(2448, 2048, 2330.0, 2328.0, 1230.0, 1017.0, (-0.08, 0.12, 4e-4, -3e-4, -0.05))


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


X_TRUE = _T(np.radians([0.8, -0.5, 1.2]), [0.0012, 0.0508, 0.0647])  # flange -> camera, about 82 mm out
Y_TRUE = _T([math.pi, 0, 0.03], [-0.62, -0.04, 0.001])  # base -> board, the print facing up


def _flanges(n, rng, tilt_deg=30.0, roll_deg=45.0):
    """Flange poses whose camera looks at the board's centre from 300-400 mm, tilted and turned."""
    centre = Y_TRUE @ np.r_[0.12, 0.09, 0.0, 1.0]
    out = []
    for _ in range(n):
        tilt, azimuth = math.radians(tilt_deg) * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
        up = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)])
        z = -up
        x = np.cross([0, 0, 1.0], z) if abs(z[2]) < 0.999 else np.array([1.0, 0, 0])
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(z, x), z]) @ Rotation.from_euler("z", rng.uniform(-1, 1) * math.radians(roll_deg)).as_matrix()
        T_base_camera = np.eye(4)
        T_base_camera[:3, :3] = R
        T_base_camera[:3, 3] = centre[:3] + rng.uniform(0.30, 0.40) * up + rng.normal(0, 0.02, 3) * [1, 1, 0]
        out.append(T_base_camera @ np.linalg.inv(X_TRUE))
    return out


def _views(rng, n=15, arm_mm=0.0, noise_px=0.05):
    """Views of the board: projected by the true camera from the true flange (the reported one moved by the arm's
    error), with pixel noise; the flange pose each view carries is the reported one."""
    views = []
    for k, F in enumerate(_flanges(n, rng)):
        D = _T(rng.normal(0, math.radians(0.01) * arm_mm / 0.1, 3), rng.normal(0, arm_mm * 1e-3, 3))
        T_cb = np.linalg.inv(F @ D @ X_TRUE) @ Y_TRUE
        rvec = cv2.Rodrigues(T_cb[:3, :3])[0]
        uv = cv2.projectPoints(BOARD.corners, rvec, T_cb[:3, 3], LENS.K(), np.asarray(LENS.dist))[0].reshape(-1, 2)
        keep = (uv[:, 0] > 0) & (uv[:, 0] < 2447) & (uv[:, 1] > 0) & (uv[:, 1] < 2047) & (rng.uniform(size=len(uv)) > 0.05)
        ids = np.flatnonzero(keep)
        views.append(he.View(f"p{k + 1:02d}", F, ids, uv[ids] + rng.normal(0, noise_px, (len(ids), 2))))
    return views


def _first_lens(views):
    objects = [BOARD.corners[v.ids].astype(np.float32) for v in views]
    _, K, dist, _, _ = cv2.calibrateCamera(objects, [v.uv.astype(np.float32) for v in views], (2448, 2048), None, None)
    return he.Intrinsics(2448, 2048, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(dist.ravel()[:5]))


def _pnp(views, lens):
    out = []
    for v in views:
        _, rvec, tvec = cv2.solvePnP(BOARD.corners[v.ids], v.uv, lens.K(), np.asarray(lens.dist))
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        out.append(T)
    return out


def test_the_simultaneous_fit_finds_x_better_than_the_closed_forms_on_the_same_images():
    ours, theirs = [], {}
    for seed in range(4):
        views = _views(np.random.default_rng(seed))
        lens0 = _first_lens(views)
        result = he.fit_views(views, BOARD, "eye-in-hand", lens0)
        t, r = he.transform_error(result.X, X_TRUE)
        assert t < 0.02e-3 and math.degrees(r) < 0.005
        assert he.transform_error(result.Y, Y_TRUE)[0] < 0.05e-3
        assert result.rms_px < 0.1 and not result.rejected
        ours.append(t)
        baselines = he.opencv_baselines([v.T_base_flange for v in views], _pnp(views, lens0), "eye-in-hand")
        assert len(baselines) == 7
        for name, b in baselines.items():
            theirs.setdefault(name, []).append(he.transform_error(b["X"], X_TRUE)[0] if b["X"] is not None else 1.0)
    best = min(np.median(v) for v in theirs.values())
    assert np.median(ours) * 1.5 <= best  # the chain's first intrinsics and PnP depth errors stay in its X


def test_an_arm_that_errs_widens_the_reported_uncertainty_and_the_bound_still_holds():
    covered, ratios = 0, []
    for seed in range(4):
        views = _views(np.random.default_rng(10 + seed), n=12, arm_mm=0.1)
        result = he.fit_views(views, BOARD, "eye-in-hand", _first_lens(views), arm_accuracy=(0.0, 0.0))
        t, _ = he.transform_error(result.X, X_TRUE)
        covered += t <= result.bound95_X_translation_m
        ratios.append(t / np.linalg.norm(result.sigma_X_translation_m))
        assert result.noise["arm_mm"] > 0.02  # the variance components see the arm's error
    assert covered >= 3
    assert 0.3 < np.median(ratios) < 2.0


def test_a_view_whose_robot_pose_is_wrong_is_dropped_with_the_reason():
    views = _views(np.random.default_rng(5))
    views[4].T_base_flange = views[4].T_base_flange @ _T([0, 0, 0], [0.005, 0, 0])  # recorded while moving
    result = he.fit_views(views, BOARD, "eye-in-hand", _first_lens(views))
    assert [r["pose"] for r in result.rejected] == ["p05"]
    assert "off by" in result.rejected[0]["reason"] and "mm" in result.rejected[0]["reason"]
    assert he.transform_error(result.X, X_TRUE)[0] < 0.03e-3


def test_motion_about_one_axis_or_too_small_is_refused_naming_what_to_add():
    F0 = _flanges(1, np.random.default_rng(0))[0]
    about_z = [F0 @ _T([0, 0, math.radians(a)], [0.01 * k, 0, 0]) for k, a in enumerate((0, 20, 40, 60, 80))]
    with pytest.raises(CalibrationInputError, match=r"rotation axes span one direction: the poses rotate about "
                                                    r"~\(0.00, 0.00, 1.00\) in the flange frame .* add poses tilted "
                                                    r"about \(.*\), \(.*\) of the flange"):
        he.check_motion(about_z)
    tiny = [F0 @ _T(np.radians([0.5 * k, -0.3 * k, 0.2 * k]), [0.01 * k, 0, 0]) for k in range(5)]
    with pytest.raises(CalibrationInputError, match=r"rotations too small: the largest between two poses is "
                                                    r"[0-9.]+ deg .* tilt the tool by at least 5 deg"):
        he.check_motion(tiny)
    views = _views(np.random.default_rng(0), n=5)
    for v, F in zip(views, about_z):
        v.T_base_flange = F
    with pytest.raises(CalibrationInputError, match="rotation axes span one direction"):
        he.fit_views(views, BOARD, "eye-in-hand", LENS)
    with pytest.raises(CalibrationInputError, match="rotation axes span one direction"):
        he.fit_pose_pairs(about_z, [np.eye(4)] * 5, "eye-in-hand")
    spread = he.check_motion(_flanges(15, np.random.default_rng(1)))
    assert 0.1 < spread["spread"] <= 1 and spread["max_angle_deg"] > 20


def _pairs(rng, n=15, mm=0.05, deg=0.02):
    flanges = _flanges(n, rng)
    measured = []
    for F in flanges:
        T = np.linalg.inv(F @ X_TRUE) @ Y_TRUE
        measured.append(_T(rng.normal(0, math.radians(deg), 3), rng.normal(0, mm * 1e-3, 3)) @ T)
    return flanges, measured


def test_pose_pairs_alone_fit_no_worse_than_the_best_closed_form_and_drop_a_bad_pair():
    ours, theirs = [], {}
    for seed in range(5):
        flanges, measured = _pairs(np.random.default_rng(40 + seed))
        result = he.fit_pose_pairs(flanges, measured, "eye-in-hand")
        ours.append(he.transform_error(result.X, X_TRUE)[0])
        assert result.intrinsics is None and np.all(result.sigma_X_translation_m > 0)
        for name, b in he.opencv_baselines(flanges, measured, "eye-in-hand").items():
            theirs.setdefault(name, []).append(he.transform_error(b["X"], X_TRUE)[0] if b["X"] is not None else 1.0)
    assert np.median(ours) <= min(np.median(v) for v in theirs.values())
    measured[6] = _T([0, 0, 0], [0.004, 0, 0]) @ measured[6]
    result = he.fit_pose_pairs(flanges, measured, "eye-in-hand")
    assert [r["pose"] for r in result.rejected] == ["pair 7"]
    assert "off the others by 4.0" in result.rejected[0]["reason"]
    assert he.transform_error(result.X, X_TRUE)[0] < 0.15e-3


def test_eye_to_hand_pairs_are_read_the_other_way_round():
    rng = np.random.default_rng(3)
    T_flange_board = _T(np.radians([180, 0, 5]), [0.0, -0.06, 0.035])
    T_base_camera = _T([math.pi, 0, 0], [-0.5, -0.13, 1.0])
    flanges = [T_base_camera @ _T(rng.normal(0, 0.3, 3), [rng.normal(0, 0.05), rng.normal(0, 0.05), 0.5])
               @ np.linalg.inv(T_flange_board) for _ in range(12)]
    measured = [np.linalg.inv(T_base_camera) @ F @ T_flange_board for F in flanges]
    result = he.fit_pose_pairs(flanges, measured, "eye-to-hand")
    assert he.transform_error(result.X, T_flange_board)[0] < 1e-6
    assert he.transform_error(result.Y, T_base_camera)[0] < 1e-6
    exact = [name for name, b in he.opencv_baselines(flanges, measured, "eye-to-hand").items()
             if b["X"] is not None and he.transform_error(b["X"], T_flange_board)[0] < 1e-6]
    assert set(exact) >= {"PARK", "HORAUD", "ANDREFF", "DANIILIDIS", "SHAH", "LI"}  # OpenCV's TSAI misses here


def test_a_pose_is_refused_when_it_is_not_one():
    good = he.pose_to_dict(X_TRUE)
    assert np.allclose(he.pose_from_dict(good), X_TRUE, atol=1e-12) and good["qw"] >= 0
    with pytest.raises(CalibrationInputError, match=r"the quaternion \(qw, qx, qy, qz\) has length 1\.00000\d+, not 1 \(within 1e-6\)"):
        he.pose_from_dict(dict(good, qw=good["qw"] + 1e-5))
    with pytest.raises(CalibrationInputError, match="y_mm=nan is not a finite number"):
        he.pose_from_dict(dict(good, y_mm=float("nan")))
    with pytest.raises(CalibrationInputError, match="qz is missing"):
        he.pose_from_dict({k: v for k, v in good.items() if k != "qz"})
    with pytest.raises(CalibrationInputError, match="mount='eye-on-hand'; allowed: eye-in-hand, eye-to-hand"):
        he.fit_pose_pairs([np.eye(4)] * 3, [np.eye(4)] * 3, "eye-on-hand")
