"""Virtual-grid calibration end to end on the simulated micro cell, judged against the hidden truth."""

import pytest

from cellctl.core.orchestrator import JobControl
from cellctl.core.runs import run_routine
from cellctl.stores.run_folder import RunFolder


@pytest.mark.parametrize("seed", [1, 2])
def test_default_cell_meets_the_accuracy_budget(microcell, tmp_path, seed):
    config, text = microcell
    result = run_routine("virtual-grid", config, text, tmp_path / "run", seed=seed)
    truth, stats = result["truth"], result["stats"]
    # the grid stops once the predicted accuracy meets today's figure (issue 31): well within its 112 samples
    assert 9 <= stats["calibration"]["n"] < 112 and stats["target"]["met"] and stats["verification"]["n"] == 56
    assert truth["centroid_rms_px"] <= 0.05
    assert stats["verification"]["mean_um"] <= 3.0
    assert truth["mapping_mean_um"] <= 1.2
    assert truth["mapping_max_um"] <= 4.0
    # the fit's own accuracy prediction is honest: within a factor 2 of the true map error
    assert 0.5 < stats["predicted"]["map_rms_um"] / truth["mapping_rms_um"] < 2.0
    assert result["cell_time_s"] > (stats["calibration"]["n"] + 56) * 0.25  # at least the settling time of its moves
    folder = tmp_path / "run"
    for name in ("result.json", "samples.csv", "report.md", "residuals.png", "run.json"):
        assert (folder / name).stat().st_size > 0


SMALL = {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1}


def test_resume_refuses_a_different_run(microcell, tmp_path):
    config, text = microcell
    run_routine("virtual-grid", config, text, tmp_path / "r", seed=5, overrides=SMALL)
    from cellctl.stores.run_folder import RunFolderError

    with pytest.raises(RunFolderError, match="params differs"):
        run_routine("virtual-grid", config, text, tmp_path / "r", seed=5, overrides=dict(SMALL, rows=5), resume=True)
    with pytest.raises(RunFolderError, match="already holds a run"):
        run_routine("virtual-grid", config, text, tmp_path / "r", seed=5, overrides=SMALL)


def test_pause_holds_between_steps(microcell, tmp_path):
    import threading

    config, text = microcell
    control = JobControl()
    seen = []

    def pause_at_three(progress):
        seen.append(progress.done)
        if progress.done == 3:
            control.pause()
            threading.Timer(0.3, lambda: (seen.append("resumed"), control.resume())).start()

    run_routine("virtual-grid", config, text, tmp_path / "p", seed=5, overrides=SMALL,
                control=control, on_progress=pause_at_three)
    assert seen.index("resumed") == seen.index(3) + 1  # no step ran while paused


def test_a_step_without_a_feature_is_kept_and_reported(microcell, tmp_path):
    """A verification point outside the field of view: recorded, listed, not fitted."""
    config, text = microcell
    area = config.areas["area1"].model_copy(update={"size_mm": (19.5, 11.0)})  # wider than the camera sees
    config = config.model_copy(update={"areas": {"area1": area}})
    result = run_routine("virtual-grid", config, text, tmp_path / "f", seed=5,
                         overrides={"rows": 4, "cols": 7, "n_verify": 0, "margin_mm": 0.1, "passes": 1,
                                    "target_um": 0.001})  # out of reach: the whole grid
    rows = RunFolder(tmp_path / "f").samples()
    missing = [r for r in rows if r["status"] == "no-feature"]
    assert len(rows) == 28 and len(missing) == 8  # the two outer columns
    assert {r["step"] for r in missing} <= {r["step"] for r in result["rejected"]}
    assert result["stats"]["calibration"]["n"] == 20


def test_a_cut_step_is_dropped_when_the_folder_is_reopened(tmp_path):
    """A crash while writing leaves a partial line or a multi-row step with rows missing: both go."""
    from cellctl.stores.run_folder import RunFolder

    folder = RunFolder(tmp_path / "r")
    columns = ("step", "x", "step_rows")
    folder.create({"routine": "t"}, columns)
    folder.append_many([{"step": 0, "x": 1.0, "step_rows": 1}], columns)
    folder.append_many([{"step": 1, "x": 2.0, "step_rows": 3}, {"step": 1, "x": 3.0, "step_rows": 3}], columns)
    with open(folder.samples_path, "a") as f:
        f.write("1,4.0")  # the third row of step 1, cut mid-line
    assert [r["step"] for r in folder.samples()] == [0]
    assert folder.samples_path.read_text().splitlines()[-1].startswith("0,")
