"""CSM model (seed 002 section III): view parameters, flattening, 3D target, weights, IK, mark detection."""

import numpy as np
import pinocchio as pin
import pytest

from calibration.errors import CalibrationInputError, VisionError
from calibration.models import csm
from calibration.models.irb120 import Fixture, Kinematics
from calibration.vision.csm_markers import Marks, find_marks, label_fixture
from drivers.interfaces import JointState, MotionRejected, Pose
from drivers.registry import DriverContext, backend_class
from drivers.sim.kinds import build_world
from drivers.sim.six_axis.config import SixAxisCamera
from drivers.sim.six_axis.world import draw_camera
from tests.drivers.contract import ArmContract

AIM = np.array([0.35, 0.0, 0.2])
FIXTURE = Fixture((0.04, 0.0), {"white": (0, 0, 0), "black1": (0.04, 0, 0), "black2": (0.055, 0.015, 0),
                                "black3": (0.055, -0.015, 0)})


def perspective_cameras(seed=1, distortion=(0.0, 0.0)):
    rng = np.random.default_rng(seed)
    return [draw_camera(SixAxisCamera(azimuth_deg=a, corner_distortion_px=distortion), AIM, rng) for a in (-45, 45)]


def test_view_parameters_recovered_from_an_orthographic_camera():
    rng = np.random.default_rng(0)
    C_true = np.array([0.3, 0.5, -0.2, 0.7, 800.0, 600.0]) * np.array([30, 30, 30, 30, 1, 1])
    points = AIM + rng.uniform(-0.1, 0.1, (25, 3))
    uv = csm.project(C_true, points)
    C = csm.fit_view(points, uv, np.ones(25), csm.initial_view(points, uv))
    C *= np.sign(C[0])  # C and -C are the same camera (the model is quadratic in C1..C4)
    assert C == pytest.approx(C_true, rel=1e-8)
    M, r3 = csm.view_rows(C)
    assert np.cross(M[0], M[1]) / np.linalg.norm(np.cross(M[0], M[1])) == pytest.approx(r3, abs=1e-9)


@pytest.mark.parametrize("fit_depth", [False, True])
def test_flattening_recovers_a_perspective_camera(fit_depth):
    cams = perspective_cameras()
    rng = np.random.default_rng(2)
    target = AIM + np.array([0.02, -0.03, 0.01])
    points = target + rng.uniform(-0.1, 0.1, (30, 3))
    samples = [csm.CameraSamples(points, c.project(points), np.array([(c.width - 1) / 2, (c.height - 1) / 2]), 1.2)
               for c in cams]
    target_uv = [c.project(target)[0] for c in cams]
    flat = csm.estimate(samples, target_uv, "equal", fit_depth=fit_depth)
    unflattened = csm.solve_target([csm.fit_view(s.points, s.uv, np.ones(30), csm.initial_view(s.points, s.uv))
                                    for s in samples], target_uv)
    err_flat = np.linalg.norm(flat.target - target) * 1e3
    err_plain = np.linalg.norm(unflattened - target) * 1e3
    assert err_plain > 0.3  # perspective the orthographic model cannot take
    assert err_flat < (0.02 if fit_depth else 0.05) < err_plain / 10
    if fit_depth:  # the fitted flattening depth is the camera's distance to the target
        for cam, z in zip(cams, flat.depths):
            assert z == pytest.approx(cam.depth_of(target), abs=2e-3)


def test_weights_follow_eqs_12_to_15():
    d = np.array([0.05, 1.0, 2.0, 10.0])
    assert csm.weights("equal", 3, d) == pytest.approx(np.ones(4))
    dis = np.maximum(d, csm.MIN_DISTANCE_MM)
    assert csm.weights("reciprocal", 3, d) == pytest.approx(1 / dis)
    assert csm.weights("w1", 3, d) == pytest.approx(3 / dis)
    assert csm.weights("w2", 3, d) == pytest.approx(3 + 1 / dis)
    assert csm.weights("w3", 3, d) == pytest.approx(dis ** -3.0)
    assert csm.weights("w4", 3, d) == pytest.approx(3 * dis ** -3.0)
    with pytest.raises(CalibrationInputError, match="allowed: equal"):
        csm.weights("w5", 1, d)


