"""The simulated world: reproducible, realistic, and not an ideal mirror."""

import numpy as np
import pytest

from drivers.interfaces import (
    CaptureTimeout,
    ConnectionLost,
    CorruptFrame,
    MotionRejected,
    Pose,
)
from drivers.limits import WorkspaceBox
from drivers.sim.devices import SimArm, SimCamera, SimGripper
from drivers.sim.micro.world import World

BOX = WorkspaceBox(x_mm=(-10, 160), y_mm=(-10, 110), z_mm=(-5, 40))


def test_same_seed_same_truth_other_seed_other_truth(microcell_sim):
    a, b = World(microcell_sim), World(microcell_sim)
    c = World(microcell_sim.model_copy(update={"seed": 2}))
    assert a.cameras["cam1"].k1 == b.cameras["cam1"].k1
    np.testing.assert_array_equal(a.cameras["cam1"].R_cw, b.cameras["cam1"].R_cw)
    assert a.cameras["cam1"].k1 != c.cameras["cam1"].k1


@pytest.mark.parametrize("seed", range(6))
def test_camera1_budget(microcell_sim, seed):
    """Seed 001 cell, camera 1: 6.6 µm/px, 1-2° tilt, corners displaced 3-8 px by distortion."""
    world = World(microcell_sim.model_copy(update={"seed": seed}))
    cam = world.cameras["cam1"]
    corners = np.array([[0, 0], [2447, 0], [0, 2049], [2447, 2049]], float)
    x, y = cam.undistort(corners)
    ideal = np.column_stack([cam.fx * x + cam.cx, cam.fy * y + cam.cy])
    seen = np.column_stack([2447 - corners[:, 0], corners[:, 1]])  # camera 1 looks through a mirror
    shift = np.linalg.norm(ideal - seen, axis=1)
    assert 2.5 < shift.max() < 9.0
    tilt = np.degrees(np.arccos(abs(cam.R_cw[2, 2])))
    assert 1.0 <= tilt <= 2.0
    assert abs(np.hypot(cam.cx - 1223.5, cam.cy - 1024.5)) <= 5.0
    # spatial resolution at the focal plane
    p = cam.backproject_to_plane([[1224, 1025], [1225, 1025]], 0.0)
    assert np.linalg.norm(p[1] - p[0]) == pytest.approx(6.6e-6, rel=0.03)


def test_project_and_backproject_are_inverse(microcell_sim):
    cam = World(microcell_sim).cameras["cam1"]
    uv = np.array([[10.0, 20.0], [1224.0, 1025.0], [2400.0, 2000.0]])
    back = cam.project(cam.backproject_to_plane(uv, 0.0))
    np.testing.assert_allclose(back, uv, atol=1e-8)


def _arm(world):
    arm = SimArm("arm", world, SimArm.Settings(limits=BOX))
    arm.connect()
    return arm


def test_moves_take_time_and_report_commanded_pose(microcell_sim):
    world = World(microcell_sim)
    arm = _arm(world)
    t0 = world.clock.now()
    arm.move_linear(Pose(0.050, 0.030, 0.0))  # 20 mm down + 10 mm over from home (40, 30, 20)
    elapsed = world.clock.now() - t0
    distance = np.hypot(0.010, 0.020)
    assert elapsed > distance / 0.100 + 0.25  # at most 100 mm/s, plus settling
    reported = arm.pose()
    assert reported.x == pytest.approx(0.050, abs=0.051e-6)
    assert round(reported.x / 1e-7) * 1e-7 == pytest.approx(reported.x, abs=1e-12)  # quantised to 0.1 µm


def test_repeatability_matches_budget(microcell_sim):
    world = World(microcell_sim)
    arm = _arm(world)
    tips = []
    for k in range(600):
        world.begin_step(k)
        arm.move_linear(Pose(0.040, 0.030, 0.0))
        tips.append(world.arm.axis[:2].copy())
    sd = np.std(np.array(tips), axis=0) * 1e6
    assert sd == pytest.approx([1.7, 1.7], rel=0.15)


