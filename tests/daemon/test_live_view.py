"""The live camera view in a real browser (Debian's chromium through Playwright), against the real daemon: on the
simulated micro cell, and on the micro cell driven through the ABB and the UR protocol simulators (the real ABB
and VGC10, UR and EPick drivers against loopback simulators on this worker's ports, or address for UR). Frames arrive and change; a longer exposure saturates
pixels, which the page reports and the histogram shows; a value out of range is refused with its range; the
settings are written back to the cell file after the diff (or refused, naming the file, where the cell file
`extends:` the one that has the camera); a stream stops when its client goes away and when a job starts, and a
live view asked for while a job uses the cell is refused naming the job."""

from __future__ import annotations

import json
import os
import time

import cv2
import numpy as np
import pytest

from tests.support.cells import write_abb_cell_file
from tests.support.console import browser_page, open_console
from tests.support.daemon import ROOT, DaemonProcess, wait_for
from tests.support.ports import free_ports
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py

SMALL = {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1}


@pytest.fixture(scope="module")
def micro(tmp_path_factory):
    """The micro cell's file as written (comments, flow mappings), a job taking a few seconds of wall time."""
    folder = tmp_path_factory.mktemp("live-micro")
    text = (ROOT / "config" / "sim-microcell.yaml").read_text()
    text = text.replace("settle_s: 0.25,", "settle_s: 0.25, realtime_factor: 0.5,")
    assert "realtime_factor: 0.5" in text
    cell_file = folder / "cell.yaml"
    cell_file.write_text(text + f"\nstore_dir: {folder / 'store'}\n")
    with DaemonProcess(cell_file).start() as d:
        yield d


def write_ur_cell_file(folder) -> object:
    """config/sim-microcell-ur.yaml on a loopback address of this test worker's own: the UR simulator's ports are
    fixed (those of a real controller), so each worker's UR cell listens on another address of 127/8."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    host = f"127.0.29.{10 + worker % 200}"
    epick, = free_ports(1, host)
    path = folder / "ur.yaml"
    path.write_text(f"extends: {ROOT / 'config' / 'sim-microcell-ur.yaml'}\nstore_dir: {folder / 'store'}\n"
                    f"arm: {{host: {host}}}\ngripper: {{host: {host}, port: {epick}}}\n"
                    f"sim:\n  servers:\n    - {{protocol: ur, host: {host}}}\n"
                    f"    - {{protocol: epick, host: {host}, port: {epick}}}\n")
    return path


@pytest.fixture(scope="module", params=["abb", "ur"])
def driven(request, tmp_path_factory):
    """The micro cell through a protocol simulator: ABB (and a VGC10) or UR (and an EPick)."""
    folder = tmp_path_factory.mktemp(f"live-{request.param}")
    cell_file = (write_abb_cell_file(folder, extra=f"store_dir: {folder / 'store'}") if request.param == "abb"
                 else write_ur_cell_file(folder))
    with DaemonProcess(cell_file).start(timeout=120) as d:
        d.arm_backend = request.param
        yield d


@pytest.fixture
def page(browser):
    with browser_page(browser) as page:
        yield page


def go_live(page, daemon, camera: str) -> None:
    open_console(page, daemon)
    page.fill("#token-input", daemon.token)
    page.click("#token-form button")
    page.wait_for_selector(f"#live-camera option[value='{camera}']", state="attached")
    page.select_option("#live-camera", camera)
    page.wait_for_selector("#live-set-exposure_s")
    page.click("#live-start")


def frame_id(page) -> int:
    return int(page.evaluate("document.querySelector('#live-image').dataset.frame || '-1'"))


def wait_frames(page, n: int) -> int:
    """Waits until `n` more frames have been shown; the last frame's id."""
    start = frame_id(page)
    page.wait_for_function(f"Number(document.querySelector('#live-image').dataset.frame || -1) >= {start + n}")
    return frame_id(page)


def saturated_pct(page) -> float:
    return float(page.evaluate("document.querySelector('#live-saturated').dataset.pct || '-1'"))


def shown(page, tmp_path, name: str) -> np.ndarray:
    path = tmp_path / f"{name}.png"
    page.locator("#live-image").screenshot(path=path)
    return cv2.imread(str(path), cv2.IMREAD_COLOR).astype(int)


