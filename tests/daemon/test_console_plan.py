"""The plan of a routine that plans its own motion (hand-eye), shown before anything moves: in the web console (a
real Chromium) and over the HTTP API, against the real daemon on the simulated UR5e hand-eye cell. A region out
of reach is refused in words; nothing moves either way."""

from __future__ import annotations

import json

import pytest
import yaml

from tests.conftest import ROOT
from tests.support.console import open_console
from tests.support.daemon import DaemonProcess

pytestmark = pytest.mark.long  # run first: see conftest.py


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    folder = tmp_path_factory.mktemp("plan")
    data = yaml.safe_load((ROOT / "config" / "sim-ur5e-handeye.yaml").read_text())
    data["store_dir"] = str(folder / "store")
    cell_file = folder / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(data))
    with DaemonProcess(cell_file).start() as d:
        yield d


def test_the_console_shows_the_hand_eye_plan_before_anything_moves(daemon, browser, tmp_path):
    page = browser.new_context(viewport={"width": 1400, "height": 1000}).new_page()
    page.set_default_timeout(30_000)
    open_console(page, daemon)
    with daemon.client(token=None) as c:
        before = {k: v for k, v in c.get("/cell").json()["arm_pose"].items() if k != "read_at"}
    page.select_option("#routine", "virtual-grid")
    assert page.is_hidden("#plan")  # a routine that plans no motion of its own has no plan to show
    page.select_option("#routine", "hand-eye")
    page.fill("#param-poses", "12")
    page.click("#plan")
    page.wait_for_selector("#plan-box table")
    rows = page.locator("#plan-box tbody tr")
    assert rows.count() == 12 + 5  # the calibration poses and the held-out ones
    assert page.locator("#plan-box tbody tr").first.locator("td").first.text_content() == "p01"
    assert "rotation-axis spread" in page.text_content("#plan-box")
    page.screenshot(path=tmp_path / "plan.png", full_page=True)

    page.fill("#param-target_mm", "[-1500, 0, 0]")  # out of the UR5e's reach
    page.click("#plan")
    page.wait_for_selector("#plan-box .error")
    assert "out of reach" in page.text_content("#plan-box .error")
    with daemon.client(token=None) as c:
        after = {k: v for k, v in c.get("/cell").json()["arm_pose"].items() if k != "read_at"}
        assert after == before and c.get("/jobs").json() == {"jobs": []}


def test_the_plan_over_http_is_read_only_and_refuses_what_it_cannot_plan(daemon):
    with daemon.client(token=None) as c:  # no token: it changes nothing
        plan = c.get("/routines/hand-eye/plan", params={"params": json.dumps({"poses": 8, "verify_poses": 2})})
        assert plan.status_code == 200, plan.text
        assert [r[0] for r in plan.json()["tables"][0]["rows"]][:2] == ["p01", "p02"]
        assert len(plan.json()["tables"][0]["rows"]) == 10
        assert c.get("/routines/virtual-grid/plan").status_code == 404
        bad = c.get("/routines/hand-eye/plan", params={"params": "{not json"})
        assert bad.status_code == 422 and "params: not JSON" in bad.json()["detail"]
        far = c.get("/routines/hand-eye/plan", params={"params": json.dumps({"target_mm": [-1500, 0, 0]})})
        assert far.status_code == 422 and "out of reach" in far.json()["detail"]
