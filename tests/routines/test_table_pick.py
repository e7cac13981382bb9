"""table-pick on the simulated UR5e cell: the wrist camera, through its hand-eye calibration, finds a puck at a
hidden place on the table, the vacuum cup picks it and puts it down; the world scores the pick and the place.
What it refuses, it refuses before anything moves."""

import pytest

from calibration.errors import CalibrationInputError

from cellctl.config import load_cell_file
from cellctl.core import runs

from tests.conftest import ROOT

pytestmark = pytest.mark.long  # run first: see conftest.py

CELL = ROOT / "config" / "sim-ur5e-handeye.yaml"


@pytest.fixture(scope="module")
def calibrated(wrist_hand_eye_seed2, tmp_path_factory):
    """The wrist camera's hand-eye calibration (seed 2, the routine's defaults, no touch test), made once for this
    module and test_iso9283.py (tests/routines/conftest.py), in a store of ours."""
    config, text = load_cell_file(CELL)
    return config, text, wrist_hand_eye_seed2.store_copy(tmp_path_factory.mktemp("table-pick") / "calibrations")


def test_the_wrist_camera_finds_the_puck_and_the_cup_picks_it_and_puts_it_where_asked(calibrated, tmp_path):
    config, text, store = calibrated
    result = runs.run_routine("table-pick", config, text, tmp_path / "pick", seed=2, store=store)
    stats, truth = result["stats"], result["truth"]
    assert stats["parts_seen"] == 2 and stats["picked"] and stats["placed"]  # both pucks in view, one picked
    assert truth["picked"] and truth["pick_miss_mm"] <= 0.5  # the cup seals within 4 mm; it lands far closer
    assert truth["place_error_mm"] <= 0.5
    assert 50 <= stats["pick_sigma_um"] <= 500  # the located puck's 1-sigma, from the calibration
    assert [r[0] for r in result["tables"][0]["rows"]] == ["look", "look", "pick", "place"]


def test_a_puck_out_of_view_ends_the_job_with_the_reason_and_nothing_is_placed(calibrated, tmp_path):
    config, text, store = calibrated
    result = runs.run_routine("table-pick", config, text, tmp_path / "pick", seed=2, store=store,
                              overrides={"look_mm": [-300.0, -400.0]})  # bare table
    assert result["stats"] == {"parts_seen": 0, "picked": False, "placed": False}
    reasons = [r["reason"] for r in result["rejected"]]
    assert reasons[0].startswith("no part in view: no bright disc of") and "nothing placed" in reasons[-1]
    assert result["truth"] == {"picked": False}  # the cup never came down


def test_it_refuses_before_anything_moves(calibrated, tmp_path):
    config, text, store = calibrated
    with pytest.raises(CalibrationInputError, match="camera: 'top' has no active hand-eye calibration; run hand-eye"):
        runs.run_routine("table-pick", config, text, tmp_path / "a", seed=2, store=store, overrides={"camera": "top"})
    with pytest.raises(CalibrationInputError, match=r"place_mm: the flange would have to be at \(-1200, 0, 156\) mm, "
                                                    r"out of the arm's reach"):
        runs.run_routine("table-pick", config, text, tmp_path / "b", seed=2, store=store,
                         overrides={"place_mm": [-1200.0, 0.0]})
    assert not (tmp_path / "a" / "samples.csv").exists() and not (tmp_path / "b" / "samples.csv").exists()
