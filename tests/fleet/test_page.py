"""The fleet page against a real plant database, in a real browser.

Three cells' records reach a real PostgreSQL the way a cell sends them (PostgresSink.deliver, with records as
the outbox makes them): press-1 is running a job, press-2 is paused in one, weld-3 stopped (offline, closed
gracefully). They have calibration versions with verification means and checks with drift, one of them a
drift verdict. `create_app` runs under uvicorn on loopback; Debian's chromium (headless, driven by Playwright,
as the console's tests do) reads the table and the plots and compares them with plant.py's answers from the
database; a record delivered while the page is open shows up at its next refresh. With the database stopped
the API answers 503 and the page says so, keeping what it had. A daemon whose cell file names the plant
database serves the same page at /fleet/. Screenshots: fleet.png (and fleet-updated.png, fleet-down.png)
under the tests' tmp_path.
"""

from __future__ import annotations

import itertools
import re
import threading
import time
from contextlib import contextmanager
from datetime import datetime, timedelta, timezone
from pathlib import Path

import cv2
import httpx
import psycopg
import pytest
import uvicorn
import yaml

from cellctl.fleet import plant
from cellctl.fleet.page import connector, create_app
from cellctl.fleet.postgres import PostgresSink
from cellctl.stores.outbox import Record

from tests.support.daemon import DaemonProcess, write_cell_file
from tests.support.servers import free_port
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py

REFRESH_WAIT_MS = 20_000  # the page reads again every 5 s

# the DOM's table as data: {cell: {state, live_job, last_seen, targets: {target: {version, mean, health}}}}
TABLE_JS = """() => Object.fromEntries([...document.querySelectorAll('#cells tbody tr')].map((tr) => {
  const text = (sel) => tr.querySelector(sel).textContent;
  const targets = {};
  for (const td of tr.querySelectorAll('td[data-target]')) {
    const field = ['version', 'mean', 'health'].find((k) => td.classList.contains(k));
    (targets[td.dataset.target] ||= {})[field] = td.textContent;
  }
  return [tr.dataset.cell, {state: text('td.state'), live_job: text('td.live-job'), last_seen: text('td.last-seen'),
                            state_class: tr.querySelector('td.state .badge').className, targets}];
}))"""
# the plots as data: {target: {cell: {means, checks, drift}}}
PLOTS_JS = """() => Object.fromEntries([...document.querySelectorAll('#charts figure.chart')].map((f) => [
  f.dataset.target, Object.fromEntries([...f.querySelectorAll('g.series')].map((g) => [g.dataset.cell, {
    means: g.querySelectorAll('circle.mean').length, checks: g.querySelectorAll('path.check').length,
    drift: g.querySelectorAll('path.check.drift').length, legend: !!f.querySelector(`g.legend[data-cell="${g.dataset.cell}"]`),
  }]))]))"""

_seq = itertools.count(1)


def when(days_ago: float) -> str:
    """A time as a cell's stores write it (calstore: %Y-%m-%dT%H:%M:%S%z)."""
    return (datetime.now(timezone.utc) - timedelta(days=days_ago)).strftime("%Y-%m-%dT%H:%M:%S%z")


def record(kind: str, key: str, body: dict) -> Record:
    return Record(next(_seq), kind, key, body, time.time(), "calibrations")


def calibration(cal_id: int, target: str, version: int, days_ago: float, mean_um: float, active: bool) -> Record:
    result = {"routine": "virtual-grid", "target": target,
              "stats": {"verification": {"mean_um": mean_um, "max_um": mean_um * 2.1, "rms_um": mean_um * 1.2}},
              "provenance": {"job": cal_id, "seed": 5}}
    return record("calibration", f"calibration/{cal_id}", {
        "id": cal_id, "target": target, "routine": "virtual-grid", "version": version, "created": when(days_ago),
        "active": active, "cell_file": "cell: {name: test}\n", "result": result, "samples": None})


def check(check_id: int, days_ago: float, targets: dict[str, tuple[int, float, float, bool]]) -> Record:
    """A health check: per target (calibration id, dx µm, dy µm, drifted)."""
    body = {target: {"calibration_id": cal, "drifted": drifted, "p_value": 0.001 if drifted else 0.4,
                     "drift": {"dx_um": dx, "dy_um": dy, "dx_std_um": 0.8, "dy_std_um": 0.8},
                     "action": "recalibrate" if drifted else "none"}
            for target, (cal, dx, dy, drifted) in targets.items()}
    return record("health_check", f"health_check/{check_id}", {
        "id": check_id, "created": when(days_ago), "verdict": "drift" if any(t["drifted"] for t in body.values())
        else "ok", "targets": body})


