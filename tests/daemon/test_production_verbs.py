"""The production verbs through the real daemon, on a store calibrated by calibrate-cell (seed 5): a pick-place job
from the job queue, what camera 2 then sees (features) and where a pixel is (locate), over HTTP and the CLI; a
pick-place job the cell cannot do is refused at submit (422 naming the parameter) and nothing is queued."""

from __future__ import annotations

import json
import math

import pytest

from tests.support.daemon import running_daemon, wait_for

TARGET = {"x_mm": 112.0, "y_mm": 38.0, "alpha_deg": -140.0}


@pytest.fixture(scope="module")
def daemon(tmp_path_factory, calibrated_cell):
    with running_daemon(tmp_path_factory.mktemp("production"), calibrated_cell.store_path, realtime_factor=0.0) as d:
        yield d


def test_pick_place_runs_from_the_queue_and_camera_2_then_sees_the_part(daemon):
    with daemon.client() as c:
        job = c.post("/jobs", json={"routine": "pick-place", "params": TARGET, "seed": 5})
        assert job.status_code == 201, job.text
        done = wait_for(c, job.json()["id"], {"done", "faulted"})
        assert done["state"] == "done", done
        result = c.get(f"/jobs/{done['id']}/result").json()
        assert result["stats"]["verification"]["n"] == 1 and result["stats"]["verification"]["mean_um"] <= 25.0
        seen = c.get("/cameras/cam2/features").json()
        assert set(seen) == {"camera", "frame_id", "captured", "features"} and seen["camera"] == "cam2"
        part = min(seen["features"], key=lambda f: math.hypot(f["x_mm"] - TARGET["x_mm"], f["y_mm"] - TARGET["y_mm"]))
        assert set(part) == {"kind", "u_px", "v_px", "x_mm", "y_mm", "sigma_um", "outside_calibrated_region",
                             "diameter_px"}
        assert part["kind"] == "sphere" and part["sigma_um"] > 0
        assert math.hypot(part["x_mm"] - TARGET["x_mm"], part["y_mm"] - TARGET["y_mm"]) < 0.03
        where = c.get("/locate", params={"camera": "cam2", "u_px": part["u_px"], "v_px": part["v_px"],
                                         "diameter_px": part["diameter_px"]}).json()
        assert (where["x_mm"], where["y_mm"], where["sigma_um"]) == (part["x_mm"], part["y_mm"], part["sigma_um"])
        cams = {cal["target"]: cal for cal in c.get("/calibrations").json()["calibrations"] if cal["active"]}
        assert where["calibration_id"] == cams["cam2"]["id"] and where["version"] == cams["cam2"]["version"]
        assert where["health"] == "unchecked"
        assert c.get("/cameras/cam9/features").status_code == 404
        assert c.get("/locate", params={"camera": "cam2", "u_px": 1, "v_px": 2, "diameter_px": -3}).status_code == 422


@pytest.mark.parametrize("params, named", [
    ({"x_mm": 150.0, "y_mm": 40.0}, "x_mm: 150 is outside area area2"),
    ({"x_mm": 110.0, "y_mm": 40.0, "alpha_deg": 400}, "alpha_deg"),
    ({"x_mm": 110.0, "y_mm": 40.0, "pick_mm": [70.0, 500.0]}, "pick_mm: y_mm: 500 is outside the arm's limits"),
])
def test_a_job_the_cell_cannot_do_is_refused_at_submit(daemon, params, named):
    with daemon.client() as c:
        before = c.get("/jobs").json()
        r = c.post("/jobs", json={"routine": "pick-place", "params": params})
        assert r.status_code == 422 and named in r.json()["detail"]
        assert c.get("/jobs").json() == before


def test_cli_features_and_locate(daemon, capsys, monkeypatch):
    from cellctl import cli as client

    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    assert client.main(["features", "cam2"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("cam2: frame") and "sphere" in out
    assert client.main(["locate", "--camera", "cam1", "--pixel", "1224", "1025"]) == 0
    out = capsys.readouterr().out
    assert "sigma_um=" in out and "health: unchecked" in out
    assert client.main(["features", "cam9"]) == 2
    assert "cam9" in capsys.readouterr().err


def test_locate_off_the_image_unknown_cameras_and_outside_the_calibrated_region(daemon, capsys, monkeypatch):
    """The service's answers on every front end here: a pixel off the image is refused (422, exit 2) naming it and
    the image's size; an unknown camera is 404 naming the cameras; a pixel outside the calibrated region is
    answered with a warning and its grown sigma (JSON fields; the CLI's line and a warning on stderr)."""
    from cellctl import cli as client

    with daemon.client() as c:
        r = c.get("/locate", params={"camera": "cam9", "u_px": 1, "v_px": 1})
        assert r.status_code == 404 and r.json()["detail"] == "no camera 'cam9'; cameras: cam1, cam2, cam3"
        r = c.get("/locate", params={"camera": "cam1", "u_px": 99999, "v_px": -5})
        assert r.status_code == 422
        assert r.json()["detail"].startswith("pixel (99999, -5) is outside cam1's 2448 x 2050 image")
        centre = c.get("/locate", params={"camera": "cam1", "u_px": 1224, "v_px": 1025}).json()
        corner = c.get("/locate", params={"camera": "cam1", "u_px": 3, "v_px": 3}).json()
        assert centre["outside_calibrated_region"] is False and centre["warning"] is None
        assert corner["outside_calibrated_region"] is True and "outside the calibrated region" in corner["warning"]
        assert corner["sigma_um"] > centre["sigma_um"]

    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    capsys.readouterr()
    assert client.main(["locate", "--camera", "cam1", "--pixel", "99999", "-5"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "pixel (99999, -5) is outside cam1's 2448 x 2050 image" in err
    assert client.main(["locate", "--camera", "cam1", "--pixel", "3", "3"]) == 0
    out, err = capsys.readouterr()
    assert "calibrated region: outside" in out and "warning: outside the calibrated region" in err
    assert client.main(["locate", "--camera", "cam1", "--pixel", "3", "3", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["outside_calibrated_region"] is True
    assert client.main(["locate", "--camera", "cam9", "--pixel", "3", "3"]) == 2
    assert "no camera 'cam9'; cameras: cam1, cam2, cam3" in capsys.readouterr().err