def live_frame_id(daemon, camera: str) -> int:
    """A frame taken now over HTTP: its id counts the camera's captures (the daemon's own, the stream's too)."""
    with daemon.client(token=None) as c:
        r = c.get(f"/cameras/{camera}/live.jpg", params={"layers": "none", "width": 64})
        assert r.status_code == 200, r.text
        return int(r.headers["X-Frame-Id"])


def frames_arrive_change_and_saturate(page, daemon, camera: str, tmp_path) -> None:
    """The live view of `camera`: frames arrive and change; exposure up saturates pixels the page reports."""
    go_live(page, daemon, camera)
    wait_frames(page, 3)
    assert "live" in page.text_content("#live-status")
    first = shown(page, tmp_path, f"{camera}-first")
    wait_frames(page, 2)
    second = shown(page, tmp_path, f"{camera}-second")
    assert first.shape == second.shape and np.abs(first - second).mean() > 0.01  # new frames (the sensor's noise)
    assert saturated_pct(page) == 0.0 and page.text_content("#live-saturated").startswith("0.00 %")
    assert page.evaluate("document.querySelector('#live-histogram').dataset.bins") == "64"
    nominal = float(page.input_value("#live-set-exposure_s"))

    page.fill("#live-set-exposure_s", str(round(nominal * 30, 6)))  # 30 times the light
    page.click("#live-apply")
    page.wait_for_function("Number(document.querySelector('#live-saturated').dataset.pct) > 50")
    assert page.evaluate("document.querySelector('#live-saturated').className") == "state-faulted"
    magenta = shown(page, tmp_path, f"{camera}-saturated")
    assert ((magenta[:, :, 0] > 200) & (magenta[:, :, 1] < 80) & (magenta[:, :, 2] > 200)).mean() > 0.3

    page.fill("#live-set-exposure_s", "20")  # beyond the range: refused with it, nothing changed
    page.click("#live-apply")
    page.wait_for_function("document.querySelector('#live-settings-note').textContent.includes('allowed')")
    assert "exposure_s: 20; allowed: 1e-05 to 10 s" in page.text_content("#live-settings-note")
    with daemon.client(token=None) as c:
        assert c.get(f"/cameras/{camera}/settings").json()["settings"]["exposure_s"]["value"] == pytest.approx(
            nominal * 30)
    page.fill("#live-set-exposure_s", str(nominal))  # back, for what follows
    page.click("#live-apply")
    page.wait_for_function("Number(document.querySelector('#live-saturated').dataset.pct) === 0")


def test_live_view_on_the_micro_cell(micro, page, tmp_path):
    frames_arrive_change_and_saturate(page, micro, "cam2", tmp_path)

    # a gain written back: the diff first, then the file, only that line changed and its comment kept
    before = micro.cell_file.read_text()
    page.fill("#live-set-gain_db", "6")
    page.click("#live-apply")
    page.wait_for_function("!document.querySelector('#live-diff').disabled")
    page.click("#live-diff")
    page.wait_for_function("document.querySelector('#live-diff-text').textContent.includes('+++')")
    diff = page.text_content("#live-diff-text")
    assert "-  cam2: {backend: sim}   # top view of area2" in diff
    assert "+  cam2: {backend: sim, gain_db: 6.0}   # top view of area2" in diff
    assert micro.cell_file.read_text() == before  # shown, not written
    page.click("#live-write")
    page.wait_for_function("document.querySelector('#live-write-note').textContent.includes('written to')")
    after = micro.cell_file.read_text()
    assert after == before.replace("  cam2: {backend: sim}   # top view of area2",
                                   "  cam2: {backend: sim, gain_db: 6.0}   # top view of area2")
    assert page.is_hidden("#live-write")

    # the client goes away (Stop, then the tab closed): the daemon takes no more frames for it. Two seconds of a
    # stream at 4 frames a second are 8 captures; stopped, at most the one in flight, the console's cameras panel's
    # (one every 4 s) and ours
    page.click("#live-stop")
    seen = frame_id(page)
    page.wait_for_timeout(2000)
    assert frame_id(page) == seen
    assert live_frame_id(micro, "cam2") <= seen + 3
    page.click("#live-start")
    wait_frames(page, 2)
    page.context.close()
    closed_at = live_frame_id(micro, "cam2")
    time.sleep(2.0)  # eight frames' time at 4 a second
    assert live_frame_id(micro, "cam2") <= closed_at + 2  # the one in flight, and ours


