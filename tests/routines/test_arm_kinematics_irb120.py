"""`arm-kinematics` with `observe: fixed-cameras` on the IRB 120 cell (config/sim-irb120-csm.yaml: links off by up to
0.5 mm, joint zeros by 0.05 deg, two uncalibrated cameras 1.2 m away watching the four-circle fixture): the arm,
the cameras and the fixture's mount in one adjustment, judged against the true arm over 50 configurations of the
working volume the fit never saw (cellctl/truth/arm_stereo.py)."""

from __future__ import annotations

import numpy as np
import pytest

from geometry.kinematic_table import nominal_table

from drivers.arms.abb.driver import AbbArm
from drivers.interfaces import Pose
from drivers.sim.servers import abb as abb_sim

from calibration.errors import CalibrationInputError
from calibration.models import arm_kinematics_stereo as msk
from calibration.routines.base import Step
from calibration.routines.six_axis import _arm_stereo as stereo
from calibration.routines.six_axis._arm_poses import Candidate
from calibration.routines.six_axis.arm_kinematics import ArmKinematics

from cellctl.config import load_cell_file
from cellctl.core.calibrated_arm import CalibratedArm
from cellctl.core.cell import Cell
from cellctl.core.runs import routine_params, run_routine, with_seed
from cellctl.stores.calibrations import CalibrationStore
from cellctl.truth.arm_stereo import triangulated

from tests.conftest import ROOT

pytestmark = pytest.mark.long

CELL = ROOT / "config" / "sim-irb120-csm.yaml"
ABB_CELL = ROOT / "config" / "sim-irb120-abb.yaml"
IMAGE = (1600, 1200)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    config, text = load_cell_file(CELL)
    return run_routine("arm-kinematics", config, text, tmp_path_factory.mktemp("arm-irb120") / "run", seed=0)


def params(**overrides):
    config, _ = load_cell_file(CELL)
    return routine_params(ArmKinematics(), config, overrides)


def test_the_arm_is_identified_and_holds_over_the_working_volume(run):
    """Issue 28's figures for this cell, judged in camera 1's frame (the cameras' poses absorb the gauge)."""
    t = run["truth"]
    assert t["position_error_after_max_mm"] <= 0.25
    assert t["position_error_before_mean_mm"] / t["position_error_after_mean_mm"] >= 5
    assert t["orientation_error_after_mean_deg"] <= 0.02
    assert t["position_error_sequential_mean_mm"] / t["position_error_after_mean_mm"] >= 1.5
    assert 0.5 <= t["error_over_sigma_median"] <= 2
    assert run["cell_time_s"] <= 300


@pytest.mark.xfail(strict=True, reason="camera 1's own frame is known only to about 0.1-0.4 mm at the fixture: its "
                   "principal point trades against its pose and decentring (correlation -1.00), an error common to "
                   "every pose (truth.position_offset_after_mm, 0.20 mm on seed 0; the fit's sigma "
                   "stats.calibration.position_sigma_in_cam1_mm, 0.10 mm), not the arm's: the measured frame below")
def test_the_mean_error_in_camera_1s_frame_meets_the_issue(run):
    assert run["truth"]["position_error_after_mean_mm"] <= 0.10


def test_as_the_calibrated_cameras_measure_it_and_in_the_arms_own_frame(run):
    """The same figures where camera 1's own frame does not count: the true fixture as the model's cameras
    triangulate it, and the model's arm laid rigidly onto the true one."""
    t = run["truth"]
    for frame in ("measured_", "arm_frame_"):
        assert t[f"{frame}position_error_after_mean_mm"] <= 0.10
        assert t[f"{frame}position_error_after_max_mm"] <= 0.25
        assert t[f"{frame}improvement"] >= 5
        assert t[f"{frame}orientation_error_after_mean_deg"] <= 0.02
        assert t[f"{frame}simultaneous_over_sequential"] >= 1.5
    # most of the error in camera 1's frame is common to every pose: camera 1's own frame
    assert t["position_offset_after_mm"] > 0.5 * t["position_error_after_mean_mm"]


