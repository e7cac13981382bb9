"""Manual motion on the real daemon (the simulated micro cell): a jog moves the arm by the asked amount, a refused
one moves nothing, the lock holder alone may move, a held jog stops when released or when its heartbeats stop,
never beside a job; every move audited."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.support.daemon import SMALL, running_daemon, wait_for
from tests.support.wait import eventually

HEARTBEAT_TIMEOUT_S = 2.0  # the longest the cell file allows


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    # the tests heartbeat over HTTP from a machine that may be busy: a long time-out, not 0.15 s, so a slow beat
    # does not stop a move the test means to stop itself (tests/daemon/test_jog_console.py: the default's figure)
    with running_daemon(tmp_path_factory.mktemp("manual"), realtime_factor=0.0,
                        manual={"heartbeat_timeout_s": HEARTBEAT_TIMEOUT_S}) as d:
        yield d


@pytest.fixture()
def operator(daemon):
    """A client holding the operator lock (released after)."""
    with daemon.client(**{"X-Cellctl-Client": "jogger"}) as c:
        lock = c.post("/lock", json={"holder": "jogger", "ttl_s": 120}).json()["lock_id"]
        c.headers["X-Cellctl-Lock"] = lock
        yield c
        c.delete("/lock")


def pose(c) -> dict:
    """The arm's reported pose (without the time it was read)."""
    return {k: v for k, v in c.get("/cell").json()["arm_pose"].items() if k != "read_at"}


def ended(c, motion: int, alive: bool = True) -> dict:
    """The move's end, its client present meanwhile (`alive`: the dead-man heartbeat) or gone."""
    def last():
        got = c.post(f"/manual/moves/{motion}/alive").json() if alive else c.get("/manual").json()["last"]
        return got if got and got["motion"] == motion and got["state"] != "moving" else None
    return eventually(last, timeout=60, what=f"manual move {motion} to end")


def test_a_step_jog_moves_the_arm_by_the_asked_amount(operator):
    before = pose(operator)
    r = operator.post("/manual/jog", json={"axis": "x", "distance": 2.5})
    assert r.status_code == 200, r.text
    end = ended(operator, r.json()["motion"])
    assert end["state"] == "done", end
    after = pose(operator)
    assert after["x_mm"] - before["x_mm"] == pytest.approx(2.5, abs=1e-3)  # the reported pose: 0.1 µm encoders
    assert after["y_mm"] == pytest.approx(before["y_mm"], abs=1e-3)
    assert after["z_mm"] == pytest.approx(before["z_mm"], abs=1e-3)
    r = operator.post("/manual/jog", json={"axis": "rz", "distance": -5, "frame": "tool"})
    assert ended(operator, r.json()["motion"])["state"] == "done"
    assert pose(operator)["alpha_deg"] == pytest.approx(before["alpha_deg"] - 5, abs=1e-6)


def test_a_tool_frame_jog_follows_the_tool(operator):
    r = operator.post("/manual/move-to", json={"pose": {"x_mm": 40, "y_mm": 30, "z_mm": 20, "alpha_deg": 90}})
    assert r.status_code == 200, r.text
    ended(operator, r.json()["motion"])
    before = pose(operator)
    ended(operator, operator.post("/manual/jog", json={"axis": "x", "distance": 3, "frame": "tool"}).json()["motion"])
    after = pose(operator)
    # the tool's x turned by 90 degrees is the cell's y
    assert after["x_mm"] == pytest.approx(before["x_mm"], abs=1e-3)
    assert after["y_mm"] - before["y_mm"] == pytest.approx(3.0, abs=1e-3)


@pytest.mark.parametrize("body, says", [
    ({"axis": "z", "distance": 45}, "outside the workspace box"),  # home z 20 + 45 > 40
    ({"axis": "x", "distance": 60}, "max_step_mm"),
    ({"axis": "x", "distance": 1, "speed_pct": 50}, "manual cap"),
    ({"axis": "rx", "distance": 5}, "turns about the vertical only"),
])
def test_a_refused_jog_moves_nothing(operator, body, says):
    before = pose(operator)
    r = operator.post("/manual/jog", json=body)
    assert r.status_code == 422, r.text
    assert says in r.text and "nothing moved" in r.text
    assert pose(operator) == before


def test_only_the_lock_holder_moves_the_arm(daemon):
    with daemon.client(**{"X-Cellctl-Client": "passer-by"}) as c:
        before = pose(c)
        r = c.post("/manual/jog", json={"axis": "x", "distance": 1})
        assert r.status_code == 423 and "take it first" in r.text
        assert c.post("/gripper/grip").status_code == 423
        assert pose(c) == before
        audit = c.get("/audit").json()["audit"]
    assert any(a["action"] == "POST /manual/jog" and a["outcome"].startswith("refused 423") for a in audit)


def test_a_held_jog_stops_when_released_and_when_its_heartbeat_stops(operator):
    settings = operator.get("/manual").json()
    assert settings["speed_mm_s"] == pytest.approx(10.0)  # 10 % of the simulated arm's 100 mm/s
    ended(operator, operator.post("/manual/move-to", json={"position": None, "pose": {
        "x_mm": 40, "y_mm": 30, "z_mm": 20}}).json()["motion"])
    r = operator.post("/manual/jog", json={"axis": "y", "direction": 1})
    motion = r.json()["motion"]
    # held: it goes on while the heartbeat comes, until released
    eventually(lambda: operator.post(f"/manual/moves/{motion}/alive").json()["sent"] >= 10, timeout=30,
               what="ten segments of the held jog")
    operator.post(f"/manual/moves/{motion}/stop")
    end = ended(operator, motion)
    assert end["stopped_by"] == "released" and end["state"] == "stopped"
    assert end["coast_s"] <= 0.05  # of motion after the release: at most the segment under way
    assert end["delta_mm"][1] == pytest.approx(end["sent"] * 10.0 * 0.05, rel=0.02)  # 10 mm/s, 50 ms segments
    # a client that goes away: no heartbeat, the dead-man stops it
    r = operator.post("/manual/jog", json={"axis": "y", "direction": -1})
    end = ended(operator, r.json()["motion"], alive=False)
    assert end["stopped_by"] == "heartbeat lost" and end["coast_s"] <= HEARTBEAT_TIMEOUT_S + 0.05
    assert abs(end["delta_mm"][1]) <= 10.0 * (HEARTBEAT_TIMEOUT_S + 0.05) + 1e-6
    audit = operator.get("/audit").json()["audit"]
    assert any(a["action"] == "manual move end" and a["target"] == f"manual move {motion}" for a in audit)


