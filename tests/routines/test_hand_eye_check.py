"""calibration-check of a hand-eye calibration (`targets=hand-eye:<camera>`) on the simulated UR5e cell, calibrated
once (seed 3, small runs) and checked in later runs of the same cell with and without the move the world applies
(`sim.drift`): a camera bumped on its mount is found, named and estimated near the true bump, an untouched cell
holds, a moved board is told from a bumped camera, and a target without a calibration is refused before anything
moves. The figures over 20 seeds are tools/hand_eye_check_figures.py's."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from drivers.sim.kinds import build_world

from calibration.errors import CalibrationInputError, UnknownName
from calibration.routines.health.calibration_check import CalibrationCheck
from calibration.routines.six_axis.hand_eye import HandEye

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore

from tests.conftest import ROOT

pytestmark = pytest.mark.long  # run first: see conftest.py

CELL = ROOT / "config" / "sim-ur5e-handeye.yaml"
SEED = 3
TARGET = "hand-eye:wrist"
SMALL = {"targets": TARGET, "hand_eye_poses": CalibrationCheck.small_params["hand_eye_poses"]}
MOVE = {"translation_mm": [0.3, -0.3, 0.2], "rotation_deg": [0.06, 0.05, -0.06]}  # 0.47 mm, 0.099 deg


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The cell file, its text and a store holding the wrist camera's hand-eye calibration."""
    config, text = load_cell_file(CELL)
    folder = tmp_path_factory.mktemp("hand-eye-check")
    store = CalibrationStore(folder / "store")
    run_routine("hand-eye", config, text, folder / "hand-eye", seed=SEED, store=store,
                overrides={**HandEye.small_params, "touches": 0})
    store.close()
    return config, text, folder / "store"


def check(calibrated, tmp_path, drift: dict, **params) -> tuple[dict, CalibrationStore]:
    config, text, store_dir = calibrated
    shutil.copytree(store_dir, tmp_path / "store")
    sim = config.sim.model_validate(dict(config.sim.model_dump(), drift=drift))
    store = CalibrationStore(tmp_path / "store")
    result = run_routine("calibration-check", config.model_copy(update={"sim": sim}), text, tmp_path / "check",
                         seed=SEED, store=store, overrides={**SMALL, **params})
    return result, store


def test_the_knob_moves_the_cameras_hidden_mount_from_its_time():
    config, _ = load_cell_file(CELL)
    sim = config.sim.model_validate(dict(config.sim.model_dump(), drift={"wrist": {**MOVE, "from_cell_time_s": 5}}))
    world = build_world(sim)
    drawn = world.cameras["wrist"].mount
    assert np.array_equal(world.mount_now("wrist"), drawn)
    world.clock.advance(5.0)
    now = world.mount_now("wrist")
    assert np.allclose(now[:3, 3] - drawn[:3, 3], np.array(MOVE["translation_mm"]) * 1e-3, atol=1e-12)
    turn = Rotation.from_matrix(now[:3, :3] @ drawn[:3, :3].T).as_rotvec(degrees=True)
    assert np.allclose(turn, MOVE["rotation_deg"], atol=1e-9)
    assert np.allclose(world.camera_pose("wrist"), world.flange @ now)
    with pytest.raises(ValidationError, match="no camera or board 'nosuch'"):
        config.sim.model_validate(dict(config.sim.model_dump(), drift={"nosuch": MOVE}))


def test_a_bumped_camera_is_found_named_and_estimated(calibrated, tmp_path, capsys):
    result, store = check(calibrated, tmp_path, {"wrist": MOVE})
    drift = result["stats"]["drift"][TARGET]
    assert result["verdict"] == "drift" and result["drifted"] == [TARGET]
    assert drift["attributed_to"] == ["camera"]
    camera = drift["camera"]
    assert np.linalg.norm(np.subtract(camera["translation_mm"], MOVE["translation_mm"])) <= 0.1
    assert np.linalg.norm(np.subtract(camera["rotation_deg"], MOVE["rotation_deg"])) <= 0.015
    assert camera["frame"] == "flange" and drift["board"]["shift_mm"] <= 0.1
    assert result["actions"][TARGET].startswith("recalibrate: the camera moved on its mount by 0.4")
    assert result["checked"] == {TARGET: store.active_models()[TARGET]["calibration_id"]}
    truth = result["truth"]  # what the world moved, and how far the estimate is from it
    assert truth["drifted"] == [TARGET] and truth[TARGET]["camera"]["translation_mm"] == pytest.approx(0.469, abs=1e-3)
    assert truth[TARGET]["camera"]["estimate_error_mm"] <= 0.1 and truth[TARGET]["board"]["translation_mm"] == 0
    # kept with the calibration it checked, as the micro cell's checks are: `cellctl health` shows it
    assert store.health()[TARGET]["verdict"] == "drift"
    store.close()
    from cellctl.cli import main

    assert main(["health", "--config", str(CELL), "--store", str(tmp_path / "store")]) == 0
    out = capsys.readouterr().out
    assert TARGET in out and "DRIFT" in out and "the camera moved on its mount" in out


def test_an_untouched_cell_holds(calibrated, tmp_path):
    result, store = check(calibrated, tmp_path, {})
    drift = result["stats"]["drift"][TARGET]
    assert result["verdict"] == "ok" and result["drifted"] == [] and drift["attributed_to"] == []
    assert result["truth"]["drifted"] == []
    assert result["actions"] == {TARGET: "ok"}
    assert drift["camera"]["shift_mm"] <= 0.1 and drift["camera"]["turn_deg"] <= 0.01
    assert result["stats"]["readings"][TARGET]["n_poses"] == SMALL["hand_eye_poses"]
    assert store.health()[TARGET]["verdict"] == "ok"
    store.close()


def test_a_moved_board_is_told_from_a_bumped_camera(calibrated, tmp_path):
    result, store = check(calibrated, tmp_path, {"table": MOVE})
    store.close()
    drift = result["stats"]["drift"][TARGET]
    assert result["drifted"] == [TARGET] and drift["attributed_to"] == ["board"]
    assert np.linalg.norm(np.subtract(drift["board"]["translation_mm"], MOVE["translation_mm"])) <= 0.15
    assert drift["camera"]["shift_mm"] <= 0.1


def test_a_target_without_a_calibration_is_refused_before_anything_moves(calibrated, tmp_path):
    config, text, store_dir = calibrated
    empty = CalibrationStore(tmp_path / "empty")
    with pytest.raises(CalibrationInputError, match="needs an active calibration of 'hand-eye:wrist'; none is stored"):
        run_routine("calibration-check", config, text, tmp_path / "a", store=empty, overrides={"targets": TARGET})
    empty.close()
    shutil.copytree(store_dir, tmp_path / "store")
    store = CalibrationStore(tmp_path / "store")
    with pytest.raises(CalibrationInputError, match=r"of 'hand-eye:top'; none is stored \(active: hand-eye:wrist\)"):
        run_routine("calibration-check", config, text, tmp_path / "b", store=store, overrides={"targets": "hand-eye:top"})
    with pytest.raises(UnknownName, match="no camera 'nosuch' in the cell file"):
        run_routine("calibration-check", config, text, tmp_path / "c", store=store,
                    overrides={"targets": "hand-eye:nosuch"})
    with pytest.raises(CalibrationInputError, match="update=true"):
        run_routine("calibration-check", config, text, tmp_path / "d", store=store,
                    overrides={"targets": TARGET, "update": True})
    assert store.checks() == []
    store.close()
    assert not any((tmp_path / name).exists() for name in "abcd")