def job(job_id: int, state: str, event: int, days_ago: float = 0.01) -> Record:
    return record("job", f"job/{job_id}", {
        "id": job_id, "routine": "virtual-grid", "params": {"rows": 4}, "seed": 5, "state": state, "reason": "",
        "submitted_by": "console@127.0.0.1", "created": when(days_ago), "updated": when(0), "event": event})


def cell_state(state: str, live_job: int | None) -> Record:
    return record("cell", "cell", {"state": state, "live_job": live_job})


def send(dsn: str, cell: str, records: list[Record], stop: bool = False) -> None:
    """Deliver as the cell's replicator does; `stop`: then close as a stopping cell does (it says offline)."""
    sink = PostgresSink(dsn, cell, {"description": f"{cell} (test)", "software_revision": "0.1.0+test",
                                    "api_url": "http://127.0.0.1:8470"})
    sink.connect()
    sink.deliver(records)
    sink.close(graceful=stop)


@pytest.fixture(scope="module")
def plant_db(postgres):
    send(postgres.dsn, "press-1", [
        calibration(1, "cam1", 1, 20, 14.2, True), calibration(3, "tool", 1, 15, 22.5, True),
        check(1, 12, {"cam1": (1, 3.0, 4.0, False), "tool": (3, 1.0, 1.0, False)}),
        calibration(2, "cam1", 2, 9, 11.8, True),
        check(2, 5, {"cam1": (2, 2.0, 1.5, False), "tool": (3, 12.0, 9.0, True)}),
        job(7, "running", 40), cell_state("running", 7)])
    send(postgres.dsn, "press-2", [
        calibration(1, "cam1", 1, 18, 9.4, True), check(1, 10, {"cam1": (1, 0.8, 0.6, False)}),
        calibration(2, "cam1", 2, 4, 8.1, True),  # not checked since: unchecked
        job(3, "paused", 12), cell_state("paused", 3)])
    send(postgres.dsn, "weld-3", [
        calibration(1, "cam1", 1, 16, 12.9, True), check(1, 8, {"cam1": (1, 6.0, 8.0, True)}),
        job(2, "running", 9), cell_state("running", 2)], stop=True)
    return postgres


@contextmanager
def serving(app):
    """`app` under uvicorn, in a thread, on a free loopback port: its URL."""
    port = free_port()
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    def started() -> bool:
        assert thread.is_alive(), "uvicorn stopped"
        return srv.started

    eventually(started, timeout=20, every=0.05, what="uvicorn started")
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        thread.join(10)


@pytest.fixture(scope="module")
def server(plant_db):
    with serving(create_app(connector(plant_db.dsn))) as url:
        yield url


@pytest.fixture
def page(browser):
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.set_default_timeout(30_000)
    yield page
    context.close()
    assert not errors, errors  # no script error, ever


def read(dsn: str, query):
    with psycopg.connect(dsn) as conn:
        return query(conn)


def expected_table(dsn: str) -> dict:
    """What the table must show, from plant.py's answers."""
    status, jobs = read(dsn, plant.status), read(dsn, plant.jobs)
    routine = {(j["cell"], j["id"]): j["routine"] for j in jobs["jobs"]}
    targets = sorted({t for c in status["cells"] for t in c["calibrations"]})
    out = {}
    for c in status["cells"]:
        live = "–" if c["live_job"] is None else f"#{c['live_job']} {routine[(c['name'], c['live_job'])]}"
        cols = {}
        for t in targets:
            cal = c["calibrations"].get(t)
            cols[t] = ({"version": f"v{cal['version']}", "mean": f"{cal['verification_mean_um']:.1f}",
                        "health": cal["health"]} if cal else {"version": "–", "mean": "–", "health": "–"})
        out[c["name"]] = {"state": c["state"], "live_job": live, "targets": cols}
    return out


def expected_plots(dsn: str) -> dict:
    trend = read(dsn, plant.trend)["targets"]
    return {t: {cell: {"means": len(s["calibrations"]), "checks": len(s["checks"]),
                       "drift": sum(c["drifted"] for c in s["checks"]), "legend": True} for cell, s in cells.items()}
            for t, cells in trend.items()}


def shown(page) -> dict:
    return {name: {k: row[k] for k in ("state", "live_job", "targets")} for name, row in page.evaluate(TABLE_JS).items()}