def test_the_held_out_images_agree_with_the_simultaneous_model(run):
    v = run["stats"]["verification"]
    assert v["after"]["n"] == 8 and v["after"]["reprojection_rms_px"] < 0.1
    assert v["after"]["position_mean_mm"] < v["before"]["position_mean_mm"] / 5
    assert v["after"]["position_mean_mm"] < v["sequential"]["position_mean_mm"] / 1.5
    # the ellipse's centre is not the circle's: a few hundredths of a pixel, predicted by the model
    assert 0.005 < run["stats"]["calibration"]["ellipse_centre_shift_px"]["mean"] < 0.1


def test_the_report_names_what_it_fixed_and_what_absorbs_it(run):
    model = run["model"]
    assert model["observe"] == "fixed-cameras" and model["arm_model"] == "irb120"
    assert set(model["cameras"]) == {"cam1", "cam2"} and len(model["table"]["joints"]) == 6
    gauge = model["gauge"]
    # the base joint's zero and height move the whole arm, as moving both cameras does; after the last joint, all
    # is the fixture's mount
    assert {"theta_joint_1", "d_joint_1"} <= set(gauge["the cameras' poses"])
    assert {"theta_joint_6", "d_joint_6", "a_joint_6", "alpha_joint_6", "beta_joint_6"} <= set(
        gauge["the fixture's mount"])
    assert set(model["fixed"]) == {n for names in gauge.values() for n in names}
    assert {"a_joint_2", "a_joint_3", "d_joint_4", "theta_joint_2"} <= set(model["identified"])
    assert all(model["sigma"][k] > 0 for k in model["identified"])


def test_one_row_per_circle_per_camera_per_pose(run):
    assert run["n_samples"] == 48 * 2 * 4 and not run["rejected"]


def test_a_frame_without_the_fixture_is_kept_as_a_refused_row():
    config, text = load_cell_file(CELL)
    p = params()
    with Cell(with_seed(config, 0), text) as cell:
        # the tool pointing up: the plate faces the floor, no camera sees its circles
        step = Step(0, "pose", {"pose": "cal1", "set": "cal", "joints": list(np.radians([0, 0, 0, 0, -60, 0]))})
        rows = ArmKinematics().execute(step, p, cell.devices).rows
    assert [r["camera"] for r in rows] == ["cam1", "cam2"]
    assert all(r["status"] == "refused" and "expected 1 white and 3 black marks" in r["message"] for r in rows)
    assert all(r["j5_deg"] == pytest.approx(-60) for r in rows)


def test_a_region_no_camera_sees_is_refused_before_anything_moves():
    p = params(**ArmKinematics.small_params, aim_mm=(350, 0, -600))
    with pytest.raises(CalibrationInputError, match=r"the region gives only 0 reachable poses where every camera "
                                                     r"sees the fixture, fewer than the 27 asked for"):
        ArmKinematics().preview(p, IMAGE)


def test_poses_that_barely_move_the_arm_are_refused_naming_what_they_cannot_identify():
    """Only the last wrist turns: the rest of the arm cannot be told from the cameras' poses and the mount."""
    p = params(**ArmKinematics.small_params)
    table = nominal_table("irb120")
    region = stereo.region_of(p, IMAGE)
    q0 = stereo.candidates(region, p, 1, 0)[0].joints
    cands = [Candidate(q0 + np.r_[0, 0, 0, 0, 0, np.radians(a)], np.eye(4)) for a in range(-150, 151, 20)]
    free = np.array([n not in stereo.structural("irb120") for n in table.parameter_names()])
    J = stereo.pose_jacobians(cands, table, region, free)
    names = [n for n, f in zip(table.parameter_names(), free) if f]
    seen = stereo.plan_observability(J, names, 34, 2e-4)
    with pytest.raises(CalibrationInputError, match=r"cannot identify .*a_joint_2.*: the joints joint_1 \(0 deg\), "
                                                    r"joint_2 \(0 deg\).* turn less than 30 deg"):
        stereo.refuse_unidentifiable(seen, np.array([c.joints for c in cands]), table)


