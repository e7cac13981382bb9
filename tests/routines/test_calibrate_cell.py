"""calibrate-cell: the routines in the order the seed needs, each stored as the active calibration."""

import json

from cellctl.calstore import CalibrationStore
from cellctl.config import load_cell_file
from cellctl.runs import run_sequence
from tests.conftest import MICROCELL


def test_calibrate_then_place_runs_in_order_and_resumes(tmp_path):
    config, text = load_cell_file(MICROCELL)
    small = dict(config.routines)
    small["virtual-grid"] = dict(small["virtual-grid"], rows=4, cols=4, passes=1, n_verify=4)
    small["rotation-sweep"] = dict(small["rotation-sweep"], rows=1, cols=2, step_deg=45, n_verify=4)
    small["virtual-grid-area2"] = dict(small["virtual-grid-area2"], n_verify=2)
    small["onboard-camera"] = dict(small["onboard-camera"], alphas_deg=[0, 20])
    small["place-test"] = dict(small["place-test"], n=6)
    config = config.model_copy(update={"routines": small})
    store = CalibrationStore(tmp_path / "store")
    done = run_sequence("calibrate-and-place", config, text, tmp_path / "cc", seed=3, store=store)
    assert list(done["results"]) == ["virtual-grid", "rotation-sweep", "virtual-grid-area2", "onboard-camera",
                                     "place-test"]
    placed = done["results"]["place-test"]
    print(placed["stats"]["verification"], placed["truth"])
    assert placed["stats"]["verification"]["n"] == 6
    assert placed["stats"]["verification"]["mean_um"] <= 12.0  # at arbitrary alpha, tool offset compensated
    assert placed["truth"]["placement_mean_um"] <= 12.0
    assert {c.target for c in store.list() if c.active} == {"cam1", "nozzle", "cam2", "cam3"}
    summary = json.loads((tmp_path / "cc" / "result.json").read_text())
    assert summary["runs"]["rotation-sweep"]["truth"]["dx_um"] == -68.7
    # every routine's fit also runs offline on its recorded samples (cellctl fit), to the same result
    from cellctl.cli import main

    for k, routine in enumerate(done["results"], start=1):
        out = tmp_path / f"{routine}.json"
        samples = tmp_path / "cc" / f"{k:02d}-{routine}" / "samples.csv"
        assert main(["fit", routine, "--samples", str(samples), "--out", str(out), "--image-size", "2592x1944"
                     if routine == "onboard-camera" else "2448x2050" if routine == "virtual-grid" else "1360x1024"]) == 0
        offline = json.loads(out.read_text())
        assert offline["stats"]["verification"] == done["results"][routine]["stats"]["verification"]
    again = run_sequence("calibrate-and-place", config, text, tmp_path / "cc", seed=3, store=store, resume=True)
    assert again["summary"]["runs"] == summary["runs"]  # finished runs are kept, not repeated
    assert len(store.list()) == 4
