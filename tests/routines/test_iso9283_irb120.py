"""iso9283 on the simulated IRB 120 cell (config/sim-irb120-csm.yaml), measured by the two fixed cameras that
`arm-kinematics --param observe=fixed-cameras` calibrated (calibration/routines/six_axis/_iso_stereo.py): the arm as
its controller moves it (`moves=controller`, before) and through the arm calibration (after), judged against the
world's truth (cellctl/truth/iso9283.py: the true fixture poses in the cameras' frame). What it refuses, it refuses
before anything moves."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.errors import CalibrationInputError
from calibration.models.hand_eye import pose_to_dict
from calibration.routines.base import Step
from calibration.routines.six_axis.iso9283 import POSE_KEYS, Iso9283

from cellctl.config import load_cell_file
from cellctl.core.cell import Cell
from cellctl.core.orchestrator import Aborted, JobControl
from cellctl.core.runs import routine_params, run_routine, run_sequence, with_seed
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.run_folder import RunFolder

from tests.conftest import ROOT
from tests.support.shared_runs import made_once

pytestmark = pytest.mark.long

CELL = ROOT / "config" / "sim-irb120-csm.yaml"
CYCLES = 30  # ISO 9283's
FRAMES = 2  # per camera and visit: half the cell file's 4, so twice their sensor noise in RP, and half the time
SEEDS = (0, 1)
POSES = ("P1", "P2", "P3", "P4", "P5")


def _make(seed: int):
    def make(folder, store_path) -> dict:
        config, text = load_cell_file(CELL)
        store = CalibrationStore(store_path)
        arm = run_routine("arm-kinematics", config, text, folder / "arm", seed=seed, store=store)
        out = {"arm": arm}
        for moves in ("controller", "calibrated"):
            out[moves] = run_routine("iso9283", config, text, folder / moves, seed=seed, store=store,
                                     overrides={"cycles": CYCLES, "moves": moves, "frames": FRAMES})
        store.close()
        return out
    return make


@pytest.fixture(scope="module")
def seeds(request, tmp_path_factory) -> dict:
    """Per seed: arm-kinematics, then iso9283 with the arm as its controller moves it and through the calibration."""
    return {seed: made_once(request, tmp_path_factory, f"iso9283-irb120-seed{seed}", _make(seed)) for seed in SEEDS}


def _outside(measured: dict, truth: dict, share: float = 0.15, floor_mm: float = 0.005) -> dict:
    """The poses whose measured figure is not within `share` (or floor_mm) of the truth, with both."""
    return {p: (round(measured[p], 4), round(truth[p], 4)) for p in POSES
            if abs(measured[p] - truth[p]) > max(share * truth[p], floor_mm)}


def _misses(seeds: dict, moves: str, figure: str) -> dict:
    return {seed: miss for seed, run in seeds.items()
            if (miss := _outside(run.result[moves]["stats"][figure], run.result[moves]["truth"][figure]))}


def test_before_calibration_ap_and_rp_are_within_15_percent_or_5_um_of_truth(seeds):
    for run in seeds.values():
        r = run.result["controller"]
        assert r["n_samples"] == 5 * CYCLES and not r["rejected"]
        assert min(r["truth"]["ap_mm"][p] for p in POSES) > 0.3  # the arm as it came: off by tenths of a mm
    assert not _misses(seeds, "controller", "ap_mm")
    assert not _misses(seeds, "controller", "rp_mm")


def test_through_the_arm_calibration_rp_is_within_15_percent_or_5_um_of_truth(seeds):
    assert not _misses(seeds, "calibrated", "rp_mm")
    for run in seeds.values():
        before, after = run.result["controller"], run.result["calibrated"]
        assert after["arm_calibration"] == run.result["arm"]["calibration"]["id"]
        # the same noise and the same repeatability: the arm's RP does not depend on its calibration
        assert after["truth"]["rp_mm"] == pytest.approx(before["truth"]["rp_mm"], rel=0.3)


def test_through_the_arm_calibration_ap_falls_to_what_the_cameras_can_resolve(seeds):
    for run in seeds.values():
        before, after = run.result["controller"], run.result["calibrated"]
        assert after["truth"]["ap_mm"]["worst"] < 0.015  # the calibrated arm lands within about 10 um
        assert after["stats"]["ap_mm"]["worst"] < 0.025  # what the cameras make of it (next test)
        assert before["stats"]["ap_mm"]["worst"] / after["stats"]["ap_mm"]["worst"] > 20


@pytest.mark.xfail(strict=True, reason="the calibrated arm's AP is 1-13 um, as small as what these cameras resolve: "
                   "the circles' detector has a bias of a few hundredths of a pixel that depends on where each circle "
                   "falls on the pixel grid, the same at every cycle of a pose (the arm repeats to 0.02 px), so not "
                   "averaged away; at 1.2 m it moves a pose's measured barycentre by up to about 10 um (seed 0, P1: "
                   "AP 14.9 um measured, 5.4 um true; seed 1 meets the figure; seeds 0-9: 41 of 50 poses, "
                   "tools/iso9283_irb120_figures.py). The same cameras fed the true circle centres agree with the "
                   "truth to 8 um (next test)")
def test_through_the_arm_calibration_ap_is_within_15_percent_or_5_um_of_truth(seeds):
    assert not _misses(seeds, "calibrated", "ap_mm")


def test_the_instrument_without_its_image_noise_agrees_with_the_truth(seeds):
    """The same measurement fed each frame's true circle centres: what remains is the cameras' calibration."""
    for run in seeds.values():
        for moves in ("controller", "calibrated"):
            t = run.result[moves]["truth"]
            assert not _outside(t["ap_image_mm"], t["ap_mm"], share=0.0, floor_mm=0.008)
            assert t["frame"]["volume_poses"] >= 30 and t["frame"]["registration_rms_mm"] < 0.01


def test_the_report_has_the_standard_table_and_says_how_the_arm_moved(seeds):
    run = seeds[0]
    before, after = (run.folder / m / "report.md" for m in ("controller", "calibrated"))
    text = before.read_text()
    assert "ISO 9283 pose accuracy (§7.2.1) and pose repeatability (§7.2.2)" in text
    assert "the fixed cameras of the arm calibration" in text and "moves=controller" in text
    # the arm as it came: no move went through the active arm calibration, and neither result nor report says so
    assert "arm_calibration" not in run.result["controller"] and "Every move went through" not in text
    arm_id = run.result["arm"]["calibration"]["id"]
    assert run.result["calibrated"]["arm_calibration"] == arm_id
    assert f"every move through the arm calibration (id {arm_id})" in after.read_text()
    stats = run.result["calibrated"]["stats"]
    assert set(stats["per_pose"]) == set(POSES) and stats["calibrations"] == {"arm": arm_id}


@pytest.fixture(scope="module")
def cell_with_arm(seeds, tmp_path_factory):
    config, text = load_cell_file(CELL)
    store = seeds[0].store_copy(tmp_path_factory.mktemp("iso-irb120") / "store")
    return config, text, store


@pytest.mark.parametrize("overrides, refusal", [
    ({"centre_mm": (350, 0, 450)}, r"P4: the fixture at \(430.0, 80.0, 530.0\) mm would not show every circle to "
                                   r"every camera \(cam1, cam2: inside the image by 20 px, at most 60 deg from "
                                   r"face-on\), predicted through the arm calibration \(id 1\); .* nothing moved"),
    ({"centre_mm": (550, 0, 200)}, r"P1: the fixture at \(550.0, 0.0, 200.0\) mm: arm: \(0.5500, 0.0000, 0.2000\) "
                                   r"m through the calibrated arm \(calibration 1\): .* out of reach .*; move "
                                   r"centre_mm or shrink cube_mm; nothing moved$"),
], ids=["out-of-view", "out-of-reach"])
def test_a_cube_out_of_view_or_reach_is_refused_naming_the_pose_before_anything_moves(cell_with_arm, tmp_path,
                                                                                        overrides, refusal):
    config, text, store = cell_with_arm
    with Cell(with_seed(config, 0), text) as cell:
        with pytest.raises(CalibrationInputError, match=refusal):
            run_routine("iso9283", config, text, tmp_path / "run", seed=0, store=store,
                        overrides={"cycles": 2, **overrides}, cell=cell)
        assert cell.sim_world.moves == []
    assert not (tmp_path / "run" / "samples.csv").exists()


def test_without_an_arm_calibration_from_fixed_cameras_it_is_refused(tmp_path):
    config, text = load_cell_file(CELL)
    with Cell(with_seed(config, 0), text) as cell:
        with pytest.raises(CalibrationInputError, match=r"no active calibration of 'arm'; iso9283 measures with the "
                                                        r"cameras arm-kinematics calibrates"):
            run_routine("iso9283", config, text, tmp_path / "run", seed=0, store=CalibrationStore(tmp_path / "empty"),
                        overrides={"cycles": 2}, cell=cell)
        assert cell.sim_world.moves == []
    assert not (tmp_path / "run" / "samples.csv").exists()


def test_a_camera_named_twice_is_refused(cell_with_arm, tmp_path):
    config, text, store = cell_with_arm
    with pytest.raises(CalibrationInputError, match=r"cameras: cam1, cam1 names a camera twice; name each of cam1, "
                                                    r"cam2 once"):
        run_routine("iso9283", config, text, tmp_path / "run", seed=0, store=store,
                    overrides={"cycles": 2, "cameras": ["cam1", "cam1"]})


def test_a_frame_without_the_circles_is_kept_as_a_refused_row(cell_with_arm):
    config, text, store = cell_with_arm
    params = routine_params(Iso9283(), config, {"cycles": 2, "frames": 1})
    with Cell(with_seed(config, 0), text) as cell:
        cell.devices.calibrations = store.active_models()
        # the plate turned from facing both cameras to facing -y: cam1 (at y = -0.6 m) sees it, cam2 (at +0.6 m)
        # sees it edge-on
        T = np.eye(4)
        T[:3, :3] = (Rotation.from_euler("x", 90, degrees=True) * Rotation.from_euler("y", -144.74, degrees=True)
                     ).as_matrix()
        T[:3, 3] = (0.35, 0.0, 0.25)
        values = [pose_to_dict(T)[k] for k in POSE_KEYS]
        step = Step(0, "visit", {"pose": "P1", "cycle": 1, "commanded": values, "flange": values,
                                 "approach": values})
        row = Iso9283().execute(step, params, cell.devices).rows
    row = row[0] if isinstance(row, list) else row
    assert row["status"] == "refused" and row["message"].startswith("cam2 frame")
    assert "expected 1 white and 3 black marks" in row["message"] and "meas_x_mm" not in row


def test_the_stereo_arm_acceptance_sequence_shows_iso_9283_before_and_after(tmp_path):
    """arm-kinematics, iso9283 as the controller moves the arm, iso9283 through the calibration: one job."""
    cell = tmp_path / "cell.yaml"
    cell.write_text(f"extends: {CELL}\nroutines:\n  iso9283: {{cycles: 3, frames: 1}}\n")
    config, text = load_cell_file(cell)
    out = run_sequence("arm-acceptance-stereo", config, text, tmp_path / "seq", seed=1,
                       store=CalibrationStore(tmp_path / "store"))
    assert list(out["summary"]["runs"]) == ["arm-kinematics", "iso9283.before", "iso9283.after"]
    before, after = out["results"]["iso9283.before"], out["results"]["iso9283.after"]
    arm_id = out["results"]["arm-kinematics"]["calibration"]["id"]
    assert before["params"]["moves"] == "controller" and after["arm_calibration"] == arm_id
    assert after["stats"]["ap_mm"]["worst"] < before["stats"]["ap_mm"]["worst"] / 20


def test_the_arm_calibrations_report_plots_the_held_out_error_by_model(seeds):
    """arm-kinematics (fixed cameras): before, cameras first and simultaneous over the held-out poses."""
    folder = seeds[0].folder / "arm"
    assert (folder / "held_out_errors.png").stat().st_size > 0
    assert "![Held-out poses: the fixture's position error by model](held_out_errors.png)" in (
        folder / "report.md").read_text()


def test_a_run_aborted_part_way_and_resumed_equals_the_uninterrupted_one(cell_with_arm, tmp_path):
    """The stereo measurement through the orchestrator's resume: the same rows and the same AP and RP."""
    config, text, store = cell_with_arm
    small = {"cycles": 2, "frames": 1}
    whole = run_routine("iso9283", config, text, tmp_path / "whole", seed=0, store=store, overrides=small)
    control = JobControl()

    def abort_at_step(progress):
        if progress.done == 4:
            control.abort()

    with pytest.raises(Aborted):
        run_routine("iso9283", config, text, tmp_path / "cut", seed=0, store=store, overrides=small, control=control,
                    on_progress=abort_at_step)
    assert len(RunFolder(tmp_path / "cut").samples()) == 4
    resumed = run_routine("iso9283", config, text, tmp_path / "cut", seed=0, store=store, overrides=small,
                          resume=True)
    assert RunFolder(tmp_path / "cut").samples() == RunFolder(tmp_path / "whole").samples()
    assert resumed["stats"] == whole["stats"] and resumed["truth"]["ap_mm"] == whole["truth"]["ap_mm"]