def test_fixed_cameras_refuse_an_arm_without_the_fixture_row():
    with pytest.raises(CalibrationInputError, match=r"arm_model='ur5e'; allowed: irb120"):
        ArmKinematics().preview(params(arm_model="ur5e"), IMAGE)


@pytest.mark.parametrize("driver", ["in-process", "abb"])
def test_moves_through_the_calibrated_arm_land_where_the_cameras_see_them(run, driver):
    """The run's calibration in force (cellctl/core/calibrated_arm.py), in-process and through the ABB socket driver:
    the same linear targets of the fixture frame, sent raw and through the calibration, judged by where the
    calibration's own cameras see the true fixture (what a camera-guided move misses by)."""
    model = dict(run["model"], calibration_id=1)
    m, fixture, p = msk.StereoModel.from_dict(model), params().fixture(), params()
    config, text = load_cell_file(CELL)
    with Cell(with_seed(config, 0), text) as cell:
        world, server = cell.sim_world, None
        arm = cell.arm
        if driver == "abb":
            options = load_cell_file(ABB_CELL)[0].arm.options
            server = abb_sim.start(world, "127.0.0.1", 0, logger_port=0, limits=options["limits"])
            arm = AbbArm.create("arm", {**options, "motion_port": server.motion_port, "logger_port": server.logger_port})
            arm.connect()
        try:
            # the fixture pointing down about the workspace centre the cameras aim at
            targets = [Pose(0.35 + dx, dy, 0.2 + dz, 0.3) for dx, dy, dz in
                       ((0.0, 0.0, 0.0), (0.08, -0.1, 0.05), (-0.06, 0.12, -0.04), (0.1, 0.08, 0.1))]
            misses = {}
            for name, moving in (("raw", arm), ("calibrated", CalibratedArm(arm, model))):
                misses[name] = []
                for target in targets:
                    moving.move_linear(target)
                    T_true = np.eye(4)
                    T_true[:3, :3], T_true[:3, 3] = world.fixture_rotation, world.fixture_translation
                    seen = triangulated(world, cell.devices, p, m.cameras, fixture, T_true[None])[0]
                    misses[name].append(float(np.linalg.norm(seen[:3, 3] - np.array(target.xyz)) * 1e3))
        finally:
            if server is not None:
                arm.close()
                server.close()
    assert np.mean(misses["raw"]) > 0.3
    assert np.mean(misses["calibrated"]) < 0.1 and np.mean(misses["calibrated"]) < np.mean(misses["raw"]) / 5


def test_csm_open_loop_through_the_calibrated_arm_needs_no_camera_iteration(run, tmp_path):
    """csm-positioning with open_loop: each target triangulated by the arm calibration's cameras and reached in one
    move through the calibrated arm, its error beside the closed-loop CSM's; without an arm calibration from fixed
    cameras it is refused before anything moves."""
    config, text = load_cell_file(CELL)
    small = {"open_loop": True, "n_targets": 5, "loops": ["white:w4"], "primary": "white:w4"}
    with pytest.raises(CalibrationInputError, match="csm-positioning needs an active calibration of 'arm'"):
        run_routine("csm-positioning", config, text, tmp_path / "refused", seed=0,
                    store=CalibrationStore(tmp_path / "empty"), overrides=small)
    assert not (tmp_path / "refused" / "samples.csv").exists()
    store = CalibrationStore(tmp_path / "store")
    saved = store.save("arm", run, text, run_dir=tmp_path)
    result = run_routine("csm-positioning", config, text, tmp_path / "csm", seed=0, store=store, overrides=small)
    assert result["arm_calibration"] == saved.id
    t = result["truth"]
    assert t["open_loop_physical"]["n"] == 5 and t["open_loop_physical"]["camera_iterations"] == 0
    assert t["open_loop_physical"]["mean_mm"] <= 0.1
    assert result["stats"]["open_loop"]["open loop"]["n"] == 5
    assert "Open loop through the calibrated arm" in (tmp_path / "csm" / "report.md").read_text()