def test_a_job_owns_the_cameras(micro, page, tmp_path):
    go_live(page, micro, "cam1")
    wait_frames(page, 2)
    with micro.client() as c:
        job = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": 5}).json()
        eventually(lambda: c.get(f"/jobs/{job['id']}").json()["state"] == "running", timeout=30, what="the job running")
        # the stream stops when the job starts, saying which job took the cell
        page.wait_for_function("document.querySelector('#live-status').textContent.startsWith('stopped')")
        status = page.text_content("#live-status")
        assert f"job {job['id']} (virtual-grid, running) is using the cell" in status, status
        assert page.is_enabled("#live-start") and page.is_disabled("#live-stop")
        # asked again during the job: refused (409), naming the job; a stream, a frame, the settings alike
        page.click("#live-start")
        page.wait_for_function("document.querySelector('#live-status').textContent.includes('refused')")
        assert f"refused (409): job {job['id']} (virtual-grid, running)" in page.text_content("#live-status")
        for path in ("/cameras/cam1/live.mjpg", "/cameras/cam1/live.jpg", "/cameras/cam1/settings"):
            r = c.get(path)
            assert r.status_code == 409 and f"job {job['id']} (virtual-grid" in r.json()["detail"], (path, r.text)
        r = c.post("/cameras/cam1/settings", json={"values": {"gain_db": 3}})
        assert r.status_code == 409 and f"job {job['id']}" in r.json()["detail"]
        assert c.get("/cameras/cam1/frame.png").status_code in (200, 404)  # the `frame` verb as it was
        assert wait_for(c, job["id"], {"done", "faulted"}, timeout=120)["state"] == "done"
        # done: live again, with the new calibration's grid drawn over cam1
        page.click("#live-start")
        wait_frames(page, 2)
        plain = c.get("/cameras/cam1/live.png", params={"layers": "none", "width": 800})
        grid = c.get("/cameras/cam1/live.png", params={"layers": "grid", "width": 800})
    colour = [np.ptp(cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR).astype(int), axis=2) > 60
              for r in (plain, grid)]
    assert colour[0].mean() == 0 and colour[1].mean() > 0.005
    assert page.errors == []


def test_live_view_through_a_protocol_simulator(driven, page, tmp_path):
    abb = driven
    with abb.client(token=None) as c:
        devices = {d["name"]: (d["backend"], d["state"]) for d in c.get("/cell").json()["devices"]}
    gripper = {"abb": "vgc10", "ur": "epick"}[abb.arm_backend]
    assert devices["arm"] == (abb.arm_backend, "ready") and devices["gripper"] == (gripper, "ready"), devices
    frames_arrive_change_and_saturate(page, abb, "cam3", tmp_path)
    # the features the routines of cam3 measure, found live in its frames, reported by the page
    page.wait_for_function("Number(document.querySelector('#live-features').textContent) >= 1")

    # this cell file extends the micro cell's, which has the cameras: writing back is refused, naming that file
    page.fill("#live-set-gain_db", "6")
    page.click("#live-apply")
    page.wait_for_function("!document.querySelector('#live-diff').disabled")
    before = abb.cell_file.read_text()
    page.click("#live-diff")
    page.wait_for_function("document.querySelector('#live-write-note').textContent.includes('cannot write')")
    note = page.text_content("#live-write-note")
    assert "extends" in note and f"cameras.cam3 is in {ROOT / 'config' / 'sim-microcell.yaml'}" in note, note
    assert abb.cell_file.read_text() == before
    page.click("#release-lock")
    with abb.client() as c:
        eventually(lambda: not c.get("/lock").json()["held"], timeout=10, what="the console's lock given back")
        r = c.post("/cameras/cam3/settings/save", json={"confirm": True})
        assert r.status_code == 422 and "extends" in r.json()["detail"]
        r = c.get("/cameras/cam3/live.jpg")
        stats = json.loads(r.headers["X-Live-Stats"])
        assert stats["gain_db"] == 6.0 and stats["features"]
    assert page.errors == []
