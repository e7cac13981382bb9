"""repeatability: ISO 9283 pose repeatability of the simulated robot, seen by camera 1 after its virtual grid."""

import json
import math

import numpy as np
import pytest

from calibration.errors import CalibrationInputError
from calibration.routines.health.repeatability import fit_repeatability

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore

from tests.conftest import MICROCELL

RAYLEIGH_RP = math.sqrt(math.pi / 2) + 3 * math.sqrt(2 - math.pi / 2)  # RP / sigma for 2-D Gaussian noise


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """cam1 calibrated by the smallest virtual grid, 3 x 3 points and a perspective map (what the spread needs
    of it is its local scale: the distortion changes that by < 1 %), then the routine at its defaults:
    5 positions, 30 cycles."""
    config, text = load_cell_file(MICROCELL)
    out = tmp_path_factory.mktemp("repeatability")
    store = CalibrationStore(out / "store")
    run_routine("virtual-grid", config, text, out / "vg", seed=2, store=store,
                overrides={"rows": 3, "cols": 3, "passes": 1, "n_verify": 0, "radial_terms": 0, "tangential": False,
                           "fit_centre": False})
    result = run_routine("repeatability", config, text, out / "rp", seed=2, store=store)
    return out / "rp", result


def test_recovers_the_simulated_repeatability(run):
    """Within 15 % of the simulated robot's RP (the mean over the positions: one position's RP from 30
    cycles scatters by about 10 %); the camera adds little (0.005 px of centroid noise is 0.03 µm)."""
    _, result = run
    rp, truth = result["stats"]["repeatability"], result["truth"]
    assert truth["rp_um"] == pytest.approx(1.7 * RAYLEIGH_RP)
    assert set(rp["rp_um"]) == {"P1", "P2", "P3", "P4", "P5"}
    assert all(p["n"] == 30 for p in rp["positions"].values())
    assert abs(rp["rp_mean_um"] / truth["rp_um"] - 1) <= 0.15
    for k, value in rp["rp_um"].items():  # what the camera saw of each position is what the nozzle did
        assert value == pytest.approx(truth["rp_attained_um"][k], abs=0.3)
    assert rp["drift_mean_um"] < 3 * 1.7  # no drift simulated: the means of 3 cycles differ by noise alone
    assert "calibration" not in result  # a measurement, not a calibration


def test_report_table_chart_and_plot(run):
    folder, _ = run
    result = json.loads((folder / "result.json").read_text())
    (table,) = result["tables"]
    assert table["columns"][0] == "position" and [r[0] for r in table["rows"][:5]] == ["P1", "P2", "P3", "P4", "P5"]
    assert table["rows"][-1][6] == 5.0  # seed 001's +/- 5 µm beside ours
    report = (folder / "report.md").read_text()
    assert "Pose repeatability RP = mean l + 3 S_l" in report and "seed 001 section 4" in report
    assert (folder / result["files"]["plot"]).stat().st_size > 1000
    assert (folder / result["files"]["charts"]["repeatability"]).stat().st_size > 1000


def test_fit_offline_gives_the_same_figures(run, tmp_path):
    from cellctl.cli import main

    folder, result = run
    samples, out = folder / "samples.csv", tmp_path / "rp.json"
    assert main(["fit", "repeatability", "--samples", str(samples), "--out", str(out)]) == 0
    offline = json.loads(out.read_text())
    assert offline["stats"]["repeatability"]["rp_um"] == pytest.approx(result["stats"]["repeatability"]["rp_um"])


def test_rp_of_gaussian_noise_is_the_rayleigh_figure():
    """The fit's RP on many cycles of 2-D Gaussian noise of sigma per axis: sigma (sqrt(pi/2) + 3 sqrt(2 - pi/2))."""
    rng = np.random.default_rng(0)
    xy = np.array([40.0, 30.0]) + rng.normal(0, 2e-3, (20000, 2))  # mm: sigma 2 µm
    samples = [{"position": "P1", "cycle": j, "meas_x_mm": x, "meas_y_mm": y} for j, (x, y) in enumerate(xy)]
    rp = fit_repeatability(samples).stats["repeatability"]["rp_um"]["P1"]
    assert rp == pytest.approx(2.0 * RAYLEIGH_RP, rel=0.01)


def test_refuses_without_a_camera_calibration(tmp_path):
    config, text = load_cell_file(MICROCELL)
    with pytest.raises(CalibrationInputError, match="needs an active calibration of 'cam1'"):
        run_routine("repeatability", config, text, tmp_path / "rp", store=CalibrationStore(tmp_path / "empty"))
    assert not (tmp_path / "rp").exists()  # refused before any motion or file
