"""The VR calibration routines (seed 000) on the simulated cell of config/sim-vr.yaml, judged against its truth.

The experiments run with fewer runs and conditions than the default (the full set is
`cellctl run vr-experiments --config config/sim-vr.yaml`, see tools/bench_vr.py for timing).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from drivers.interfaces import NotConnected
from drivers.registry import DriverContext, backend_class
from drivers.sim.vr.config import VrWorldConfig

from calibration.errors import CalibrationInputError
from calibration.routines.vr._common import VrOperator

from cellctl.config import load_cell_file, parse_cell_file
from cellctl.core import runs
from cellctl.core.cell import Cell

from tests.support.contract import ArmContract, CameraContract

CELL = Path(__file__).resolve().parents[2] / "config" / "sim-vr.yaml"
REQUIREMENT_IN, REQUIREMENT_DEG = 0.25, 3.0


def run(name, out, seed=None, save_images=False, **overrides):
    config, text = load_cell_file(CELL)
    return runs.run_routine(name, config, text, out, seed=seed, overrides=overrides, save_images=save_images)


@pytest.fixture(scope="module")
def experiments(tmp_path_factory):
    out = tmp_path_factory.mktemp("vr") / "experiments"
    result = run("vr-experiments", out, save_images=True, fig7_runs=6, n_runs=2, angles_deg=[28.0, 51.0],
                 views=[[28.0, 12.0]])
    return out, result


def test_simultaneous_update_beats_the_sequential_one(experiments):
    _, result = experiments
    truth = result["truth"]["alignment"]
    sim, seq = truth["simultaneous"], truth["objloc12"]
    assert sim["n"] == 6 and seq["n"] + seq["n_failed"] == 6
    assert seq["position_in"] >= 2 * sim["position_in"], (seq, sim)
    assert seq["orientation_deg"] > sim["orientation_deg"], (seq, sim)
    # the single-view sequential updates are worse still, as in the seed's Fig. 7
    for m in ("objloc1", "objloc2"):
        assert truth[m]["position_in"] > sim["position_in"]
    # the routine's own statistics, measured against the operator's reference alignment, tell the same story
    stats = result["stats"]["alignment"]
    for m in ("objloc1", "objloc2", "objloc12", "simultaneous"):
        assert set(stats[m]) >= {"position_in", "orientation_deg"}
    assert stats["objloc12"]["position_in"] >= 2 * stats["simultaneous"]["position_in"]
    assert stats["simultaneous"]["position_in"] == pytest.approx(sim["position_in"], rel=0.5)


def test_approach_ends_within_the_insertion_requirement(experiments):
    _, result = experiments
    final = result["truth"]["approach"]["final"]
    assert final["runs"] == 4 and final["runs_reached"] == 4  # 2 angles (28 and 51 deg) x 2 runs
    assert final["position_in"] <= REQUIREMENT_IN and final["orientation_deg"] <= REQUIREMENT_DEG, final
    assert final["within_requirement"]
    assert result["stats"]["approach"]["final"]["within_requirement"]
    # the error shrinks as the ORU nears the receptacle (Fig. 8), at both angles
    for angle, by_distance in result["truth"]["approach"]["by_angle"].items():
        assert by_distance["2"]["rms_position_in"] < by_distance["20"]["rms_position_in"], angle


def test_predicted_sigma_agrees_with_the_spread(experiments):
    _, result = experiments
    for source in (result["truth"], result["stats"]):
        ratio = source["covariance_consistency"]["ratio"]
        assert 0.5 <= ratio <= 2.0, ratio


def test_report_has_the_seed_figures_and_overlays(experiments):
    out, _ = experiments
    result = json.loads((out / "result.json").read_text())  # as written, with the report's tables and charts
    titles = " ".join(t["title"] for t in result["tables"])
    for fig in ("Fig. 7", "Figs. 8-9", "Fig. 10", "Fig. 11"):
        assert fig in titles
    assert set(result["files"]["charts"]) >= {"fig7_alignment", "fig8_distance", "fig9_angle", "fig11_receptacle"}
    overlays = sorted(p.name for p in (out / "images").glob("*overlay-fig7-*.png"))
    assert len(overlays) == 4, overlays  # the seed's Figs. 2-5
    report = (out / "report.md").read_text()
    assert "Fig. 7" in report and "seed pos (in)" in report
    assert result["stats"]["ellipses"]["receptacle_sigma_in"][0] > 0


def test_samples_are_plain_numeric_columns_that_resume_reads_back(experiments):
    """No JSON inside a CSV cell: every estimate, pose, error and covariance is one number per column."""
    from calibration.routines.vr._samples import SAMPLE_COLUMNS, estimate_from, has_estimate

    from cellctl.stores.run_folder import read_samples_text

    out, result = experiments
    text = (out / "samples.csv").read_text()
    assert "[" not in text and "{" not in text
    rows = read_samples_text(text)
    assert list(rows[0]) == [*SAMPLE_COLUMNS, "cell_time_s", "step_rows", "image"]
    words = {k for r in rows for k, v in r.items() if isinstance(v, str)}
    assert words <= {"kind", "condition", "method", "status", "message", "image"}, words
    # the estimate read back from the file is the model's, to the last bit
    last = [r for r in rows if r["method"] == "simultaneous" and has_estimate(r)][-1]
    assert estimate_from(last).to_dict() == result["model"]["estimate"]
    assert any(r.get("cov_rec_xx_m2") for r in rows)


@pytest.fixture(scope="module")
def coarse_and_fine(tmp_path_factory):
    """vr-coarse, then vr-fine, each from 5.1 in off the nominal receptacle position (itself off the true one):
    {name: (folder, result)}."""
    out = tmp_path_factory.mktemp("vr-scene")
    offset = {"initial_offset_in": [4.0, -2.5, 2.0], "initial_turn_deg": [3.0, -2.0, 4.0]}
    return {name: (out / name, run(name, out / name, seed=3, **offset)) for name in ("vr-coarse", "vr-fine")}


def test_coarse_matching_converges_from_more_than_4_in_off(coarse_and_fine):
    _, coarse = coarse_and_fine["vr-coarse"]
    assert coarse["truth"]["final"]["position_in"] < 1.0, coarse["truth"]["final"]
    assert coarse["model"]["kind"] == "vr-scene" and len(coarse["model"]["focal_px"]) == 2
    _, fine = coarse_and_fine["vr-fine"]
    assert fine["truth"]["final"]["position_in"] < REQUIREMENT_IN
    assert fine["truth"]["final"]["orientation_deg"] < REQUIREMENT_DEG


@pytest.mark.parametrize("name, methods, receptacle_in", [
    ("vr-coarse", ["point-objloc12", "point-simultaneous"], 1.0), ("vr-fine", ["simultaneous"], 0.4)])
def test_scene_report_leads_with_the_matching_and_the_fitted_scene(coarse_and_fine, name, methods, receptacle_in):
    out, result = coarse_and_fine[name]
    matching, scene = result["tables"]
    assert [row[0] for row in matching["rows"]] == methods
    columns = matching["columns"]
    for row in matching["rows"]:
        assert row[columns.index("RMS (px)")] < 3 and row[columns.index("converged")] == "yes"
        assert 0 < row[columns.index("σ position (in)")] < 1
    # the fitted scene beside the hidden truth: the receptacle where it is, the cameras where they stand
    rows = {row[0]: row for row in scene["rows"]}
    truth = result["truth"]
    fitted = np.array(rows["receptacle, robot frame"][1:4])
    assert np.linalg.norm(fitted - truth["receptacle_in"]) < receptacle_in
    for camera in ("side", "top"):
        centre = np.array(rows[f"{camera} camera centre, robot frame"][1:4])
        assert np.linalg.norm(centre - truth["cameras"][camera]["position_m"]) < 0.5
    report = (out / "report.md").read_text()
    assert report.split("\n## ")[1].startswith(matching["title"])
    # the truth is tables too, not a run-on line
    assert "| method | stop | distance_in | position_in | orientation_deg |" in report and "- rows:" not in report
    embedded = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    assert embedded and all((out / f).is_file() for f in embedded) and "residuals.png" not in embedded


def test_vr_approach_moves_the_oru_to_its_last_via_point(tmp_path):
    config, text = load_cell_file(CELL)
    result = runs.run_routine("vr-approach", config, text, tmp_path / "approach", save_images=True)
    rows = result["truth"]["rows"]
    assert [r["distance_in"] for r in rows] == [None, 8.0, 4.0, 2.0]
    final = result["truth"]["final"]
    assert final["position_in"] <= REQUIREMENT_IN and final["orientation_deg"] <= REQUIREMENT_DEG
    # each stop's relative pose and its predicted sigma are recorded, with an overlay
    stops = result["stats"]["approach"]["stops"]
    assert len(stops) == 4 and all(s["sigma_pos_in"] > 0 for s in stops)
    assert stops[-1]["oru_in_receptacle_in"][1] == pytest.approx(2.0 + 0.0, abs=0.3)
    assert len(list((tmp_path / "approach" / "images").glob("*overlay-stop*.png"))) == 4


def test_the_simulated_and_the_web_operator_speak_the_vr_protocol_a_terminal_does_not(tmp_path):
    config, text = load_cell_file(CELL)
    with Cell(config, text) as cell:
        assert isinstance(cell.operator, VrOperator)
    # the web operator (a person at the daemon's console) can click; outside a daemon nobody answers it
    web = text.replace("operator:\n  backend: sim-vr", f"store_dir: {tmp_path / 'store'}\noperator:\n  backend: web")
    assert web != text
    with Cell(parse_cell_file(web), web) as cell:
        assert isinstance(cell.operator, VrOperator)
    with pytest.raises(NotConnected, match="answered through the daemon"):
        runs.run_routine("vr-coarse", parse_cell_file(web), web, tmp_path / "web")
    # a terminal cannot click: refused before anything moves, naming the backends that can
    console = text.replace("operator:\n  backend: sim-vr", "operator:\n  backend: console")
    assert console != text
    with pytest.raises(CalibrationInputError, match="click.*'web'.*'sim-vr'"):
        runs.run_routine("vr-coarse", parse_cell_file(console), console, tmp_path / "console")


def test_cell_file_errors_name_the_key():
    text = CELL.read_text().replace("inter_camera_angle_deg: 50.0\n  side:", "inter_camera_angle_deg: 500.0\n  side:")
    assert text != CELL.read_text()
    with pytest.raises(Exception, match="sim.inter_camera_angle_deg"):
        parse_cell_file(text)
    assert json.dumps(parse_cell_file(CELL.read_text()).sim.model_dump())  # the sim section round-trips


def test_blooming_is_rendered_and_compensated():
    import numpy as np

    from calibration.models.model_matching import CameraState
    from calibration.routines.vr._common import (
        CAM,
        Estimate,
        VrParams,
        line_observations,
        load_models,
    )

    config, text = load_cell_file(CELL)
    sim = config.sim.model_copy(update={"rendering": config.sim.rendering.model_copy(update={"blooming": True})})
    config = config.model_copy(update={"sim": sim})
    with Cell(config, text) as cell:
        world = cell.sim_world
        frames = [cell.cameras[n].capture() for n in CAM]
        assert max((f.image == 255).mean() for f in frames) > 0.005  # over-exposed faces
        est = Estimate([CameraState.centred(world.cameras[n].V, world.cameras[n].f, 640, 480) for n in CAM],
                       world.oru_pose(), world.receptacle)
        params = VrParams()
        obs = line_observations(params, frames[0], 0, est, load_models(params))
        # the blooming term (eq. 12) widens the variance of the lines beside saturated faces
        variances = np.linalg.inv(obs.line_W).diagonal(axis1=1, axis2=2).max(axis=1)
        assert (variances > 4.0).any() and (variances < 1.0).any()


# the simulated VR devices honour the driver contracts


def _vr_factory(kind, options):
    context = DriverContext(sim_config=VrWorldConfig())
    return lambda: backend_class(kind, "sim-vr").create(kind, options, context)


class TestVrArmContract(ArmContract):
    @pytest.fixture
    def make_device(self):
        return _vr_factory("arm", {"limits": {"x_mm": [-1500, 1500], "y_mm": [-1500, 2500], "z_mm": [-1500, 1500]}})


class TestVrCameraContract(CameraContract):
    @pytest.fixture
    def make_device(self):
        return _vr_factory("camera", {"sim_camera": "side"})


def test_cellctl_fit_on_the_samples_file_gives_the_run_result(experiments, tmp_path):
    """`cellctl fit vr-experiments` on a run's samples.csv (reference rows have no angle_deg, and say so by
    their kind) fits the same stats and model as the run did."""
    import json

    from cellctl.cli import main

    out, result = experiments
    overrides = {"fig7_runs": 6, "n_runs": 2, "angles_deg": [28.0, 51.0], "views": [[28.0, 12.0]]}
    params = [f"--param={k}={json.dumps(v)}" for k, v in overrides.items()]
    assert main(["fit", "vr-experiments", "--samples", str(out / "samples.csv"), "--config", str(CELL),
                 "--out", str(tmp_path / "fit.json"), *params]) == 0
    fitted = json.loads((tmp_path / "fit.json").read_text())
    assert fitted["model"] == json.loads(json.dumps(result["model"]))
    assert fitted["stats"] == json.loads(json.dumps(result["stats"]))
