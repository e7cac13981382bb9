"""`cellctl camera CAM`: a live snapshot as PNG (written atomically), exposure and gain set with their ranges checked,
and the settings written back to the cell file after its diff, against the real daemon on the simulated micro cell."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from cellctl.cli import main

from tests.support.daemon import ROOT, DaemonProcess


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    """The micro cell's file as written (its comments and flow mappings kept), its store in the test's folder."""
    folder = tmp_path_factory.mktemp("camera-cli")
    cell_file = folder / "cell.yaml"
    cell_file.write_text((ROOT / "config" / "sim-microcell.yaml").read_text() + f"\nstore_dir: {folder / 'store'}\n")
    with DaemonProcess(cell_file).start() as d:
        yield d


@pytest.fixture
def cli(daemon, monkeypatch):
    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    monkeypatch.delenv("CELLCTL_LOCK", raising=False)
    return lambda *args: main(["camera", *[str(a) for a in args]])


def test_snapshot_writes_a_png_of_the_live_frame(cli, daemon, tmp_path, capsys):
    out = tmp_path / "cam3.png"
    assert cli("cam3", "--snapshot", out) == 0
    said = capsys.readouterr().out
    assert f"written to {out}" in said and "saturated 0 px" in said
    image = cv2.imread(str(out), cv2.IMREAD_COLOR)
    assert image.shape[:2] == (1944, 2592)  # full size, drawn in colour
    assert (np.ptp(image.astype(int), axis=2) > 60).any()  # the feature found is drawn (green)
    assert not [p for p in tmp_path.iterdir() if p.name != "cam3.png"]  # no temporary file left
    plain = tmp_path / "plain.png"
    assert cli("cam3", "--snapshot", plain, "--layers", "none", "--width", 640, "--json") == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["snapshot"]["stats"]["width"] == 2592 and "features" not in answer["snapshot"]["stats"]
    image = cv2.imread(str(plain), cv2.IMREAD_UNCHANGED)
    assert image.shape[1] == 640 and (image.ndim == 2 or not (np.ptp(image.astype(int), axis=2) > 0).any())


def test_a_snapshot_of_an_unknown_camera_or_to_an_unwritable_path_is_a_clear_error(cli, tmp_path, capsys):
    assert cli("cam9", "--snapshot", tmp_path / "x.png") == 2
    err = capsys.readouterr().err
    assert "no camera 'cam9'" in err and "cam1, cam2, cam3" in err
    assert cli("cam1", "--snapshot", tmp_path / "missing" / "x.png") == 2
    assert "does not exist" in capsys.readouterr().err
    assert cli("cam1", "--snapshot", tmp_path) == 2
    assert "is a folder" in capsys.readouterr().err
    assert cli("cam1", "--layers", "bogus", "--snapshot", tmp_path / "y.png") == 2
    assert "allowed: features, grid, saturation" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_settings_are_checked_set_and_written_back_after_the_diff(cli, daemon, capsys):
    before = daemon.cell_file.read_text()
    assert cli("cam2", "--set", "exposure_s=20") == 2
    assert "exposure_s: 20; allowed: 1e-05 to 10 s" in capsys.readouterr().err
    assert cli("cam2", "--set", "gain_db=-3") == 2
    assert "gain_db: -3; allowed: 0 to 48 dB" in capsys.readouterr().err
    assert cli("cam2", "--set", "focus=3") == 2
    assert "focus: not a setting this camera changes live" in capsys.readouterr().err

    assert cli("cam2", "--set", "exposure_s=0.3", "--json") == 0
    exposure = json.loads(capsys.readouterr().out)["settings"]["settings"]["exposure_s"]
    assert exposure["value"] == 0.3 and exposure["changed"] and exposure["in_file"] is None
    assert cli("cam2", "--snapshot", daemon.cell_file.parent / "bright.png", "--json") == 0
    stats = json.loads(capsys.readouterr().out)["snapshot"]["stats"]
    assert stats["saturated_pct"] > 50 and stats["exposure_s"] == 0.3  # 30 times the light: saturated

    assert cli("cam2", "--save") == 0
    said = capsys.readouterr().out
    assert "+  cam2: {backend: sim, exposure_s: 0.3}" in said and "(add --yes)" in said
    assert daemon.cell_file.read_text() == before  # shown, not written
    assert cli("cam2", "--save", "--yes") == 0
    assert "written to" in capsys.readouterr().out
    after = daemon.cell_file.read_text()
    changed = [(a, b) for a, b in zip(before.splitlines(), after.splitlines()) if a != b]
    assert len(before.splitlines()) == len(after.splitlines()) and len(changed) == 1, changed
    assert changed[0] == ("  cam2: {backend: sim}   # top view of area2",
                          "  cam2: {backend: sim, exposure_s: 0.3}   # top view of area2")  # its comment kept
    with daemon.client() as c:
        audit = c.get("/audit").json()["audit"]
    assert any(a["action"] == "cli camera" or "settings/save" in a["action"] for a in audit)
    assert [a for a in audit if a["target"].startswith("camera cam2 in ")][-1]["outcome"] == "ok"
    assert cli("cam2", "--save") == 0  # the file now says what the camera uses
    assert "nothing to write" in capsys.readouterr().out
