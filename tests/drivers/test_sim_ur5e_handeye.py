"""The simulated hand-eye cell: its arm behaves as a UR controller does, its cameras render the boards where the
hidden truth puts them, and cv2.aruco finds their corners where they truly project."""

import math

import numpy as np
import pytest

from geometry import ur
from geometry.charuco import BoardDrawing

from drivers.interfaces import JointState, MotionRejected, Pose
from drivers.registry import DriverContext, backend_class
from drivers.sim.ur5e_handeye.world import drawing

from calibration.vision.charuco import find_corners

from cellctl.config import load_cell_file

from tests.conftest import ROOT

HOME = np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


@pytest.fixture(scope="module")
def cell():
    config, _ = load_cell_file(ROOT / "config" / "sim-ur5e-handeye.yaml")
    context = DriverContext(sim_config=config.sim)
    devices = {name: backend_class(kind, dev.backend).create(name, dev.options, context)
               for kind, name, dev in config.devices()}
    for d in devices.values():
        d.connect()
    return context.existing_world, devices


def test_the_true_arm_differs_from_the_table_within_its_budget(cell):
    world, _ = cell
    robot = world.config.robot
    for true, nominal in zip(world.true_arm.dh, ur.UR5E_DH):
        assert abs(true[0] - nominal[0]) <= robot.dh_length_error_mm * 1e-3
        assert abs(true[1] - nominal[1]) <= robot.dh_length_error_mm * 1e-3
    assert np.all(np.abs(np.degrees(world.true_arm.zero_offsets)) <= robot.joint_offset_error_deg)
    miss = np.linalg.norm(world.true_arm.flange(HOME)[:3, 3] - ur.forward(HOME)[:3, 3])
    assert 0 < miss < 1e-3  # off, by a fraction of a millimetre: a factory-calibrated arm


def test_the_arm_reports_its_nominal_kinematics_and_refuses_what_it_cannot_do(cell):
    world, devices = cell
    arm = devices["arm"]
    q = HOME + np.radians([10, 5, -5, 3, 4, 20])
    arm.move_joints(JointState(tuple(q)))
    pose = arm.pose()
    assert np.allclose(pose.xyz, ur.forward(q)[:3, 3], atol=1e-5)
    assert np.allclose(arm.joints().positions, q, atol=1e-5)
    T = ur.forward(q)
    T[:3, 3] += [0.02, -0.01, 0.03]
    w, x, y, z = pose.orientation
    arm.move_linear(Pose(*T[:3, 3], orientation=(w, x, y, z)))
    assert np.allclose(arm.pose().xyz, T[:3, 3], atol=1e-5)
    with pytest.raises(MotionRejected, match="out of reach"):
        arm.move_linear(Pose(2.0, 0.0, 0.5, orientation=(w, x, y, z)))
    with pytest.raises(MotionRejected, match=r"joint base=400.0000 deg is outside \[-360.0, 360.0\]"):
        arm.move_joints(JointState((math.radians(400), *HOME[1:])))
    with pytest.raises(MotionRejected, match="beyond the reach of 850 mm"):
        arm.move_joints(JointState((0.0,) * 6))  # stretched out level with the shoulder
    with pytest.raises(MotionRejected, match=r"z_mm=10.0000 is outside the workspace box \[30.0, 1000.0\]"):
        arm.move_linear(Pose(-0.5, -0.13, 0.01, orientation=(w, x, y, z)))
    assert np.allclose(arm.pose().xyz, T[:3, 3], atol=1e-5)  # nothing moved


@pytest.mark.parametrize("camera", ["wrist", "top"])
def test_the_corners_found_are_where_the_board_truly_projects(cell, camera):
    world, devices = cell
    devices["arm"].move_joints(JointState(tuple(HOME)))
    frame = devices[camera].capture()
    truth = world.frame_truth[(camera, frame.frame_id)]
    board = world.boards["table"]
    corners = find_corners(frame.image, drawing(board.config))
    ids, uv = truth.corners_px["table"]
    where = dict(zip(ids.tolist(), uv))
    errors = np.array([c - where[i] for i, c in zip(corners.ids, corners.uv)])
    assert len(corners) >= 60
    assert np.sqrt(np.mean(np.sum(errors ** 2, axis=1))) < 0.15  # px
    assert np.linalg.norm(errors.mean(axis=0)) < 0.05  # no bias from the rendering


def test_a_board_is_printed_off_its_drawing_by_its_hidden_scale(cell):
    world, _ = cell
    for board in world.boards.values():
        assert abs(board.scale - 1) <= board.config.scale_error_pct / 100
        assert board.scale != 1
        nominal = BoardDrawing(tuple(board.config.squares), board.config.square_mm * 1e-3,
                               board.config.marker_mm * 1e-3, board.config.dictionary, board.config.first_marker)
        assert np.allclose(board.true_corners(), nominal.corners() * board.scale)


def test_the_simulated_clock_counts_motion_settling_and_exposure(cell):
    world, devices = cell
    devices["arm"].move_joints(JointState(tuple(HOME)))
    start = world.clock.now()
    devices["arm"].move_joints(JointState(tuple(HOME + np.radians([30, 0, 0, 0, 0, 0]))))
    moved = world.clock.now() - start
    robot = world.config.robot
    assert moved == pytest.approx(30 / robot.speed_deg_s + robot.settle_s)
    devices["wrist"].capture()
    cam = world.config.cameras["wrist"]
    assert world.clock.now() - start - moved == pytest.approx((cam.exposure_ms + cam.readout_ms) * 1e-3)