def test_noise_is_keyed_by_step(microcell_sim):
    """A run resumed from step k sees the same noise as an uninterrupted one."""
    a, b = World(microcell_sim), World(microcell_sim)
    for world, steps in ((a, [0, 1, 2]), (b, [2])):
        arm = _arm(world)
        for k in steps:
            world.begin_step(k)
            arm.move_linear(Pose(0.040, 0.030, 0.0))
    np.testing.assert_array_equal(a.arm.axis, b.arm.axis)


def test_target_outside_box_is_refused_before_moving(microcell_sim):
    world = World(microcell_sim)
    arm = _arm(world)
    before, t0 = arm.pose(), world.clock.now()
    with pytest.raises(MotionRejected, match="x_mm=200.0000 is outside the workspace box"):
        arm.move_linear(Pose(0.200, 0.030, 0.0))
    with pytest.raises(MotionRejected, match="not a finite number"):
        arm.move_linear(Pose(float("nan"), 0.030, 0.0))
    assert arm.pose() == before and world.clock.now() == t0
    arm.stop()
    arm.stop()  # idempotent


def test_pick_only_where_a_sphere_lies(microcell_sim):
    world = World(microcell_sim)
    arm, gripper = _arm(world), SimGripper("gripper", world, SimGripper.Settings())
    gripper.connect()
    lying = len(world.spheres)  # the supply's
    world.add_sphere(0.045, 0.030, 0.0, diameter=1e-3)
    arm.move_linear(Pose(0.040, 0.030, 1e-3))
    assert gripper.grip() is False and not gripper.status().object_detected
    arm.move_linear(Pose(0.045 + 68.7e-6, 0.030 - 137.2e-6, 1e-3))  # tip (not axis) over the sphere
    assert gripper.grip() is True and gripper.status().object_detected
    arm.move_linear(Pose(0.050, 0.030, 5e-3))
    assert np.hypot(*(world.held.centre[:2] - world.nozzle_tip()[:2])) < 20e-6  # auto-centred
    gripper.release()
    assert world.held is None and len(world.spheres) == lying + 1


def test_fault_knobs(microcell_sim):
    faults = {"arm_drop_after_moves": 2, "camera_timeout_after_captures": 1}
    world = World(microcell_sim.model_copy(update={"faults": microcell_sim.faults.model_copy(update=faults)}))
    arm = _arm(world)
    cam = SimCamera("cam1", world, SimCamera.Settings())
    cam.connect()
    arm.move_linear(Pose(0.040, 0.030, 0.0))
    arm.move_linear(Pose(0.041, 0.030, 0.0))
    with pytest.raises(ConnectionLost):
        arm.move_linear(Pose(0.042, 0.030, 0.0))
    with pytest.raises(ConnectionLost, match="reconnect"):
        arm.pose()
    assert cam.capture().image.shape == (2050, 2448)
    with pytest.raises(CaptureTimeout):
        cam.capture()

    world = World(microcell_sim.model_copy(update={"faults": microcell_sim.faults.model_copy(update={"corrupt_frame_every": 2})}))
    cam = SimCamera("cam1", world, SimCamera.Settings())
    cam.connect()
    cam.capture()
    with pytest.raises(CorruptFrame):
        cam.capture()


def test_frames_are_reproducible_and_noisy(microcell_sim):
    frames = []
    for _ in range(2):
        world = World(microcell_sim)
        arm = _arm(world)
        cam = SimCamera("cam1", world, SimCamera.Settings())
        cam.connect()
        world.begin_step(3)
        arm.move_linear(Pose(0.040, 0.030, 0.0))
        frames.append(cam.capture())
    np.testing.assert_array_equal(frames[0].image, frames[1].image)
    background = frames[0].image[:200, :200].astype(float)
    assert background.std() == pytest.approx(0.01 * 255, rel=0.2)  # 1 % of full scale
    assert frames[0].host_timestamp_s > 0


def test_unconnected_device_says_so(microcell_sim):
    arm = SimArm("arm", World(microcell_sim), SimArm.Settings(limits=BOX))
    with pytest.raises(Exception, match="not connected"):
        arm.pose()


