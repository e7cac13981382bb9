"""`arm-kinematics` on the uncalibrated UR5e cell (config/sim-ur5e-uncalibrated.yaml: links off by up to 1 mm, joint
zeros by 0.1 deg): the wrist camera's views of the table board identify the arm, judged against the true arm over
50 configurations of the working volume the fit never saw (cellctl/truth/arm.py)."""

from __future__ import annotations

import numpy as np
import pytest

from geometry.kinematic_table import nominal_table
from geometry.transforms import inverse

from drivers.interfaces import MotionRejected, Pose
from drivers.sim.kinds import build_world

from calibration.errors import CalibrationInputError
from calibration.models.hand_eye import pose_from_dict
from calibration.routines.six_axis._arm_poses import Candidate, pose_jacobians
from calibration.routines.six_axis.arm_kinematics import ArmKinematics, _plan_observability, _refuse_unidentifiable

from cellctl.config import load_cell_file
from cellctl.core.calibrated_arm import CalibratedArm, matrix_of_pose
from cellctl.core.cell import Cell
from cellctl.core.runs import run_routine, run_sequence, with_seed
from cellctl.stores.calibrations import CalibrationStore

from tests.conftest import ROOT

pytestmark = pytest.mark.long

CELL = ROOT / "config" / "sim-ur5e-uncalibrated.yaml"


def caliper_scale(config, seed: int) -> float:
    """The board's print as an engineer measures it: a caliper across its 240 mm, read to 0.01 mm, within 0.02 mm
    (the simulation reads the true print, as the caliper reads the real one; tools/arm_kinematics_figures.py)."""
    world = build_world(config.sim.model_copy(update={"seed": seed}))
    board = next(b for b in world.boards.values() if b.config.mount == "table")
    reading = round(240.0 * board.scale + np.random.default_rng([seed, 28]).uniform(-0.02, 0.02), 2)
    return reading / 240.0


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    config, text = load_cell_file(CELL)
    return run_routine("arm-kinematics", config, text, tmp_path_factory.mktemp("arm") / "run", seed=0,
                       overrides=dict(ArmKinematics.small_params, board_scale=caliper_scale(config, 0),
                                      board_scale_sigma_pct=0.005))


def test_the_arm_is_identified_and_holds_over_the_working_volume(run):
    t = run["truth"]
    assert t["position_error_before_mean_mm"] > 1.0  # an uncalibrated arm, a hand-eye calibration alone
    # the length reference is the board's print, measured: its scale error sets the floor
    assert t["position_error_after_mean_mm"] < 0.15
    assert t["position_error_before_mean_mm"] / t["position_error_after_mean_mm"] > 5
    assert t["orientation_error_after_mean_deg"] < 0.02
    assert t["position_error_sequential_mean_mm"] > 0  # the usual chain, reported beside (not better here: see notes)
    v = run["stats"]["verification"]
    assert v["after"]["position_mean_mm"] < v["before"]["position_mean_mm"] / 5  # what the held-out images say


def test_the_report_names_what_it_fixed_and_the_model_is_a_table(run):
    model = run["model"]
    assert model["arm_model"] == "ur5e" and len(model["table"]["joints"]) == 6
    # the base joint's zero moves the whole arm as the board's pose does; after the last joint, all is the camera's
    assert {"theta_base", "d_base", "theta_wrist3", "d_wrist3"} <= set(model["fixed"])
    assert {"a_shoulder", "a_elbow", "theta_shoulder"} <= set(model["identified"])
    assert all(model["sigma"][k] > 0 for k in model["identified"])


def test_a_region_too_small_is_refused_before_anything_moves():
    routine = ArmKinematics()
    params = routine.Params(**dict(ArmKinematics.small_params, radius_mm=0, tilt_deg=0, standoff_mm=(350, 351),
                                   candidates=20))
    with pytest.raises(CalibrationInputError, match="the region gives only 20 reachable poses .* fewer than the 27"):
        routine.pose_plan(params, (2448, 2048))


def test_poses_that_barely_move_the_arm_are_refused_naming_what_they_cannot_identify():
    """Only the last wrist turns: the rest of the arm cannot be told from the board's pose."""
    routine = ArmKinematics()
    params = routine.Params(**ArmKinematics.small_params)
    table = nominal_table("ur5e")
    region = routine._region(params, (2448, 2048))
    home = np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
    cands = [Candidate(home + np.r_[0, 0, 0, 0, 0, np.radians(a)], np.eye(4)) for a in range(-150, 151, 20)]
    structural = routine._structural(params, (2448, 2048))
    free = np.array([n not in structural for n in table.parameter_names()])
    J = pose_jacobians(cands, table, region, free)
    with pytest.raises(CalibrationInputError, match=r"cannot identify .*a_shoulder.*: the joints base \(0 deg\), "
                                                    r"shoulder \(0 deg\).* turn less than 30 deg"):
        _refuse_unidentifiable(_plan_observability(J, table, 2e-4, free), structural,
                               np.array([c.joints for c in cands]), table)


def through_ur_rtde(folder):
    """The uncalibrated cell with its UR5e driven by the real UR driver, ur-rtde against the UR simulator on a loopback
    address of this module's own."""
    path = folder / "uncalibrated-ur.yaml"
    path.write_text(f"extends: {CELL}\narm: {{backend: ur, host: 127.0.0.37}}\n"
                    "sim: {servers: [{protocol: ur, host: 127.0.0.37}]}\n")
    return path