def check_png(path: Path) -> None:
    """A real picture: it decodes, has some size and is not one flat colour."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 600, path
    assert float(image.std()) > 10, f"{path} looks blank"


# -- the API -----------------------------------------------------------------------------------------


def test_the_api_answers_what_plant_py_reads(server, plant_db):
    with httpx.Client(base_url=server, timeout=10) as client:
        status = client.get("/api/status").json()
        assert status == read(plant_db.dsn, plant.status)
        assert client.get("/api/trend").json() == read(plant_db.dsn, plant.trend)
        assert client.get("/api/jobs", params={"limit": 2}).json() == read(plant_db.dsn,
                                                                             lambda c: plant.jobs(c, limit=2))
        page = client.get("/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert 'src="fleet.js"' in page.text and "http" not in page.text  # nothing from elsewhere
        for name, media in (("fleet.js", "text/javascript"), ("fleet.css", "text/css")):
            r = client.get(f"/{name}")
            assert r.status_code == 200 and r.headers["content-type"].startswith(media)
        # the files are served by name, never from a path the request gives
        js = client.get("/fleet.js").text
        assert client.get("/fleet.js", params={"name": "page.py", "media_type": "text/plain"}).text == js
        assert client.get("/page.py").status_code == 404
        assert client.get("/api/jobs", params={"limit": 0}).status_code == 422
    # what the records said, as plant.py reads it: the page's tests below compare the DOM with these
    cells = {c["name"]: c for c in status["cells"]}
    assert {n: (c["state"], c["live_job"]) for n, c in cells.items()} == {
        "press-1": ("running", 7), "press-2": ("paused", 3), "weld-3": ("offline", None)}
    assert cells["press-1"]["calibrations"] == {
        "cam1": {"version": 2, "verification_mean_um": 11.8, "health": "ok"},
        "tool": {"version": 1, "verification_mean_um": 22.5, "health": "drift"}}
    assert cells["press-2"]["calibrations"]["cam1"]["health"] == "unchecked"
    assert cells["weld-3"]["calibrations"]["cam1"]["health"] == "drift"


# -- the page in the browser -----------------------------------------------------------------------


def test_the_page_shows_the_fleet_and_follows_it(server, plant_db, page, tmp_path):
    page.goto(server + "/")
    page.wait_for_selector("#cells tbody tr[data-cell='weld-3']")
    page.wait_for_selector("#charts figure.chart")
    assert page.text_content("#conn") == "live" and page.is_hidden("#message")

    # the table: every cell with its state (styled), live job, and per target version, mean and health
    assert shown(page) == expected_table(plant_db.dsn)
    rows = page.evaluate(TABLE_JS)
    assert "state-running" in rows["press-1"]["state_class"] and "state-offline" in rows["weld-3"]["state_class"]
    assert rows["press-1"]["live_job"] == "#7 virtual-grid" and rows["weld-3"]["live_job"] == "–"
    assert page.locator("tr[data-cell='press-1'] td.health[data-target='tool'] .badge.health-drift").count() == 1
    assert page.locator("tr[data-cell='press-2'] td.health[data-target='cam1'] .badge.health-unchecked").count() == 1
    assert rows["press-1"]["last_seen"].endswith("s ago")  # just now, and not flagged silent

    # the plots: one per target, a series per cell with its versions' means and its checks, drift verdicts marked
    plots = page.evaluate(PLOTS_JS)
    assert plots == expected_plots(plant_db.dsn)
    assert set(plots["cam1"]) == {"press-1", "press-2", "weld-3"} and set(plots["tool"]) == {"press-1"}
    assert plots["cam1"]["press-1"] == {"means": 2, "checks": 2, "drift": 0, "legend": True}
    assert plots["cam1"]["weld-3"]["drift"] == 1 and plots["tool"]["press-1"]["drift"] == 1
    # each mark where its value puts it: its tip says the value, and a larger value sits higher
    marks = page.evaluate("""() => [...document.querySelectorAll("figure[data-target='cam1'] g.series :is(circle.mean, path.check)")]
        .map((m) => [m.querySelector('title').textContent, m.getBoundingClientRect().y])""")
    values = [(float(re.search(r"(?:mean|drift) ([\d.]+) µm", tip).group(1)), y) for tip, y in marks]
    assert sorted(v for v, _ in values) == sorted([14.2, 11.8, 9.4, 8.1, 12.9, 5.0, 2.5, 1.0, 10.0])
    assert [v for v, _ in sorted(values, key=lambda p: p[1])] == sorted((v for v, _ in values), reverse=True)
    # a cell has one colour in the table and in every plot
    colour = page.evaluate("""() => [getComputedStyle(document.querySelector("tr[data-cell='press-2'] .swatch"))
        .backgroundColor, document.querySelector("figure[data-target='cam1'] g.series[data-cell='press-2'] circle")
        .getAttribute('fill')]""")
    r, g, b = (int(colour[1][i:i + 2], 16) for i in (1, 3, 5))
    assert colour[0] == f"rgb({r}, {g}, {b})"
    page.screenshot(path=tmp_path / "fleet.png", full_page=True)
    check_png(tmp_path / "fleet.png")

    # press-2 finishes its job and makes a third cam1 version: the open page shows it at its next refresh
    send(plant_db.dsn, "press-2", [job(3, "done", 13), calibration(3, "cam1", 3, 0, 7.3, True),
                                   cell_state("idle", None)])
    page.wait_for_function("""() => document.querySelector("tr[data-cell='press-2'] td.version[data-target='cam1']")
                              .textContent === 'v3'""", timeout=REFRESH_WAIT_MS)
    page.wait_for_function("""() => document.querySelectorAll(
        "figure[data-target='cam1'] g.series[data-cell='press-2'] circle.mean").length === 3""", timeout=REFRESH_WAIT_MS)
    assert shown(page) == expected_table(plant_db.dsn)
    assert shown(page)["press-2"] == {"state": "idle", "live_job": "–", "targets": {
        "cam1": {"version": "v3", "mean": "7.3", "health": "unchecked"},
        "tool": {"version": "–", "mean": "–", "health": "–"}}}
    assert page.evaluate(PLOTS_JS) == expected_plots(plant_db.dsn)
    page.screenshot(path=tmp_path / "fleet-updated.png", full_page=True)
    check_png(tmp_path / "fleet-updated.png")


def test_a_stopped_database_answers_503_and_the_page_says_so(server, plant_db, page, tmp_path):
    page.goto(server + "/")
    page.wait_for_selector("#cells tbody tr[data-cell='press-1']")
    before = shown(page)
    plant_db.stop()
    try:
        r = httpx.get(server + "/api/status", timeout=10)
        assert r.status_code == 503 and r.headers["content-type"] == "application/json"
        detail = r.json()["detail"]
        assert detail.startswith("the plant database cannot be reached: ") and "Traceback" not in detail
        assert plant_db.password not in detail
        # the page says so at its next refresh and keeps what it last read
        page.wait_for_function("document.querySelector('#conn').textContent === 'plant database unreachable'",
                               timeout=REFRESH_WAIT_MS)
        assert page.is_visible("#message") and "cannot be reached" in page.text_content("#message")
        assert shown(page) == before
        page.screenshot(path=tmp_path / "fleet-down.png", full_page=True)
    finally:
        plant_db.resume()
    page.wait_for_function("document.querySelector('#conn').textContent === 'live'", timeout=REFRESH_WAIT_MS)
    assert page.is_hidden("#message")


def test_a_malformed_dsn_is_a_503_without_its_password():
    with serving(create_app(connector("postgresql://cellctl:s3cret-value@127.0.0.1:notaport/plant"))) as url:
        r = httpx.get(url + "/api/trend", timeout=10)
    assert r.status_code == 503 and "cannot be reached" in r.text and "s3cret-value" not in r.text, r.text


# -- the daemon serves it at /fleet/ ---------------------------------------------------------------------


def test_a_daemon_in_a_fleet_serves_the_page_at_fleet(plant_db, tmp_path):
    cell_file = write_cell_file(tmp_path, realtime_factor=0.0)
    data = yaml.safe_load(cell_file.read_text())
    data["fleet"] = {"postgres": {"dsn_env": "CELLCTL_TEST_PLANT_DSN"}, "heartbeat_s": 1}
    cell_file.write_text(yaml.safe_dump(data))
    daemon = DaemonProcess(cell_file)
    daemon.extra_env["CELLCTL_TEST_PLANT_DSN"] = plant_db.dsn
    with daemon.start():
        with httpx.Client(base_url=daemon.url, timeout=10) as client:  # no token: reading
            page = client.get("/fleet/")
            assert page.status_code == 200 and 'src="fleet.js"' in page.text
            assert client.get("/fleet/fleet.js").status_code == 200
            # the daemon's own cell reaches the plant database, and so its own fleet page
            def names() -> list[str]:
                status = client.get("/fleet/api/status")
                assert status.status_code == 200, status.text
                return [c["name"] for c in status.json()["cells"]]

            eventually(lambda: "sim-microcell" in names(), timeout=20, every=0.2, what="the daemon's own cell listed")
            assert {"sim-microcell", "press-1", "press-2", "weld-3"} <= set(names())
            assert client.get("/fleet/api/trend").json() == read(plant_db.dsn, plant.trend)
            # in the daemon's schema, with the 503 documented; read-only: other methods get 405
            schema = client.get("/openapi.json").json()["paths"]
            assert set(schema["/fleet/api/status"]) == {"get"} and "503" in schema["/fleet/api/status"]["get"]["responses"]
            assert "/fleet/" not in schema  # the page, like the console, is not part of the API
            assert client.options("/fleet/api/trend").headers["allow"] == "GET"
            assert client.post("/fleet/api/status").status_code == 405
            refused = client.get("/fleet/api/jobs", params={"limit": 0})  # the daemon's own 422, as documented
            assert refused.status_code == 422 and "limit" in refused.json()["detail"]
            assert "422" in schema["/fleet/api/jobs"]["get"]["responses"]
