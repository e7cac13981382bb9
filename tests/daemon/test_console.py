"""The web console in a real browser: Debian's chromium, headless, driven by Playwright, against the real
daemon on the simulated micro cell. An operator pastes the token, starts a small virtual grid from the
form, watches the step counter climb, pauses and resumes with the buttons, and reads the residual plot
and the seed comparison when it is done; a wrong token is refused in words and changes nothing.
Screenshots are taken and checked (decoded, not blank, the plot visible)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support.console import BAD, STEP_JS, browser_page, check_png, colour_of, open_console, step_of
from tests.support.daemon import DaemonProcess, running_daemon, write_cell_file
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py



@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    # half the simulated cell time spent as wall time: the 24-step job lasts a few seconds, time to pause it
    with running_daemon(tmp_path_factory.mktemp("console"), realtime_factor=0.5) as d:
        yield d


@pytest.fixture
def page(browser):
    with browser_page(browser) as page:
        yield page


def state_of(daemon) -> tuple:
    """Everything a refused command must leave as it was."""
    with daemon.client(token=None) as c:
        lock = c.get("/lock").json()
        return c.get("/jobs").json(), c.get("/calibrations").json(), (lock["held"], lock.get("holder"))












def test_console_runs_a_job_shows_progress_and_the_residual_plot(daemon, page, tmp_path):
    open_console(page, daemon)
    assert page.text_content("#conn") in ("live", "connecting…")
    page.fill("#token-input", daemon.token)
    page.click("#token-form button")
    assert page.is_visible("#token-state") and not page.is_visible("#token-form")

    page.select_option("#routine", "virtual-grid")
    for name, value in {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1}.items():
        page.fill(f"#param-{name}", str(value))
    page.fill("#seed", "5")
    page.click("#start")

    # progress from the event stream: the step counter climbs while the job runs
    page.wait_for_function(f"({STEP_JS})() >= 1")
    first = step_of(page)
    page.wait_for_function(f"({STEP_JS})() > {first}")
    assert page.text_content("#job-state") == "running"
    assert re.fullmatch(r"step \d+ / 24", page.text_content("#job-step")), page.text_content("#job-step")
    page.screenshot(path=tmp_path / "running.png", full_page=True)

    # pause at the step boundary, then resume, with the buttons
    page.click("#pause")
    page.wait_for_function("document.querySelector('#job-state').textContent === 'paused'")
    held = step_of(page)
    assert held < 24 and page.is_enabled("#resume") and not page.is_enabled("#pause-now")
    page.wait_for_timeout(800)
    assert step_of(page) == held  # nothing moves while paused
    page.click("#resume")
    page.wait_for_function("['running', 'done'].includes(document.querySelector('#job-state').textContent)")

    # done: the residual plot loaded and the comparison with seed 001's table
    page.wait_for_function("document.querySelector('#job-state').textContent === 'done'", timeout=60_000)
    # the grid stops once its accuracy target is met (issue 31): the count ends at the job's own total, the 8
    # verification points always among them
    done = step_of(page)
    assert 8 + 9 <= done <= 24 and page.text_content("#job-step") == f"step {done} / {done}"
    page.wait_for_function("document.querySelector('#plot').complete && document.querySelector('#plot').naturalWidth > 0")
    assert page.is_visible("#plot-figure")
    # the report's text comes with its own request: it may land after the plot
    page.wait_for_function("document.querySelector('#report').textContent.includes('verification (unseen)')")
    report = page.text_content("#report")
    assert "verification (unseen)" in report and "seed 001 Table II" in report and "OpenCV baseline" in report
    assert page.locator("#report table tbody tr").count() >= 4
    # the calibration it made is listed, active; the live view shows cam1 with its overlay
    page.wait_for_selector("#calibrations tbody tr")
    assert "cam1" in page.text_content("#calibrations tbody")
    page.wait_for_function("document.querySelector('#camera-cam1 img').naturalWidth > 0")

    page.screenshot(path=tmp_path / "done.png", full_page=True)
    page.locator("#results-panel").screenshot(path=tmp_path / "results.png")
    page.locator("#plot").screenshot(path=tmp_path / "plot.png")
    page.locator("#camera-cam1 img").screenshot(path=tmp_path / "cam1.png")
    check_png(tmp_path / "running.png")
    check_png(tmp_path / "results.png")
    check_png(tmp_path / "cam1.png", min_std=3.0)  # a dark frame with a coloured overlay
    plot = check_png(tmp_path / "plot.png")
    assert plot.shape[0] > 250 and plot.shape[1] > 300  # shown at a readable size
    # the plot's region of the whole page is the daemon's residual plot, as drawn on screen
    box = page.evaluate("""() => { const r = document.querySelector('#plot').getBoundingClientRect();
                                   return {x: r.x + scrollX, y: r.y + scrollY, width: r.width, height: r.height}; }""")
    done = check_png(tmp_path / "done.png")
    with daemon.client(token=None) as c:
        jobs = c.get("/jobs").json()["jobs"]
        audit = c.get("/audit").json()["audit"]
        served = cv2.imdecode(np.frombuffer(c.get(f"/jobs/{jobs[0]['id']}/plot").content, np.uint8), cv2.IMREAD_COLOR)
    x, y, w, h = (round(box[k]) for k in ("x", "y", "width", "height"))
    region = done[y + 2:y + h - 2, x + 2:x + w - 2].astype(float)  # inside the border
    expected = cv2.resize(served, (w, h), interpolation=cv2.INTER_AREA)[2:h - 2, 2:w - 2].astype(float)
    assert region.shape == expected.shape and np.abs(region - expected).mean() < 12, "the plot is not on screen"
    coloured = np.ptp(region, axis=2) > 60  # the red and blue arrows, not only grey axes
    assert coloured.mean() > 0.001

    # the overlay is drawn by the daemon: the active calibration's grid and residuals in colour over the frame
    with daemon.client(token=None) as c:
        plain = c.get("/cameras/cam1/overlay.png", params={"width": 640})
        drawn = c.get("/cameras/cam1/overlay.png", params={"width": 640, "layers": ["grid", "residuals"]})
        assert c.get("/cameras/cam1/overlay.png", params={"layers": "bogus"}).status_code == 422
        assert c.get("/cameras/nope/overlay.png").status_code == 404
    assert plain.status_code == drawn.status_code == 200
    colour = [np.ptp(cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR).astype(int), axis=2) > 60
              for r in (plain, drawn)]
    assert colour[0].shape[1] == 640 and colour[0].mean() == 0 and colour[1].mean() > 0.005

    job = jobs[0]
    assert (job["routine"], job["state"], job["seed"]) == ("virtual-grid", "done", 5)
    assert job["params"] == {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1}
    console_actions = [a["action"] for a in audit if a["client"].startswith("console@") and a["outcome"] == "ok"]
    for action in ("POST /lock", "POST /jobs", f"POST /jobs/{job['id']}/pause", f"POST /jobs/{job['id']}/resume"):
        assert action in console_actions
    assert page.errors == []
    # nothing the page asked for was missing (the icon: none is asked for); a refused click (409, when the machine
    # is slow and the job ended first) is the console at work: it shows it in the page
    assert [e for e in page.console_errors if "status of 404" in e] == []


def test_pause_now_then_abort_from_the_console(daemon, page):
    open_console(page, daemon)
    page.fill("#token-input", daemon.token)
    page.click("#token-form button")
    # nothing is chosen at first: Start without a choice starts nothing (the form refuses it)
    page.wait_for_selector("#routine option[value='virtual-grid']", state="attached")
    assert page.input_value("#routine") == ""
    page.click("#start")
    assert page.evaluate("document.querySelector('#routine').validity.valueMissing")
    page.select_option("#routine", "virtual-grid")
    for name, value in {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1}.items():
        page.fill(f"#param-{name}", str(value))
    page.click("#start")
    # the job shows, or the console says why it was refused (an error stays shown)
    page.wait_for_function("document.querySelector('#job-title').textContent.startsWith('2:') || "
                           "document.querySelector('#message').className === 'error'")
    assert page.text_content("#job-title").startswith("2:"), page.text_content("#message")
    page.wait_for_function(f"({STEP_JS})() >= 2")
    page.click("#pause-now")  # the arm stops now; the step cut short is redone on resume
    page.wait_for_function("document.querySelector('#job-state').textContent === 'paused'")
    assert "immediate" in page.text_content("#job-reason")
    assert "s of cell time" in page.text_content("#job-eta")  # what is left of the paused job
    assert page.is_enabled("#abort") and colour_of(page, "#abort") == BAD  # a live job's abort is the red button
    page.once("dialog", lambda dialog: dialog.accept())  # "Abort job 2?"
    page.click("#abort")
    page.wait_for_function("document.querySelector('#job-state').textContent === 'aborted'")
    assert page.is_disabled("#resume") and page.is_disabled("#abort")
    assert page.text_content("#job-eta") == "–"  # nothing is left to run
    disabled = colour_of(page, "#abort")  # drawn as every disabled button is, not red
    assert disabled != BAD and disabled == colour_of(page, "#resume"), disabled
    page.reload()  # shown afresh from the job's record, whose last progress still carries an estimate
    page.wait_for_function("document.querySelector('#job-title').textContent.startsWith('2:')")
    page.wait_for_function("document.querySelector('#job-state').textContent === 'aborted'")
    assert page.text_content("#job-eta") == "–" and page.text_content("#job-step").startswith("step ")
    with daemon.client(token=None) as c:
        job = c.get("/jobs/2").json()
    assert job["state"] == "aborted" and [h["to"] for h in job["history"]][-2:] == ["paused", "aborted"]
    assert page.errors == []


def test_a_wrong_token_is_refused_clearly_and_changes_nothing(daemon, page, tmp_path):
    before = state_of(daemon)
    open_console(page, daemon)
    # reading needs no token: the cell and the jobs show
    assert "arm" in page.text_content("#devices tbody")
    page.fill("#token-input", "not-the-token")
    page.click("#token-form button")
    page.select_option("#routine", "virtual-grid")
    page.fill("#param-rows", "4")
    page.click("#start")
    page.wait_for_selector("#message.error")
    message = page.text_content("#message")
    assert "refused the token" in message and "403" in message and "cellctl token" in message
    assert "Nothing was changed" in message
    assert page.is_visible("#token-form")  # asked again; the wrong one is not kept
    assert page.evaluate("sessionStorage.getItem('cellctl.token')") is None
    after = state_of(daemon)
    assert after == before
    page.screenshot(path=tmp_path / "wrong-token.png", full_page=True)
    check_png(tmp_path / "wrong-token.png")
    assert page.errors == []


def test_the_overlay_reads_no_simulated_truth():
    """The overlay draws what the daemon measured and fitted; the simulated world's truth is not for it."""
    import ast

    import cellctl.http.overlay as overlay

    tree = ast.parse(Path(overlay.__file__).read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert names and not [n for n in names if n.startswith("drivers")], names


def test_a_drift_verdict_raises_an_alarm_with_its_remedy_one_click_away(tmp_path, calibrated_cell, page):
    """A check finds camera 1 moved: the console shows the alarm, the health table and the trend; one click on
    the alarm's button submits the touch-up it calls for, and once that holds, the alarm goes."""
    import shutil

    import yaml

    from tests.support.daemon import wait_for

    path = write_cell_file(tmp_path, realtime_factor=0.0)
    data = yaml.safe_load(path.read_text())
    data["sim"]["seed"] = calibrated_cell.seed
    data["sim"]["drift"] = {"cam1": {"map_shift_um": [8.0, 0.0]}}
    path.write_text(yaml.safe_dump(data))
    shutil.copytree(calibrated_cell.store_path, tmp_path / "store")
    with DaemonProcess(path).start() as daemon, daemon.client() as c:
        open_console(page, daemon)
        page.fill("#token-input", daemon.token)
        page.click("#token-form button[type=submit]")
        job = c.post("/jobs", json={"routine": "calibration-check", "params": {"targets": "cam1"}}).json()
        wait_for(c, job["id"], {"done"})
        page.wait_for_selector("#health-alarm:not([hidden])")
        assert "cam1" in page.text_content("#health-alarm-text")
        assert page.locator("#health tbody tr").count() == 4  # cam1, cam2, cam3, nozzle
        assert page.locator("#health-chart svg polyline").count() >= 2  # cam1's dx and dy over the checks
        # one check: its drifts with their 1-σ error bars, on an axis that starts at it (not -1 ... 1 h)
        assert page.locator("#health-chart svg path.error-bar").count() >= 2
        labels = page.locator("#health-chart svg text[text-anchor=middle]").all_text_contents()  # the x axis's
        assert "0" in labels and "1" in labels and "-1" not in labels, labels
        page.screenshot(path=str(tmp_path / "alarm.png"))
        check_png(tmp_path / "alarm.png")
        page.click("#health-actions button.remedy")  # "Touch up cam1": the check again, with update=true
        page.wait_for_function("() => [...document.querySelectorAll('#jobs tbody tr')].length >= 2")
        touch = max(c.get("/jobs").json()["jobs"], key=lambda j: j["id"])
        assert touch["routine"] == "calibration-check" and touch["params"] == {"targets": "cam1", "update": True}
        assert wait_for(c, touch["id"], {"done"})["state"] == "done"
        assert c.get(f"/jobs/{touch['id']}/result").json()["updated"].get("cam1")
        page.click("#release-lock")  # the console took the operator lock for its command
        page.wait_for_function("() => document.querySelector('#lock-holder').textContent === 'free'")
        again = c.post("/jobs", json={"routine": "calibration-check", "params": {"targets": "cam1"}}).json()
        wait_for(c, again["id"], {"done"})
        page.wait_for_selector("#health-alarm", state="hidden")
        assert not page.errors, page.errors


def test_the_job_form_keeps_every_camera_frame_when_asked(start_daemon, page):
    """The form's "Save every camera frame" is the API's save_images (as `cellctl run --save-images`): one PNG
    per frame under the run folder's images/; unchecked, none (the default)."""
    from cellctl.stores.run_folder import RunFolder

    from tests.support.daemon import wait_for

    daemon = start_daemon(realtime_factor=0.0)
    open_console(page, daemon)
    page.fill("#token-input", daemon.token)
    page.click("#token-form button")
    assert page.is_visible("#save-images") and not page.is_checked("#save-images")
    jobs = {}
    for n, save in ((1, True), (2, False)):
        page.select_option("#routine", "virtual-grid")
        for name, value in {"rows": 3, "cols": 3, "n_verify": 3, "passes": 1}.items():
            page.fill(f"#param-{name}", str(value))
        page.set_checked("#save-images", save)
        page.click("#start")
        page.wait_for_function(f"document.querySelector('#job-title').textContent.startsWith('{n}:')")
        page.wait_for_function("document.querySelector('#job-state').textContent === 'done'", timeout=60_000)
        assert page.is_visible("#job-images") is save
        with daemon.client(token=None) as c:
            jobs[save] = wait_for(c, n, {"done"})
        if save:
            assert jobs[save]["run_dir"] in page.text_content("#job-images")
    assert jobs[True]["save_images"] is True and jobs[False]["save_images"] is False
    saved = RunFolder(jobs[True]["run_dir"])
    frames = {(r["camera"], r["frame_id"]) for r in saved.samples()}
    assert len(frames) == len(list(saved.images_path.glob("*.png"))) == 12
    assert not list(RunFolder(jobs[False]["run_dir"]).images_path.glob("*.png"))
    with daemon.client(token=None) as c:
        submitted = [a["detail"] for a in c.get("/audit").json()["audit"] if a["action"] == "POST /jobs"]
    assert ['"save_images": true' in d for d in submitted] == [True, False]
    page.click("#release-lock")
    assert page.errors == []


# -- the operator lock as the console holds it: taken by a command, a short lease renewed while the tab is open ---

TINY = {"rows": 3, "cols": 3, "n_verify": 3, "passes": 1}  # 12 steps: the smallest grid the model fits


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """A daemon whose jobs take no wall time, for the lock's tests (they need a command, not a long job)."""
    with DaemonProcess(write_cell_file(tmp_path_factory.mktemp("console-lock"), realtime_factor=0.0,
                                       lock_break_after_idle_s=3.0)).start() as d:
        yield d


def lock_of(daemon) -> dict:
    with daemon.client(token=None) as c:
        return c.get("/lock").json()


def wait_lock(daemon, until, timeout: float, what: str) -> dict:
    """Poll GET /lock until `until(lock)` holds: the daemon's own answer, with a deadline, no fixed sleep."""
    return eventually(lambda: lock if until(lock := lock_of(daemon)) else None, timeout=timeout, every=0.1,
                      what=lambda: f"{what} (the lock is {lock_of(daemon)})")


def console_audit(daemon) -> list[dict]:
    with daemon.client(token=None) as c:
        return [a for a in c.get("/audit").json()["audit"] if a["client"].startswith("console@")]


def open_with_token(page, daemon) -> None:
    open_console(page, daemon)
    page.fill("#token-input", daemon.token)
    page.click("#token-form button[type=submit]")


def start_tiny_job(page) -> int:
    """Start a 12-step virtual grid from the form (a command: it takes the lock), and wait until it is done."""
    before = page.text_content("#job-title")
    page.select_option("#routine", "virtual-grid")
    for name, value in TINY.items():
        page.fill(f"#param-{name}", str(value))
    page.click("#start")
    page.wait_for_function(f"!['–', {before!r}].includes(document.querySelector('#job-title').textContent)")
    page.wait_for_function("document.querySelector('#job-state').textContent === 'done'", timeout=60_000)
    return int(page.text_content("#job-title").split(":")[0])


def test_the_console_takes_the_lock_only_for_a_command_renews_it_and_gives_it_back_when_closed(quick, browser):
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = context.new_page()
    page.set_default_timeout(30_000)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    open_with_token(page, quick)
    # the page loaded, the token given, the cell shown: no lock taken (the cell panel says so too)
    page.wait_for_function("document.querySelector('#lock-holder').textContent === 'free'")
    assert lock_of(quick) == {"held": False}
    assert page.text_content("#lock-state") == "no lock taken"
    assert not console_audit(quick)  # it sent nothing at all

    start_tiny_job(page)  # the operator's command takes it, as a short lease
    lock = lock_of(quick)
    assert lock["held"] and lock["holder"].startswith("console-") and lock["expires_in_s"] <= 30, lock
    assert page.text_content("#lock-state") == f"lock held as {lock['holder']}"
    # the open tab renews it: its expiry moves on while nobody commands
    wait_lock(quick, lambda now: now.get("expires", 0) > lock["expires"] + 5, 25, "the lease renewed")

    page.close()  # pagehide: the tab gives the lock back as it goes
    wait_lock(quick, lambda now: not now["held"], 25, "the lock given back by a closed tab")
    assert [a["outcome"] for a in console_audit(quick) if a["action"] == "DELETE /lock"] == ["ok"]
    context.close()
    assert not errors, errors


def test_a_hung_tab_loses_the_lock_within_its_lease(quick, browser):
    """A tab that stops running (hung, crashed, frozen) neither renews nor gives back: the 30 s lease ends it."""
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = context.new_page()
    page.set_default_timeout(30_000)
    open_with_token(page, quick)
    start_tiny_job(page)
    holder = lock_of(quick)["holder"]
    releases = len([a for a in console_audit(quick) if a["action"] == "DELETE /lock"])
    # its script never runs again: no heartbeat, no pagehide (CDP's Page.crash gets no answer to wait on)
    page.evaluate("() => { setTimeout(() => { for (;;) {} }, 0); }")
    assert lock_of(quick)["holder"] == holder  # the daemon still thinks it is held ...
    wait_lock(quick, lambda now: not now["held"], 30 + 10, "the lease of a hung tab lapsed")  # ... for <= 30 s
    assert len([a for a in console_audit(quick) if a["action"] == "DELETE /lock"]) == releases  # it lapsed
    context.close()


def test_a_lapsed_lease_is_not_taken_back_by_the_next_heartbeat(quick, page):
    """A background tab's timers may run once a minute: its lease lapses, and the late renewal must not take the
    lock anew behind the operator's back (the next command does, in sight)."""
    open_with_token(page, quick)
    start_tiny_job(page)
    assert lock_of(quick)["held"]
    page.evaluate("() => clearInterval(ui.heartbeat)")  # the beats a hidden tab would not run
    # the lease ends on the daemon while the tab still thinks it holds it: what 30 s without a beat does (the
    # hung-tab test waits those out), here at once, by its own id
    with quick.client() as c:
        assert c.delete("/lock", headers={"X-Cellctl-Lock": page.evaluate("() => ui.lockId")}).status_code == 200
    assert lock_of(quick) == {"held": False}
    page.evaluate("() => heartbeat()")  # the late beat
    page.wait_for_function("() => ui.lockId === null")
    assert lock_of(quick) == {"held": False}
    assert "lapsed" in page.text_content("#lock-state")
    assert page.errors == []


def test_a_broken_lock_is_shown_and_not_taken_back(quick, page):
    open_with_token(page, quick)
    start_tiny_job(page)
    holder = lock_of(quick)["holder"]
    with quick.client(**{"X-Cellctl-Client": "shift-lead"}) as c:
        # the tab renews its lease every 10 s: this cell lets a lock 3 s idle be broken (the default is a minute,
        # which an open console never reaches)
        # (idle_s is rounded to 0.1 s: half a second more, so the break surely comes after the 3 s)
        wait_lock(quick, lambda now: now.get("idle_s", 0) >= 3.5, 15, "the console's lock idle for 3.5 s")
        r = c.post("/lock/break", json={"reason": "line 3 is handed over"})
        assert r.status_code == 200 and r.json()["broken"]["holder"] == holder, r.text
    # the event stream tells the tab at once: it shows who and why, and holds no lock any more
    page.wait_for_selector("#message.error:not([hidden])")
    message = page.text_content("#message")
    assert "Your operator lock was broken by shift-lead@" in message and "line 3 is handed over" in message, message
    assert page.text_content("#lock-state").startswith("lock broken by shift-lead@")
    assert page.evaluate("ui.lockId === null && ui.heartbeat === null")  # no heartbeat takes it back
    assert lock_of(quick) == {"held": False}
    page.screenshot(path=quick.store.parent / "broken-lock.png", full_page=True)
    check_png(quick.store.parent / "broken-lock.png")
    # the operator's next command takes the lock afresh
    start_tiny_job(page)
    assert lock_of(quick)["holder"] == holder
    page.click("#release-lock")
    wait_lock(quick, lambda now: not now["held"], 10, "the lock released with the button")
    assert page.errors == []


def test_routine_parameters_show_their_description_and_unit(quick, page, tmp_path):
    open_console(page, quick)
    with quick.client(token=None) as c:
        routines = c.get("/routines").json()["routines"]
    for routine in ("virtual-grid", "hybrid"):
        page.select_option("#routine", routine)
        properties = routines[routine]["params"]["properties"]
        rows = page.evaluate("""() => [...document.querySelectorAll('#params label.param')].map((l) => ({
            name: l.querySelector('code').textContent, description: l.querySelector('.param-description').textContent,
            unit: document.getElementById(l.htmlFor).parentElement.querySelector('.unit').textContent}))""")
        assert [r["name"] for r in rows] == list(properties)
        for r in rows:  # every parameter's declaration says what it is
            assert r["description"] and r["description"] == properties[r["name"]]["description"], r
        units = {r["name"]: r["unit"] for r in rows}
        assert units["margin_mm"] == "mm" and units.get("radial_terms") == "" and units.get("rows", "") == ""
    page.select_option("#routine", "virtual-grid")
    page.locator("#run-panel").screenshot(path=tmp_path / "form.png")
    check_png(tmp_path / "form.png", min_std=5.0)
    assert page.errors == []


def test_the_calibrations_table_follows_an_aborted_sequence(tmp_path, page):
    """A sequence aborted after its first routine stored and activated cam1: the table shows it without a reload."""
    import yaml

    path = write_cell_file(tmp_path, realtime_factor=0.0)
    data = yaml.safe_load(path.read_text())
    data["routines"]["virtual-grid"].update(TINY)  # the first routine of calibrate-cell, made quick
    path.write_text(yaml.safe_dump(data))
    with DaemonProcess(path).start() as daemon:
        open_with_token(page, daemon)
        assert page.locator("#calibrations tbody tr").count() == 0
        page.select_option("#routine", "calibrate-cell")
        page.click("#start")
        page.wait_for_function("document.querySelector('#job-step').textContent.includes('rotation-sweep')",
                               timeout=60_000)
        page.once("dialog", lambda dialog: dialog.accept())
        page.click("#abort")
        page.wait_for_function("document.querySelector('#job-state').textContent === 'aborted'")
        page.wait_for_function("document.querySelector('#calibrations tbody').textContent.includes('cam1')")
        assert page.locator("#calibrations tbody tr").count() == 1
        assert page.text_content("#job-eta") == "–"
        page.click("#release-lock")
    assert page.errors == []


def test_the_console_shows_the_store_disk_and_says_when_no_job_can_start(quick, tmp_path, page):
    open_console(page, quick)
    page.wait_for_function("document.querySelector('#disk-free').textContent.includes('MB free')")
    assert "below" not in page.text_content("#disk-free")
    assert page.get_attribute("#disk-free", "class") == ""
    # a floor above any disk here: the console says no job can start, and where to free space
    path = write_cell_file(tmp_path, realtime_factor=0.0)
    path.write_text(path.read_text() + "store: {min_free_mb: 10000000}\n")
    with DaemonProcess(path).start() as low:
        open_console(page, low)
        page.wait_for_function("document.querySelector('#disk-free').textContent.includes('floor')")
        text = page.text_content("#disk-free")
        assert re.fullmatch(r"\d+ MB free of \d+ MB: below the 10000000 MB floor, no job can start; free space "
                            r"on its filesystem \(\w+ on /\S*\)", text), text
        assert page.get_attribute("#disk-free", "class") == "state-faulted"
    assert page.errors == []