def test_stop_cuts_a_real_time_move_short(microcell_sim):
    import threading

    from drivers.interfaces import MotionStopped

    motion = microcell_sim.motion.model_copy(update={"realtime_factor": 1.0, "settle_s": 0.0})
    world = World(microcell_sim.model_copy(update={"motion": motion}))
    arm = _arm(world)
    threading.Timer(0.05, arm.stop).start()
    with pytest.raises(MotionStopped):
        arm.move_linear(Pose(0.040, 0.030, -0.004))  # 24 mm down from home: ~0.34 s at 100 mm/s
    z = arm.pose().z
    assert -0.004 < z < 0.020  # part way
    arm.move_linear(Pose(0.040, 0.030, z))  # the arm still moves after a stop


def test_supply_refills_and_operator_lays_the_grid(microcell_sim):
    from drivers.sim.devices import SimOperator

    world = World(microcell_sim)
    arm, gripper = _arm(world), SimGripper("gripper", world, SimGripper.Settings())
    operator = SimOperator("operator", world, SimOperator.Settings())
    for d in (gripper, operator):
        d.connect()
    x, y = (v * 1e-3 for v in microcell_sim.supply.position_mm)
    arm.move_linear(Pose(x + 68.7e-6, y - 137.2e-6, 0.8e-3))  # onto the smallest sphere the tolerance allows
    assert gripper.grip()
    assert any(np.hypot(s.centre[0] - x, s.centre[1] - y) < 1e-4 for s in world.spheres)  # a new one is there
    cam = SimCamera("cam1", world, SimCamera.Settings())
    cam.connect()
    operator.request("lay the dot grid on area1", fixture="grid-area1", present=True)
    image = cam.capture().image
    assert np.median(image) > 150  # the white plate fills the view
    operator.request("remove the dot grid", fixture="grid-area1", present=False)
    assert np.median(cam.capture().image) < 50


def test_drift_moves_the_camera_and_the_nozzle_not_the_calibration(microcell_sim):
    """sim.drift: camera 1 moved so that its old view of T(p) is now where it sees p (T a similarity about its view
    centre), the nozzle's offset changed; both only once in force (from_cell_time_s)."""
    before = World(microcell_sim)
    drift = {"cam1": {"map_shift_um": [3.0, -1.0], "rotation_urad": 200.0, "scale_ppm": 100.0},
             "nozzle": {"offset_change_um": [5.0, 0.0], "from_cell_time_s": 10.0}}
    after = World(microcell_sim.model_validate(dict(microcell_sim.model_dump(), drift=drift)))
    c = np.array([40e-3, 30e-3, 0.0])  # camera 1's view centre (centre_mm, focus_z_mm)
    p = np.array([[41e-3, 31e-3, 0.0], [38e-3, 29e-3, 0.5e-3]])
    theta, s, t = 200e-6, 100e-6, np.array([3e-6, -1e-6, 0.0])
    turn = np.array([[np.cos(theta), -np.sin(theta), 0], [np.sin(theta), np.cos(theta), 0], [0, 0, 1]])
    T = c + (1 + s) * (p - c) @ turn.T + t
    np.testing.assert_allclose(after.camera_now("cam1").project(p), before.camera_now("cam1").project(T), atol=1e-9)
    np.testing.assert_array_equal(after.nozzle_tip(), before.nozzle_tip())  # not yet in force
    after.clock.advance(10.0)
    np.testing.assert_allclose(after.nozzle_tip() - before.nozzle_tip(), [5e-6, 0, 0], atol=1e-15)
    np.testing.assert_allclose(after.tip_offset(np.pi / 2) - before.tip_offset(np.pi / 2), [0, 5e-6], atol=1e-15)


def test_drift_of_an_unknown_camera_is_refused(microcell_sim):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="drift: no camera 'cam9' in sim.cameras"):
        microcell_sim.model_validate(dict(microcell_sim.model_dump(), drift={"cam9": {"map_shift_um": [1, 0]}}))
    with pytest.raises(ValidationError, match="cam1: map_shift: Extra inputs"):
        microcell_sim.model_validate(dict(microcell_sim.model_dump(), drift={"cam1": {"map_shift": [1, 0]}}))