@pytest.mark.parametrize("driver", ["in-process", "ur-rtde"])
def test_moves_through_the_calibrated_arm_land_where_they_were_asked(run, driver, tmp_path):
    """The run's calibration in force (cellctl/core/calibrated_arm.py): the same linear targets, sent through the
    raw driver and through the calibration, judged in the calibration's cell frame by where the camera truly is;
    in-process and through ur-rtde alike (the correction sits above any driver)."""
    config, text = load_cell_file(CELL if driver == "in-process" else through_ur_rtde(tmp_path))
    model = dict(run["model"], calibration_id=1)
    X, Y = pose_from_dict(model["tool"]), pose_from_dict(model["world"])
    with Cell(with_seed(config, 0), text) as cell:
        assert (type(cell.arm).__name__ == "UrArm") == (driver == "ur-rtde")
        world = cell.sim_world
        X_true, Y_true = world.cameras["wrist"].mount, next(b for b in world.boards.values() if b.config.mount == "table").pose
        targets = [cell.arm.pose()]
        for dx, dy, dz in ((0.1, 0.05, -0.1), (-0.12, 0.2, 0.05), (0.05, -0.15, 0.12)):
            p = targets[0]
            targets.append(Pose(p.x + dx, p.y + dy, p.z + dz, p.alpha, p.orientation))
        misses = {}
        for name, arm in (("raw", cell.arm), ("calibrated", CalibratedArm(cell.arm, model))):
            misses[name] = []
            for target in targets:
                arm.move_linear(target)
                truly = Y @ inverse(Y_true) @ world.flange @ X_true  # the camera, in the calibration's frame
                misses[name].append(np.linalg.norm(truly[:3, 3] - (matrix_of_pose(target) @ X)[:3, 3]) * 1e3)
                assert arm.pose().xyz == pytest.approx(target.xyz, abs=1e-6) if name == "calibrated" else True
    assert np.mean(misses["raw"]) > 1.0
    assert np.mean(misses["calibrated"]) < 0.3 and np.mean(misses["calibrated"]) < np.mean(misses["raw"]) / 5


def test_a_calibrated_target_outside_the_limits_is_refused_before_anything_moves(run):
    config, text = load_cell_file(CELL)
    model = dict(run["model"], table=dict(run["model"]["table"]), calibration_id=1)
    model["table"]["joints"] = [dict(j, limits_deg=[-1.0, 1.0]) if j["name"] == "wrist3" else j
                                for j in model["table"]["joints"]]
    with Cell(with_seed(config, 0), text) as cell:
        arm = CalibratedArm(cell.arm, model)
        start, moves = cell.arm.joints().positions, len(cell.sim_world.moves)
        p = cell.arm.pose()
        turned = Pose(p.x, p.y, p.z, p.alpha + 0.5)
        with pytest.raises(MotionRejected, match=r"through the calibrated arm \(calibration 1\): .*joint wrist3=.* "
                                                 r"outside its limits .*nothing moved"):
            arm.move_linear(turned)
        assert cell.arm.joints().positions == start and len(cell.sim_world.moves) == moves


def test_a_later_job_moves_through_the_active_arm_calibration_and_says_so(run, tmp_path):
    """Stored and active, the arm calibration is in force for the next job (here the hand-eye routine, whose flange
    poses are then the calibrated arm's), and its report names it."""
    config, text = load_cell_file(CELL)
    store = CalibrationStore(tmp_path / "store")
    saved = store.save("arm", run, text, run_dir=tmp_path)
    result = run_routine("hand-eye", config, text, tmp_path / "he", seed=0, store=store,
                         overrides={"poses": 6, "verify_poses": 1, "touches": 0})
    assert result["arm_calibration"] == saved.id
    assert f"through the arm calibration {saved.id}" in (tmp_path / "he" / "report.md").read_text()


def test_the_arm_acceptance_sequence_shows_iso_9283_before_and_after(tmp_path):
    """hand-eye, iso9283, arm-kinematics, iso9283 as one job (six_axis SEQUENCES): the second ISO test moves through
    the arm calibration and measures with the hand-eye version it stored; the arm's accuracy improves."""
    config, _ = load_cell_file(CELL)
    cell = tmp_path / "cell.yaml"
    cell.write_text(f"extends: {CELL}\nroutines:\n"
                    "  hand-eye: {poses: 8, verify_poses: 1, touches: 0}\n"
                    "  iso9283: {cycles: 3}\n"
                    f"  arm-kinematics: {{poses: 24, verify_poses: 3, candidates: 200, "
                    f"board_scale: {caliper_scale(config, 0)}, board_scale_sigma_pct: 0.005}}\n")
    config, text = load_cell_file(cell)
    store = CalibrationStore(tmp_path / "store")
    out = run_sequence("arm-acceptance", config, text, tmp_path / "seq", seed=0, store=store)
    runs = out["summary"]["runs"]
    assert list(runs) == ["hand-eye", "iso9283.before", "arm-kinematics", "iso9283.after"]
    before, after = out["results"]["iso9283.before"], out["results"]["iso9283.after"]
    assert "arm_calibration" not in before and after["arm_calibration"] == out["results"]["arm-kinematics"][
        "calibration"]["id"]
    def worst(result, section):  # the worst pose's AP, measured (stats) or true (truth), in the calibration's frame
        return max(v for k, v in result[section]["ap_mm"].items() if k.startswith("P"))

    assert worst(after, "stats") < worst(before, "stats") / 3
    assert worst(after, "truth") < worst(before, "truth") / 3
