"""The console's jog panel in Chromium (Playwright), on the simulated micro cell in-process and through the UR and
ABB protocol simulators: a step moves the arm by the asked amount, a held button moves it until released and then
stops within 200 ms of motion, a closed tab stops it the same way, and a refused jog moves nothing."""

from __future__ import annotations

import pytest

from tests.conftest import ROOT
from tests.support.cells import write_abb_cell_file, write_ur_cell_file
from tests.support.console import browser_page, open_console
from tests.support.daemon import DaemonProcess
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py



# the page heartbeats every 40 ms; on a busy machine a beat can be late by more than the default 0.15 s, which
# would stop a move the test means to stop itself: a long time-out here (the default's figure: test_manual_motion.py)
PATIENT = "manual: {heartbeat_timeout_s: 2.0}\n"


def sim_cell(folder):
    path = folder / "sim.yaml"
    path.write_text(f"extends: {ROOT / 'config' / 'sim-microcell.yaml'}\nstore_dir: {folder / 'store'}\n{PATIENT}")
    return path


def ur_cell(folder):
    path = write_ur_cell_file(folder)
    path.write_text(path.read_text() + PATIENT)
    return path


def abb_cell(folder):
    return write_abb_cell_file(folder, extra=f"store_dir: {folder / 'store'}\n{PATIENT}")


@pytest.fixture(scope="module", params=[sim_cell, ur_cell, abb_cell], ids=["sim", "ur", "abb"])
def daemon(request, tmp_path_factory):
    with DaemonProcess(request.param(tmp_path_factory.mktemp("jog"))).start(timeout=120) as d:
        yield d


def with_token(page, daemon):
    open_console(page, daemon)
    page.fill("#token-input", daemon.token)
    page.click("#token-form button")
    page.wait_for_selector("#jog-axes button")
    return page


def pose(c) -> dict:
    return {k: v for k, v in c.get("/cell").json()["arm_pose"].items() if k != "read_at"}


def page_idle(page) -> None:
    """The page has seen its move end (it takes the next click only then)."""
    page.wait_for_function("!document.querySelector('#jog-axes button.moving')")


def last_move(c, after: int = 0) -> dict:
    def ended():
        got = c.get("/manual").json()
        last = got["last"]
        return last if got["current"] is None and last and last["motion"] > after else None
    return eventually(ended, timeout=60, what="the manual move to end")


def moving(c) -> dict:
    return eventually(lambda: (c.get("/manual").json()["current"] or {}).get("sent", 0) >= 3 and
                      c.get("/manual").json()["current"], timeout=60, what="a held jog to move")


def button(page, axis: str, sign: str):
    return page.locator(f"#jog-axes button[data-axis='{axis}'][data-dir='{1 if sign == '+' else -1}']")


def hold(page, target) -> None:
    box = target.bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()


def test_jog_in_the_console(daemon, browser):
    c = daemon.client()
    with browser_page(browser) as page:
        with_token(page, daemon)
        # a step: the arm moves by the asked amount
        page.select_option("#jog-mode", "step")
        page.select_option("#jog-step", "1")
        before = pose(c)
        button(page, "x", "+").click()
        end = last_move(c)
        assert end["state"] == "done", end
        after = pose(c)
        assert after["x_mm"] - before["x_mm"] == pytest.approx(1.0, abs=0.01)
        assert after["y_mm"] == pytest.approx(before["y_mm"], abs=0.01)

        # a refused step (beyond the workspace box, z at most 40 mm): said on the page, nothing moves
        page.select_option("#jog-step", "10")
        page_idle(page)
        button(page, "z", "+").click()  # home z 20 -> 30
        last = last_move(c, end["motion"])
        page_idle(page)
        button(page, "z", "+").click()  # 30 -> 40
        last = last_move(c, last["motion"])
        page_idle(page)
        at_top = pose(c)
        button(page, "z", "+").click()  # 40 -> 50: outside
        page.wait_for_function("document.querySelector('#jog-state').classList.contains('error')")
        assert "outside the workspace box" in page.text_content("#jog-state")
        assert pose(c) == at_top

        # held: moves while the button is down, stops within 200 ms of motion once released
        page_idle(page)
        page.select_option("#jog-mode", "hold")
        settings = c.get("/manual").json()  # at most 10 mm/s: a held jog far from the box edge for seconds
        slow = f"{min(settings['speed_pct'], 10.0 * settings['speed_pct'] / settings['speed_mm_s']):g}"
        page.fill("#jog-speed", slow)
        hold(page, button(page, "y", "+"))
        held = moving(c)
        page.mouse.up()
        end = last_move(c, last["motion"])
        assert end["motion"] == held["motion"] and end["stopped_by"] == "released", end
        assert end["coast_s"] <= 0.05 and end["delta_mm"][1] > 0  # at most the segment under way
        assert c.get("/manual").json()["current"] is None
        still = pose(c)
        assert pose(c) == still  # nothing moves after the stop
        assert not page.errors

    # a tab closed while a button is held: the page's last word stops the move (a tab that could not say it: the
    # dead-man, tests/unit/test_manual_motion.py)
    with browser_page(browser) as page:
        with_token(page, daemon)
        page.fill("#jog-speed", slow)  # seconds from the box's edge, however long a loaded machine takes to close
        hold(page, button(page, "y", "-"))
        held = moving(c)
        page.close()
    end = last_move(c, held["motion"] - 1)
    assert end["motion"] == held["motion"]
    if end["stopped_by"] == "released":  # the page's last word
        assert end["coast_s"] <= 0.05, end
    else:  # a browser starved of the CPU past the heartbeat time-out (seen beside a loaded suite): the dead-man's
        # stop, after the time-out (PATIENT here) and the segment under way at most
        assert end["stopped_by"] == "heartbeat lost" and end["coast_s"] <= 2.0 + 0.05, end
    c.close()