def test_no_manual_motion_beside_a_job(operator):
    job = operator.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": 1}).json()["id"]
    try:
        eventually(lambda: operator.get(f"/jobs/{job}").json()["state"] != "queued", what="the job to start")
        r = operator.post("/manual/jog", json={"axis": "x", "distance": 1})
        if operator.get(f"/jobs/{job}").json()["state"] == "running":  # else it ended first: nothing to check
            assert r.status_code == 409 and f"job {job}" in r.text
    finally:
        operator.post(f"/jobs/{job}/abort")
        wait_for(operator, job, {"done", "aborted", "faulted"})


def test_grip_and_release_by_hand(operator):
    got = operator.post("/gripper/grip")
    assert got.status_code == 200, got.text
    assert got.json()["vacuum"] == "on"
    got = operator.post("/gripper/release").json()
    assert got["vacuum"] == "off" and not got["gripping"]
    assert math.isfinite(got["vacuum_kpa"])


def test_the_cli_jogs_moves_to_and_grips_with_the_same_checks(daemon, capsys, monkeypatch):
    from cellctl import cli

    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    monkeypatch.delenv("CELLCTL_LOCK", raising=False)
    with daemon.client() as c:
        assert cli.main(["move-to", "40", "30", "20"]) == 0
        before = pose(c)
        assert cli.main(["jog", "y", "-1.5"]) == 0  # the lock taken for the command, and given back
        out = capsys.readouterr().out
        assert "y -1.500 mm (cell frame): done" in out
        assert pose(c)["y_mm"] - before["y_mm"] == pytest.approx(-1.5, abs=1e-3)
        assert c.get("/lock").json() == {"held": False}
        assert cli.main(["jog", "z", "30"]) == 2  # beyond the box: refused, nothing moved
        assert "outside the workspace box" in capsys.readouterr().err
        assert pose(c)["z_mm"] == pytest.approx(before["z_mm"], abs=1e-3)
        assert cli.main(["grip"]) == 0 and "vacuum on" in capsys.readouterr().out
        assert cli.main(["release"]) == 0 and "vacuum off" in capsys.readouterr().out
        # someone else holds the lock: refused, naming them
        lock = c.post("/lock", json={"holder": "bob", "ttl_s": 60}).json()["lock_id"]
        assert cli.main(["jog", "x", "1"]) == 2 and "bob" in capsys.readouterr().err
        c.request("DELETE", "/lock", headers={"X-Cellctl-Lock": lock})


def test_a_six_axis_arm_jogs_in_its_tool_frame_and_refuses_what_it_cannot_reach(tmp_path):
    from drivers.interfaces import Pose

    from cellctl.core.manual_path import rotation_of

    from tests.conftest import ROOT
    from tests.support.daemon import DaemonProcess

    cell = tmp_path / "ur5e.yaml"
    cell.write_text(f"extends: {ROOT / 'config' / 'sim-ur5e-handeye.yaml'}\nstore_dir: {tmp_path / 'store'}\n"
                    f"manual: {{heartbeat_timeout_s: {HEARTBEAT_TIMEOUT_S}}}\n")
    with DaemonProcess(cell).start(timeout=120) as d, d.client() as c:
        c.headers["X-Cellctl-Lock"] = c.post("/lock", json={"holder": "me", "ttl_s": 120}).json()["lock_id"]
        assert c.get("/manual").json()["axes"] == ["x", "y", "z", "rx", "ry", "rz"]

        def now() -> Pose:
            p = c.get("/cell").json()["arm_pose"]
            return Pose(p["x_mm"] * 1e-3, p["y_mm"] * 1e-3, p["z_mm"] * 1e-3, 0.0, tuple(p["orientation_wxyz"]))

        before = now()
        end = ended(c, c.post("/manual/jog", json={"axis": "z", "distance": 5, "frame": "tool"}).json()["motion"])
        assert end["state"] == "done", end
        after = now()  # along the tool's own z (pointing down): the flange goes 5 mm down
        assert np.allclose((after.xyz - before.xyz) * 1e3, rotation_of(before).as_matrix()[:, 2] * 5, atol=1e-3)
        end = ended(c, c.post("/manual/jog", json={"axis": "rx", "distance": 10, "frame": "tool"}).json()["motion"])
        turned = now()
        assert np.allclose(turned.xyz, after.xyz, atol=1e-6)
        assert math.degrees((rotation_of(after).inv() * rotation_of(turned)).magnitude()) == pytest.approx(10, abs=1e-3)
        # inside the box, beyond the arm's reach: refused before anything moves
        r = c.post("/manual/move-to", json={"pose": {"x_mm": 880, "y_mm": 0, "z_mm": 100}})
        assert r.status_code == 422 and "out of reach" in r.text and "nothing moved" in r.text, r.text
        assert np.allclose(now().xyz, turned.xyz)
