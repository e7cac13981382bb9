"""The web operator (`operator: {backend: web}`): vr-coarse on the simulated VR cell of config/sim-vr.yaml
through the real daemon, its click requests answered through the API and, in headless chromium, by clicking
on the console's overlay; instructions confirmed or declined; bad answers refused with nothing changed.

The answers come from the simulated truth: the test builds the same world from the cell file and seed (the
world is a pure function of them) and clicks the true projection of the model points it sees, plus a few
pixels of noise. Only the test looks at the truth; the daemon, the routine and the console never do.
"""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
import yaml

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine

from tests.support.console import check_png
from tests.support.daemon import DaemonProcess, wait_for
from tests.support.operator import (
    CELL,
    OFFSET,
    Truth,
    next_request,
    operator_events,
    pending,
    write_vr_cell,
)
from tests.support.wait import eventually

ROOT = Path(__file__).resolve().parents[2]
SEED = 3












@pytest.fixture(scope="module")
def vr_daemon(tmp_path_factory):
    folder = tmp_path_factory.mktemp("operator")
    with DaemonProcess(write_vr_cell(folder, timeout_s=300)).start(timeout=120) as d:
        yield d


def submit(client: httpx.Client, **body) -> dict:
    r = client.post("/jobs", json={"routine": "vr-coarse", **body})
    assert r.status_code == 201, r.text
    return r.json()




# -- (a) through the API ----------------------------------------------------------------------------------