def test_weights_favour_local_samples_under_lens_distortion():
    """With distortion the global orthographic model is wrong; ω4 with k = 3 locates a target among
    nearby samples better than equal weights."""
    cams = perspective_cameras(3, distortion=(40.0, 40.0))
    rng = np.random.default_rng(4)
    target = AIM + np.array([0.05, 0.05, 0.0])
    far = AIM + rng.uniform(-0.15, 0.15, (20, 3))
    near = target + rng.uniform(-0.005, 0.005, (6, 3))
    points = np.vstack([far, near])
    samples = [csm.CameraSamples(points, c.project(points), np.array([(c.width - 1) / 2, (c.height - 1) / 2]), 1.2)
               for c in cams]
    target_uv = [c.project(target)[0] for c in cams]
    equal = np.linalg.norm(csm.estimate(samples, target_uv, "equal").target - target)
    weighted = np.linalg.norm(csm.estimate(samples, target_uv, "w4", 3).target - target)
    assert weighted < equal / 3


def test_inverse_kinematics_reaches_the_point_within_limits_moving_joints_1_to_3():
    kin = Kinematics.nominal(FIXTURE)
    q0 = np.radians([5, 15, 5, 10, 70, -20])
    goal = kin.point(q0, "white") + [0.03, -0.02, 0.04]
    q = kin.solve_point("white", goal, q0, active=(0, 1, 2))
    assert np.linalg.norm(kin.point(q, "white") - goal) < 1e-9
    assert q[3:] == pytest.approx(q0[3:], abs=0)
    assert kin.within_limits(q)
    # an unreachable point: the solution stays inside the limits (joint 3 upper limit 70 deg)
    far = kin.solve_point("white", [2.0, 0.0, 0.3], q0, active=(0, 1, 2))
    assert kin.within_limits(far)
    pose = kin.placement(q0)
    q_pose = kin.solve_pose(pin.SE3(pose.rotation, pose.translation + [0.05, 0, 0]), q0)
    assert kin.placement(q_pose).translation == pytest.approx(pose.translation + [0.05, 0, 0], abs=1e-9)


def test_marks_found_by_both_detectors_near_the_true_centres():
    from cellctl.config import load_cell_file
    from tests.conftest import ROOT

    cfg, _ = load_cell_file(ROOT / "config" / "sim-irb120-csm.yaml")
    world = build_world(cfg.sim)
    kin = Kinematics.nominal(FIXTURE)
    q = kin.solve_pose(pin.SE3(pin.utils.rotate("x", np.pi), np.array([0.35, 0.02, 0.22])), np.radians([0, 10, 10, 0, 70, 0]))
    world.begin_step(0)
    world.move_joints(q)
    image = world.capture("cam1", 1)
    truth = world.frame_truth[("cam1", 1)].features_px
    f = cfg.sim.fixture
    for method in ("contour", "dld"):
        named = label_fixture(find_marks(image, method), np.asarray(f.white_mm[:2]),
                              np.asarray([b[:2] for b in f.black_mm]))
        for name, uv in named.items():
            assert np.hypot(*(uv - truth[name])) < 0.15, (method, name)
    with pytest.raises(VisionError, match="expected 1 white and 3 black"):
        label_fixture(Marks(np.zeros((2, 2)), np.zeros((1, 2))), [0, 0], np.zeros((3, 2)))
    with pytest.raises(VisionError, match="allowed: contour, dld"):
        find_marks(image, "hough")


def _six_axis_cell():
    from cellctl.config import load_cell_file
    from tests.conftest import ROOT

    return load_cell_file(ROOT / "config" / "sim-irb120-csm.yaml")[0]


class TestSimSixAxisArm(ArmContract):
    """The in-process IRB 120 fake (backend sim-irb120) keeps the Arm contract."""

    reachable = Pose(0.35, 0.0, 0.25, 0.0)

    @pytest.fixture
    def make_device(self):
        cfg = _six_axis_cell()
        context = DriverContext(sim_config=cfg.sim)
        return lambda: backend_class("arm", "sim-irb120").create("arm", cfg.arm.options, context)


def test_six_axis_arm_joint_moves_limits_and_reported_pose():
    cfg = _six_axis_cell()
    arm = backend_class("arm", "sim-irb120").create("arm", cfg.arm.options, DriverContext(sim_config=cfg.sim))
    arm.connect()
    q = np.radians([5, 15, 5, 10, 70, -20])
    arm.move_joints(JointState(tuple(q)))
    assert arm.joints().positions == pytest.approx(tuple(q), abs=1e-6)
    world = arm.world
    _, t_true = world.true_arm.fixture_pose(q)
    # the controller reports its nominal kinematics; the fixture really is elsewhere (hidden DH errors)
    assert 1e-5 < np.linalg.norm(arm.pose().xyz - t_true) < 3e-3
    with pytest.raises(MotionRejected, match="joint_3=80.0000 deg is outside"):
        arm.move_joints(JointState(tuple(np.radians([0, 0, 80, 0, 0, 0]))))
    with pytest.raises(MotionRejected, match="expects 6 joints"):
        arm.move_joints(JointState((0.0, 0.0, 0.0, 0.0)))
    arm.close()
