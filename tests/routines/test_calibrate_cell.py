"""calibrate-cell: the routines in the order the seed needs, each stored as the active calibration."""

import json
import shutil

from cellctl.cli import main
from cellctl.config import load_cell_file
from cellctl.core.runs import run_sequence

from tests.conftest import MICROCELL

IMAGE_SIZES = {"onboard-camera": "2592x1944", "virtual-grid": "2448x2050"}  # else camera 2's, 1360x1024


def test_calibrate_then_place_in_order_at_the_cell_files_defaults(calibrated_cell):
    """The issue's figure at the cell file's defaults: placement error mean <= 12 µm at arbitrary alpha."""
    done = calibrated_cell.done
    assert list(done["results"]) == ["virtual-grid", "rotation-sweep", "virtual-grid-area2", "onboard-camera",
                                     "place-test"]
    placed = done["results"]["place-test"]
    assert placed["stats"]["verification"]["n"] == 12
    assert placed["stats"]["verification"]["mean_um"] <= 12.0  # at arbitrary alpha, tool offset compensated
    assert placed["truth"]["placement_mean_um"] <= 12.0
    store = calibrated_cell.store_copy(calibrated_cell.folder.parent / "store-order")
    assert {c.target for c in store.list() if c.active} == {"cam1", "nozzle", "cam2", "cam3"}
    assert len(store.list()) == 4
    summary = json.loads((calibrated_cell.folder / "result.json").read_text())
    assert summary["runs"]["rotation-sweep"]["truth"]["dx_um"] == -68.7


def test_every_fit_runs_offline_on_its_samples_to_the_same_result(calibrated_cell, tmp_path):
    """cellctl fit on each routine's recorded samples.csv (with the cell file's fit parameters, e.g. the lenses'
    working distances) gives the verification the run gave."""
    for k, (routine, result) in enumerate(calibrated_cell.done["results"].items(), start=1):
        out = tmp_path / f"{routine}.json"
        samples = calibrated_cell.folder / f"{k:02d}-{routine}" / "samples.csv"
        assert main(["fit", routine, "--samples", str(samples), "--out", str(out), "--config", str(MICROCELL),
                     "--image-size", IMAGE_SIZES.get(routine, "1360x1024")]) == 0
        assert json.loads(out.read_text())["stats"]["verification"] == result["stats"]["verification"]


def test_a_resumed_sequence_keeps_its_finished_runs(calibrated_cell, tmp_path):
    config, text = load_cell_file(MICROCELL)
    store = calibrated_cell.store_copy(tmp_path / "store")
    folder = shutil.copytree(calibrated_cell.folder, tmp_path / "cc")
    summary = json.loads((folder / "result.json").read_text())
    again = run_sequence("calibrate-and-place", config, text, folder, seed=calibrated_cell.seed,
                         store=store, resume=True)
    assert again["summary"]["runs"] == summary["runs"]  # finished runs are kept, not repeated
    assert len(store.list()) == 4  # nothing stored twice