def test_coarse_matching_from_clicks_answered_through_the_api(vr_daemon, tmp_path):
    c = vr_daemon.client()
    job = submit(c, params=OFFSET, seed=SEED)
    truth = Truth(vr_daemon.cell_file, SEED)
    answered, last = [], 0
    for _ in range(4):  # both objects in both views
        req = next_request(c, last, job["id"])
        assert req["kind"] == "click_points" and req["answer_with"] == "clicks" and req["job"] == job["id"]
        assert req["at_least"] == 5 and req["image_size"] == [640, 480]
        # the job's progress says what it waits for
        def waits_for(req=req) -> bool:
            progress = c.get(f"/jobs/{job['id']}").json()["progress"] or {}
            return (progress.get("operator") or {}).get("request") == req["id"]

        eventually(waits_for, what="progress naming the request")
        n = len(truth.world.model_solids[req["object"]].vertices)
        assert [p["index"] for p in req["model_points"]] == list(range(n)) and req["edges"]
        # the overlay points are the estimate's projection: near the truth, but the estimate is 5 in off
        est = np.array([[p["u"], p["v"]] for p in req["model_points"]])
        assert 3 < np.linalg.norm(est - truth.pixels(req), axis=1).mean() < 300
        frame = cv2.imdecode(np.frombuffer(c.get(req["frame_url"]).content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert frame.shape[:2] == (480, 640) and frame.std() > 5
        clicks = truth.clicks(req)
        assert len(clicks) >= 5
        r = c.post(req["answer_url"], json={"clicks": clicks})
        assert r.status_code == 200, r.text
        assert r.json() == {"request": req["id"], "outcome": "answered", "pairs": len(clicks), "job": job["id"]}
        answered.append((req["camera"], req["object"]))
        last = req["id"]
    assert sorted(answered) == sorted((cam, obj) for cam in ("side", "top") for obj in ("oru", "receptacle"))
    done = wait_for(c, job["id"], {"done", "faulted", "aborted"})
    assert done["state"] == "done", done
    assert pending(c) is None

    # converged as with the simulated operator (tests/routines/test_vr.py: under 1 in from 5.1 in off)
    result = c.get(f"/jobs/{job['id']}/result").json()
    final = result["truth"]["final"]
    assert final["position_in"] < 1.0 and final["orientation_deg"] < 5.0, final
    config, text = load_cell_file(CELL)
    simulated = run_routine("vr-coarse", config, text, tmp_path / "simulated-operator", seed=SEED, overrides=OFFSET)
    assert simulated["truth"]["final"]["position_in"] < 1.0
    assert result["model"]["kind"] == "vr-scene" and result["calibration"]["target"] == "vr"
    # the rows record which frames were clicked on
    samples = c.get(f"/jobs/{job['id']}/samples").text
    assert "point-simultaneous" in samples

    # the event stream announced each request and its answer
    events = operator_events(vr_daemon, job["id"], 8)
    assert [e["state"] for e in events] == ["waiting", "answered"] * 4
    assert all(e["job"] == job["id"] and e["kind"] == "click_points" for e in events)
    assert {(e["camera"], e["object"]) for e in events} == set(answered)


def test_bad_answers_are_refused_and_change_nothing(vr_daemon):
    c = vr_daemon.client()
    job = submit(c, seed=SEED)
    req = next_request(c, 0, job["id"])
    truth = Truth(vr_daemon.cell_file, SEED)
    good = truth.clicks(req)
    n = len(req["model_points"])
    url = req["answer_url"]

    def refused(body, status, field, words, client=c, path=url):
        r = client.post(path, json=body)
        assert r.status_code == status, (r.status_code, r.text)
        detail = r.json()["detail"]
        if field is not None:
            assert field in [p["field"] for p in r.json()["problems"]], r.json()
        assert words in detail, detail
        again = pending(c)
        assert again is not None and again["id"] == req["id"], "the request must stay pending"
        return r.json()

    refused({"clicks": [dict(good[0], model_index=n)] + good[1:]}, 422, "body.clicks.0.model_index",
            f"{n} is not a point of the {req['object']} model (allowed: 0 to {n - 1})")
    refused({"clicks": good + [dict(good[1], u=good[1]["u"] + 3)]}, 422, f"body.clicks.{len(good)}.model_index",
            "already paired in clicks.1")
    refused({"clicks": [dict(good[0], u=640.0)] + good[1:]}, 422, "body.clicks.0.u", "outside the 640 x 480 image")
    refused({"clicks": [dict(good[2], v=-3.0)] + good[:2] + good[3:]}, 422, "body.clicks.0.v", "allowed: -0.5 to 479.5")
    refused({"clicks": good[:4]}, 422, "body.clicks", "4 pairs given; at least 5 are needed")
    refused({"clicks": [dict(good[0], x=1.0)] + good[1:]}, 422, "body.clicks.0.x", "unknown field")
    refused({"clicks": [dict(good[0], u="left")] + good[1:]}, 422, "body.clicks.0.u", "number")
    refused({"pairs": good}, 422, "body.pairs", "unknown field")
    # several problems at once: every one named, nothing taken
    body = refused({"clicks": [dict(good[0], model_index=n + 5, v=1e6)]}, 422, None, "at least 5")
    assert {p["field"] for p in body["problems"]} >= {"body.clicks.0.model_index", "body.clicks.0.v"}
    # the wrong request, or the wrong kind of answer: 409
    refused({"clicks": good}, 409, "request", f"operator request {req['id'] + 7} is not pending",
            path=f"/operator/requests/{req['id'] + 7}/clicks")
    refused(None, 409, "request", "is a click_points request", path=f"/operator/requests/{req['id']}/done")
    # no token, a wrong one, another client's lock
    with vr_daemon.client(token=None) as anonymous:
        refused({"clicks": good}, 401, None, "Authorization: Bearer", client=anonymous)
    with vr_daemon.client(token="not-the-token") as wrong:
        refused({"clicks": good}, 403, None, "wrong token", client=wrong)
    with vr_daemon.client() as bob:
        lock = bob.post("/lock", json={"holder": "bob", "ttl_s": 60}).json()
        try:
            refused({"clicks": good}, 423, None, "held by 'bob'")
            with vr_daemon.client(token=None) as reader:  # reading stays open meanwhile
                assert reader.get(req["frame_url"]).status_code == 200
        finally:
            assert bob.delete("/lock", headers={"X-Cellctl-Lock": lock["lock_id"]}).status_code == 200
    assert c.get(f"/jobs/{job['id']}").json()["state"] == "running"
    refusals = [a for a in c.get("/audit").json()["audit"] if a["action"] == f"POST {url}"]
    assert len(refusals) == 12 and all(a["outcome"].startswith("refused") for a in refusals), refusals

    # the frame with the points drawn, for clients that cannot draw: the object's colour over the grey frame
    raw = cv2.imdecode(np.frombuffer(c.get(req["frame_url"]).content, np.uint8), cv2.IMREAD_COLOR)
    drawn = cv2.imdecode(np.frombuffer(c.get(req["frame_url"], params={"points": "true"}).content, np.uint8),
                         cv2.IMREAD_COLOR)
    assert (np.ptp(raw.astype(int), axis=2) > 60).mean() == 0 and (np.ptp(drawn.astype(int), axis=2) > 60).mean() > 0.002

    # declined (too few points seen): the job faults saying so; the request is gone
    r = c.post(f"/operator/requests/{req['id']}/decline", json={"reason": "the ORU is in the dark"})
    assert r.status_code == 200 and r.json()["outcome"] == "declined"
    faulted = wait_for(c, job["id"], {"faulted", "done", "aborted"})
    assert faulted["state"] == "faulted" and "only 0 points clicked" in faulted["reason"], faulted
    assert pending(c) is None and c.post(url, json={"clicks": good}).status_code == 409
    # acknowledged and resumed, the step is asked again
    assert c.post(f"/jobs/{job['id']}/ack").status_code == 200
    assert c.post(f"/jobs/{job['id']}/resume").status_code == 200
    again = next_request(c, req["id"], job["id"])
    assert (again["camera"], again["object"]) == (req["camera"], req["object"])

    # aborted while waiting: the request is withdrawn, the job ends aborted
    assert c.post(f"/jobs/{job['id']}/abort").status_code == 200
    aborted = wait_for(c, job["id"], {"aborted", "faulted", "done"})
    assert aborted["state"] == "aborted", aborted
    assert pending(c) is None
    last = c.get("/operator/request").json()["last"]
    assert last["request"] == again["id"] and last["outcome"] == "withdrawn"


# -- instructions (request, align by hand, mount camera), on the daemon's objects in-process ------------------


def test_instructions_are_confirmed_or_declined_and_time_out(tmp_path):
    from fastapi.testclient import TestClient

    from drivers.interfaces import MotionStopped
    from drivers.operators.web import OperatorDeclined, OperatorTimeout

    from cellctl.http.api import create_app
    from cellctl.startup.daemon import Daemon

    daemon = Daemon(write_vr_cell(tmp_path, timeout_s=30))
    try:
        client = TestClient(create_app(daemon), headers={"Authorization": f"Bearer {daemon.token}"})
        operator = daemon.cells.cell.operator

        def in_worker(call):
            """Run an operator verb as the worker would (it blocks); returns (thread, outcome box)."""
            box: dict = {}

            def run():
                try:
                    box["value"] = call()
                except Exception as exc:  # noqa: BLE001 - the test looks at it
                    box["error"] = exc

            t = threading.Thread(target=run, daemon=True)
            t.start()
            return t, box

        def ask(call) -> tuple[threading.Thread, dict, dict]:
            before = (client.get("/operator/request").json()["last"] or {}).get("request", 0)
            t, box = in_worker(call)
            req = eventually(lambda: (r := client.get("/operator/request").json()["request"]) and r["id"] > before and r,
                             timeout=10, what="the instruction")
            return t, box, req

        t, box, req = ask(lambda: operator.request("Lay the dot grid on area1", fixture="grid-area1", present=True))
        assert req["kind"] == "request" and req["answer_with"] == "confirm" and "frame_url" not in req
        assert req["instruction"] == "Lay the dot grid on area1" and req["fixture"] == "grid-area1"
        assert client.post(req["done_url"].replace("/done", "/clicks"), json={"clicks": []}).status_code == 409
        assert client.post(req["done_url"]).json()["outcome"] == "answered"
        t.join(5)
        assert box == {"value": None}

        t, box, req = ask(lambda: operator.mount_camera("top", 28.0, 12.0))
        assert "Mount camera top at an inter-camera angle of 28 deg, zoomed to a view 12 in wide" in req["instruction"]
        client.post(req["done_url"])
        t.join(5)
        assert box == {"value": None}
        operator.mount_camera("top", 28.0, 12.0)  # mounted so already: not asked again (returns at once)

        t, box, req = ask(lambda: operator.align_by_hand(daemon.cells.cell.arm, 2 * 0.0254))
        assert req["kind"] == "align_by_hand" and "2.00 in" in req["instruction"]
        r = client.post(req["decline_url"], json={"reason": "the jog pendant is out of reach"})
        assert r.status_code == 200
        t.join(5)
        assert isinstance(box["error"], OperatorDeclined) and "jog pendant" in str(box["error"])

        # the job stopped (abort, pause now, shutdown: the cell's stop) while waiting: withdrawn
        t, box, req = ask(lambda: operator.request("Remove the grid"))
        daemon.cells.stop()
        t.join(5)
        assert isinstance(box["error"], MotionStopped)
        assert client.post(req["done_url"]).status_code == 409
        with pytest.raises(MotionStopped, match="not asked"):  # nor is anything else asked in this step
            operator.request("Remove the grid")
        # the next step asks again
        daemon.cells.cell.begin_step(1)
        t, box, req = ask(lambda: operator.request("Remove the grid"))
        client.post(req["done_url"])
        t.join(5)
        assert box == {"value": None}

        # nobody answers in time: the job would fault with a reason that says so
        from drivers.operators.web import WebOperator

        quick = WebOperator("operator", WebOperator.Settings(timeout_s=0.2), operator.desk)
        quick.connect()
        with pytest.raises(OperatorTimeout, match="no answer to operator request .* within 0.2 s"):
            quick.request("Clear the jam")
        assert client.get("/operator/request").json()["last"]["outcome"] == "timed-out"
        # every request and its end was an operator event
        states = [d["state"] for _, kind, d in daemon.hub.since(0) if kind == "operator"]
        assert states == ["waiting", "answered"] * 2 + ["waiting", "declined", "waiting", "withdrawn",
                                                        "waiting", "answered", "waiting", "timed-out"]
    finally:
        daemon.cells.close()
        daemon.jobs.close()
        daemon.calstore.close()


def test_a_bad_operator_option_names_the_key(tmp_path):
    from cellctl.config import CellFileError

    with pytest.raises(CellFileError, match="operator.timeout_s"):
        load_cell_file(write_vr_cell(tmp_path, timeout_s=-1))
    with pytest.raises(CellFileError, match="operator.backend: unknown operator backend 'webb'; allowed: console, "
                                            "sim, sim-vr, web"):
        data = yaml.safe_load(CELL.read_text())
        data["operator"] = {"backend": "webb"}
        (tmp_path / "bad.yaml").write_text(yaml.safe_dump(data))
        load_cell_file(tmp_path / "bad.yaml")


# -- (b) in the browser -------------------------------------------------------------------------------------


def screen_point(box: dict, view: dict, u: float, v: float) -> tuple[float, float]:
    """Where image pixel (u, v) is on the page: the canvas's box and its view (data attributes)."""
    return (box["x"] + (u - view["left"]) / view["spanU"] * box["width"],
            box["y"] + (v - view["top"]) / view["spanV"] * box["height"])


def test_the_console_shows_the_request_and_takes_clicked_pairs(vr_daemon, browser, tmp_path):
    context = browser.new_context(viewport={"width": 1400, "height": 1100})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.set_default_timeout(30_000)
    try:
        page.goto(vr_daemon.url + "/console/")
        page.wait_for_selector("#routine option[value='vr-coarse']", state="attached")
        page.fill("#token-input", vr_daemon.token)
        page.click("#token-form button")
        page.select_option("#routine", "vr-coarse")
        page.fill("#seed", str(SEED))
        page.click("#start")
        truth = Truth(vr_daemon.cell_file, SEED)
        with vr_daemon.client(token=None) as c:
            last = (c.get("/operator/request").json()["last"] or {}).get("request", 0)
            for round_ in range(4):
                req = next_request(c, last)
                page.wait_for_function(f"document.querySelector('#op-title').textContent.includes('request {req['id']}')")
                assert page.is_visible("#operator-panel") and page.is_visible("#op-canvas")
                # brought into sight when it opened, however long the form above it
                assert page.evaluate("() => { const r = document.querySelector('#op-instruction')"
                                     ".getBoundingClientRect(); return r.top >= 0 && r.bottom <= innerHeight; }")
                assert page.text_content("#op-instruction") == req["instruction"]
                assert page.is_disabled("#op-submit") and not page.is_visible("#op-done")
                page.wait_for_function("document.querySelector('#op-canvas').dataset.spanU !== undefined")
                view = {k: float(page.eval_on_selector("#op-canvas", f"c => c.dataset.{k}"))
                        for k in ("left", "top", "spanU", "spanV")}
                shown = np.array([[p["u"], p["v"]] for p in req["model_points"]])
                clicks = truth.clicks(req)[:5]  # the fewest allowed
                for n, click in enumerate(clicks, 1):
                    # as a person would: the frame scrolled into view (the parameters' descriptions make the page long)
                    page.locator("#op-canvas").scroll_into_view_if_needed()
                    box = page.locator("#op-canvas").bounding_box()
                    k = click["model_index"]
                    page.mouse.click(*screen_point(box, view, *shown[k]))  # the model point on the overlay
                    assert f"model point {k} is in the image" in page.text_content("#op-hint")
                    page.mouse.click(*screen_point(box, view, click["u"], click["v"]))  # then its image point
                    page.wait_for_function(f"document.querySelectorAll('#op-pairs li').length === {n}")
                # undo takes the last pair back; it is clicked again
                page.click("#op-undo")
                assert page.locator("#op-pairs li").count() == 4 and page.is_disabled("#op-submit")
                page.mouse.click(*screen_point(box, view, *shown[clicks[-1]["model_index"]]))
                page.mouse.click(*screen_point(box, view, clicks[-1]["u"], clicks[-1]["v"]))
                page.wait_for_function("document.querySelectorAll('#op-pairs li').length === 5")
                items = page.locator("#op-pairs li").all_text_contents()
                assert [int(t.split()[1]) for t in items] == [cl["model_index"] for cl in clicks]
                for text, cl in zip(items, clicks):  # the image points, as clicked, within a screen pixel
                    u, v = (float(x) for x in text.split("(")[1].rstrip(")").split(","))
                    assert abs(u - cl["u"]) < 1.0 and abs(v - cl["v"]) < 1.0, (text, cl)
                if round_ == 0:
                    page.locator("#operator-panel").screenshot(path=tmp_path / "operator.png")
                    page.locator("#op-canvas").screenshot(path=tmp_path / "canvas.png")
                    page.screenshot(path=tmp_path / "console.png", full_page=True)
                page.click("#op-submit")
                last = eventually(lambda req=req: (r := c.get("/operator/request").json()["last"])
                                  and r["request"] == req["id"] and r["request"], timeout=20, what="the answer taken")
            job = c.get("/jobs").json()["jobs"][0]
            done = wait_for(c, job["id"], {"done", "faulted", "aborted"})
        assert done["state"] == "done" and done["routine"] == "vr-coarse", done
        page.wait_for_function("document.querySelector('#operator-panel').hidden")
        page.wait_for_function("document.querySelector('#job-state').textContent === 'done'")

        check_png(tmp_path / "operator.png")
        check_png(tmp_path / "console.png")
        canvas = check_png(tmp_path / "canvas.png", min_std=5.0).astype(int)
        # the drawn points: the ORU's green (#50dc50) rings and labels, the white crosses of the pairs
        green = (np.abs(canvas - np.array([80, 220, 80])[::-1]).max(axis=2) < 40).mean()
        white = (canvas.min(axis=2) > 235).mean()
        assert green > 0.0005 and white > 0.0002, (green, white)
        assert errors == []
    finally:
        if page.evaluate("sessionStorage.getItem('cellctl.lock')"):
            page.click("#release-lock")
            page.wait_for_function("sessionStorage.getItem('cellctl.lock') === null")
        context.close()
