"""The routines are found by their files: a routine added as one file in its family's folder runs, from the CLI
to its report, with no other file touched; the sequences, the fit aliases and the judge are the families' own."""

import json
import shutil
from pathlib import Path

import pytest

import calibration.routines as registry
from calibration.errors import UnknownName
from calibration.routines import micro

from cellctl.cli import main

from tests.conftest import MICROCELL

EXAMPLE = Path(__file__).parent / "example" / "camera_noise.py"


@pytest.fixture
def example_in_micro(tmp_path, monkeypatch):
    """The micro family's folder with camera_noise.py added (a second folder on the family's __path__, so the
    source tree is left as it is for the other tests)."""
    folder = tmp_path / "micro-added"
    folder.mkdir()
    shutil.copy(EXAMPLE, folder / EXAMPLE.name)
    monkeypatch.setattr(micro, "__path__", [*micro.__path__, str(folder)])
    registry.rescan()
    yield
    monkeypatch.undo()
    registry.rescan()


def test_a_routine_added_as_one_file_runs_from_the_cli_to_its_report(example_in_micro, tmp_path):
    assert "camera-noise" in registry.routine_names()
    out = tmp_path / "run"
    assert main(["run", "camera-noise", "--config", str(MICROCELL), "--out", str(out), "--seed", "3", "--quiet",
                 "--param", "frames=5"]) == 0
    result = json.loads((out / "result.json").read_text())
    noise = result["stats"]["noise"]
    assert result["routine"] == "camera-noise" and noise["n"] == 5 and "truth" not in result
    assert 0 < noise["sd_u_px"] < 1 and 0 < noise["sd_v_px"] < 1  # a still nozzle, a camera's centroid noise
    assert "The still nozzle's centroid scatter" in (out / "report.md").read_text()
    # and its offline fit, from the samples it recorded
    assert main(["fit", "camera-noise", "--samples", str(out / "samples.csv"), "--out", str(tmp_path / "fit.json")]) == 0
    assert json.loads((tmp_path / "fit.json").read_text())["stats"] == result["stats"]


def test_without_its_file_the_routine_is_unknown():
    assert "camera-noise" not in registry.routine_names()
    with pytest.raises(UnknownName, match="unknown routine 'camera-noise'; allowed: arm-kinematics, calibration-check"):
        registry.routine_class("camera-noise")


def test_every_routine_is_its_files_name_and_every_sequence_names_routines():
    routines = registry.all_routines()
    assert all(cls.name == name for name, cls in routines.items())
    for sequence in registry.sequences().values():
        assert {item.routine for item in sequence.items} <= set(routines), sequence.name
    assert set(registry.fit_aliases().values()) <= set(routines)


def test_one_routine_judges_the_calibrations_and_says_when_to_raise_an_alarm():
    judge = registry.routine_class(registry.judging_routine())()
    assert judge.alarm({"verdict": "ok"}) is None
    drift = {"verdict": "drift", "drifted": ["cam1"], "actions": {"cam1": "touched up"}, "stats": {"drift": {}}}
    assert judge.alarm(drift)["drifted"] == ["cam1"]


def test_a_sequence_item_names_its_folder_and_refuses_an_unknown_item():
    seed = registry.sequence("seed-001")
    assert seed.folder("hybrid.area2") == "02-hybrid-area2" and seed.number("hybrid.area2") == "2/7"
    with pytest.raises(UnknownName, match="'nope' is not part of seed-001"):
        seed.folder("nope")
