"""Accuracy-targeted plans (issue 31): stop the calibration budget once the target is met, verify always, and
resume exactly (the decision is replayed from the stored samples)."""

import json
import math

import pytest

from calibration.routines import targeted
from calibration.routines.micro.virtual_grid import CAL, VER

from cellctl.core.orchestrator import Aborted, JobControl
from cellctl.core.runs import run_routine
from cellctl.stores.run_folder import RunFolder

SMALL = {"rows": 5, "cols": 5, "n_verify": 8}  # a budget of 2 x 25 grid samples
BOOKKEEPING = ("cell_time_s", "image", "step_rows")


def steps_of(folder, kind: str) -> list[int]:
    return sorted({int(r["step"]) for r in RunFolder(folder).samples() if r["set"] == kind})


def test_default_target_stops_early_and_still_verifies(microcell, tmp_path):
    config, text = microcell
    result = run_routine("virtual-grid", config, text, tmp_path / "run", seed=5, overrides=SMALL)
    target = result["stats"]["target"]
    assert target["met"] and target["budget"] == 50 and 9 <= target["samples"] < 50
    assert "target met after" in target["reason"]
    assert result["stats"]["calibration"]["n"] == target["samples"]
    # the first grid samples taken, then every verification point: the rest of the budget skipped
    assert steps_of(tmp_path / "run", CAL) == list(range(target["samples"]))
    assert steps_of(tmp_path / "run", VER) == list(range(50, 58))
    assert result["truth"]["mapping_mean_um"] <= 2.0
    assert (tmp_path / "run" / "area1_predicted_accuracy.png").stat().st_size > 0
    assert "Accuracy target: where collection stopped" in (tmp_path / "run" / "report.md").read_text()


def test_a_target_the_cell_cannot_reach_spends_the_budget_and_says_so(microcell, tmp_path):
    config, text = microcell
    result = run_routine("virtual-grid", config, text, tmp_path / "run", seed=5,
                         overrides=dict(SMALL, target_um=0.5))
    target = result["stats"]["target"]
    assert not target["met"] and target["samples"] == 50
    assert "NOT met" in target["reason"] and "0.5 µm" in target["reason"]
    assert target["predicted_um"] > 0.5  # what it reached, reported
    assert result["stats"]["verification"]["n"] == 8


@pytest.mark.parametrize("at", [10, 30])  # cut inside the budget, and after the stop (in verification)
def test_a_cut_run_resumed_on_a_fresh_world_decides_alike(microcell, tmp_path, at):
    config, text = microcell
    whole = run_routine("virtual-grid", config, text, tmp_path / "whole", seed=5, overrides=SMALL)
    control = JobControl()

    def abort_at(progress):
        if progress.done == at:
            control.abort()

    with pytest.raises(Aborted):
        run_routine("virtual-grid", config, text, tmp_path / "cut", seed=5, overrides=SMALL, control=control,
                    on_progress=abort_at)
    resumed = run_routine("virtual-grid", config, text, tmp_path / "cut", seed=5, overrides=SMALL, resume=True)
    a, b = RunFolder(tmp_path / "whole").samples(), RunFolder(tmp_path / "cut").samples()
    assert len(a) == len(b)
    assert all(repr(ra[k]) == repr(rb[k]) for ra, rb in zip(a, b) for k in ra if k not in BOOKKEEPING)
    for key in ("stats", "model", "cell_time_s"):
        assert resumed[key] == whole[key]


def test_rotation_sweep_identifies_the_offset_in_a_fraction_of_its_budget(calibrated_cell):
    sweep = calibrated_cell.done["results"]["rotation-sweep"]
    target = sweep["stats"]["target"]
    assert target["met"] and target["samples"] < target["budget"] / 4
    assert math.hypot(sweep["model"]["dx_um"] - sweep["truth"]["dx_um"],
                      sweep["model"]["dy_um"] - sweep["truth"]["dy_um"]) <= 1.0
    plan = json.loads((calibrated_cell.folder / "02-rotation-sweep" / "run.json").read_text())["plan"]
    turns = [math.degrees(s["args"]["turn"]) for s in plan if s["args"]["set"] == "cal"]
    assert turns[:12] == [0.0] * 6 + [180.0] * 6  # opposite turns first: they identify the offset best


def test_greedy_circle_order_fills_the_circle():
    order = [round(math.degrees(a)) for a in targeted.greedy_circle_order([math.radians(a) for a in range(0, 360, 90)])]
    assert order == [0, 180, 90, 270]


def test_upper_bound_of_a_sigma_shrinks_with_its_degrees_of_freedom():
    assert targeted.upper_factor(6) > targeted.upper_factor(60) > targeted.upper_factor(6000) > 1.0
    assert targeted.prediction(5, 1e-6, 2, 0.0) is None  # too few degrees of freedom to decide
