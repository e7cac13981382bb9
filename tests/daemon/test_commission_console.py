"""The device self-test through the daemon: POST /cell/commission (the token, the operator lock for the move, refused
beside a job, audited), `cellctl commission` through the daemon (named, or found owning the cell's store), and the
console's Commission panel in Chromium (Playwright) running it and showing the findings table."""

from __future__ import annotations

import json

import pytest

from cellctl.cli import main

from tests.support.console import browser_page, open_console
from tests.support.daemon import SMALL, running_daemon, wait_for
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    with running_daemon(tmp_path_factory.mktemp("commission"), realtime_factor=0.0) as d:
        yield d


@pytest.fixture(scope="module")
def faulty(tmp_path_factory):
    """A cell whose vacuum has no air and whose cam3 is out of focus."""
    with running_daemon(tmp_path_factory.mktemp("commission-faulty"), realtime_factor=0.0,
                        faults={"gripper_no_air": True, "camera_blur_px": {"cam3": 8.0}}) as d:
        yield d


def slow_client(daemon):
    """The daemon's client, waiting as long as a self-test takes (frames of every camera, a move)."""
    client = daemon.client()
    client.timeout = 120.0
    return client


def row(answer: dict, device: str, check: str) -> dict:
    found = [c for c in answer["checks"] if c["device"] == device and c["check"] == check]
    assert len(found) == 1, (device, check, answer["checks"])
    return found[0]


def test_commission_is_a_command_and_the_move_needs_the_lock(daemon):
    with daemon.client(token=None) as anonymous:
        assert anonymous.post("/cell/commission", json={}).status_code == 401
    with slow_client(daemon) as c:
        r = c.post("/cell/commission", json={"move": False})
        assert r.status_code == 200, r.text
        answer = r.json()
        assert answer["problems"] == 0 and row(answer, "arm", "motion")["result"] == "skipped"
        # the move is for the holder of the operator lock only: nobody holding it is not enough
        r = c.post("/cell/commission", json={"move": True})
        assert r.status_code == 423 and "take it first" in r.json()["detail"]
        lock = c.post("/lock", json={"holder": "tester", "ttl_s": 60}).json()["lock_id"]
        try:
            r = c.post("/cell/commission", json={"move": True}, headers={"X-Cellctl-Lock": lock})
            assert r.status_code == 200, r.text
            moved = r.json()
            assert moved["problems"] == 0 and moved["moved"] is True
            assert "reported 5.000 mm" in row(moved, "arm", "motion")["figure"]
            assert row(moved, "cam3", "motion seen")["result"] == "ok"
            # another client, without the lock, is refused while it is held
            with daemon.client() as other:
                assert other.post("/cell/commission", json={}).status_code == 423
        finally:
            c.request("DELETE", "/lock", headers={"X-Cellctl-Lock": lock})
        r = c.post("/cell/commission", json={"device": "cam9"})
        assert r.status_code == 404 and "arm, gripper, cam1, cam2, cam3" in r.json()["detail"]
        r = c.post("/cell/commission", json={"move": "yes"})
        assert r.status_code == 422
        audit = [e for e in c.get("/audit").json()["audit"] if e["action"] == "POST /cell/commission"]
    outcomes = [e["outcome"] for e in audit]
    assert outcomes.count("ok") == 2 and any(o.startswith("refused 423") for o in outcomes)
    assert any(o.startswith("refused 404") for o in outcomes)
    assert any('"move_mm": 5.0' in e["detail"] for e in audit if e["outcome"] == "ok")


def test_commission_is_refused_beside_a_job_naming_it(daemon):
    with slow_client(daemon) as c:
        job = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": 5}).json()
        try:
            def refused():
                r = c.post("/cell/commission", json={})
                if r.status_code == 200:  # the job had not started yet, or had ended already
                    return None
                return r
            r = eventually(refused, timeout=30, what="a self-test refused beside the job")
            assert r.status_code == 409 and f"job {job['id']}" in r.json()["detail"], r.text
        finally:
            c.post(f"/jobs/{job['id']}/abort")
            wait_for(c, job["id"], {"aborted", "done", "faulted"})


def test_the_cli_goes_through_the_daemon(daemon, faulty, capsys, monkeypatch):
    monkeypatch.setenv("CELLCTL_TOKEN", faulty.token)
    code = main(["commission", "--url", faulty.url, "--json"])
    answer = json.loads(capsys.readouterr().out)
    assert code == 1
    assert "check the air supply" in row(answer, "gripper", "grip with nothing held")["finding"]
    assert "focus cam3's lens" in row(answer, "cam3", "focus")["finding"]
    # the move, confirmed: the CLI takes the free lock for the one command, as jog does, and gives it back
    code = main(["commission", "--url", faulty.url, "--device", "arm", "--move", "--json"])
    answer = json.loads(capsys.readouterr().out)
    assert answer["moved"] and row(answer, "arm", "motion")["result"] == "ok", answer
    with faulty.client() as c:
        assert c.get("/lock").json() == {"held": False}
    # no --url: the daemon that owns the cell's store runs it
    monkeypatch.delenv("CELLCTL_TOKEN")
    code = main(["commission", "--config", str(daemon.cell_file), "--store", str(daemon.store), "--device", "gripper"])
    captured = capsys.readouterr()
    assert code == 0 and "owned by the daemon" in captured.err and "0 problems found" in captured.out


@pytest.fixture
def page(browser):
    with browser_page(browser, 60_000) as page:
        yield page


def test_the_console_panel_runs_the_self_test_and_shows_the_findings(faulty, page, tmp_path):
    open_console(page, faulty)
    page.fill("#token-input", faulty.token)
    page.click("#token-form button")
    page.wait_for_selector("#commission-device option[value='cam3']", state="attached")
    page.check("#commission-move")
    page.click("#commission-run")
    page.wait_for_selector("#commission-checks:not([hidden]) tbody tr")
    cells = page.eval_on_selector_all("#commission-checks tbody tr",
                                      "rows => rows.map(r => [...r.cells].map(c => c.textContent))")
    by_check = {(d, check): (result, finding) for d, check, result, _figure, finding in cells}
    assert by_check[("gripper", "grip with nothing held")][0] == "problem"
    assert "check the air supply" in by_check[("gripper", "grip with nothing held")][1]
    assert by_check[("cam3", "focus")][0] == "problem" and "focus cam3's lens" in by_check[("cam3", "focus")][1]
    assert by_check[("arm", "motion")][0] == "ok"  # moved: the box was ticked
    assert "2 problems found" in page.text_content("#commission-summary")
    assert page.eval_on_selector("td.result-problem", "c => getComputedStyle(c).color") == "rgb(198, 40, 40)"
    page.screenshot(path=tmp_path / "commission.png", full_page=True)
    # one device: the table shows its checks only
    page.select_option("#commission-device", "cam2")
    page.uncheck("#commission-move")
    page.click("#commission-run")
    page.wait_for_function("document.querySelector('#commission-summary').textContent.includes(': cam2, without')")
    devices = set(page.eval_on_selector_all("#commission-checks tbody tr", "rows => rows.map(r => r.cells[0]"
                                                                           ".textContent)"))
    assert devices == {"cam2", "arm"}
    assert not page.errors
