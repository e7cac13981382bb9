"""`/metrics` in Prometheus's text format: it parses, needs no token, leaks no secret, and moves as a job runs
(through the real daemon on the simulated micro cell); what the stores know survives a restart, the request
counters do not. In-process: the health verdict and the age of the last check, and `count_request`."""

from __future__ import annotations

import time
from types import SimpleNamespace

import pytest
from prometheus_client.parser import text_string_to_metric_families

from cellctl.http import metrics

from tests.support.daemon import SEED, SMALL, DaemonProcess, wait_for, wait_step, write_cell_file


def samples(text: str) -> dict[tuple, float]:
    """Every sample of the exposition, by (name, sorted labels); it must parse as Prometheus text."""
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def scrape(client) -> tuple[str, dict[tuple, float]]:
    r = client.get("/metrics")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
    return r.text, samples(r.text)


def value(found: dict, name: str, default=None, **labels) -> float | None:
    return found.get((name, tuple(sorted(labels.items()))), default)


VG = {"routine": "virtual-grid"}


def test_metrics_parse_need_no_token_and_move_as_a_job_runs(tmp_path):
    cell_file = write_cell_file(tmp_path, realtime_factor=0.3)
    with DaemonProcess(cell_file).start() as d, d.client(token=None) as anon, d.client() as c:
        text, before = scrape(anon)  # no token: a scraper has none
        for device in ("arm", "gripper", "cam1", "cam2", "cam3"):
            assert any(k[0] == "cellctl_device_up" and ("device", device) in k[1] and v == 1.0
                       for k, v in before.items()), device
        assert value(before, "cellctl_jobs", 0.0, state="done", **VG) == 0.0
        assert value(before, "cellctl_live_job_id") == 0.0
        assert value(before, "cellctl_job_cell_time_seconds_count", **VG) is None
        assert not any(k[0] == "cellctl_calibration_active_version" for k in before)

        assert anon.post("/jobs", json={"routine": "virtual-grid"}).status_code == 401
        t0 = time.monotonic()
        job = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": SEED}).json()
        wait_step(c, job["id"], 2)
        _, live = scrape(anon)
        assert value(live, "cellctl_live_job_id") == job["id"]
        assert 2 <= value(live, "cellctl_live_job_step", **VG) <= 24
        assert value(live, "cellctl_live_job_steps", **VG) == 24
        assert value(live, "cellctl_jobs", state="running", **VG) == 1.0
        done = wait_for(c, job["id"], {"done"})
        wall = time.monotonic() - t0
        result = c.get(f"/jobs/{job['id']}/result").json()
        text, after = scrape(anon)

    # the job counted once, its times in the histograms
    assert value(after, "cellctl_jobs", state="done", **VG) == 1.0
    assert value(after, "cellctl_jobs", state="running", **VG) == 0.0
    assert value(after, "cellctl_job_cell_time_seconds_count", **VG) == 1.0
    assert value(after, "cellctl_job_cell_time_seconds_sum", **VG) == pytest.approx(result["cell_time_s"])
    assert value(after, "cellctl_job_cell_time_seconds_bucket", le="+Inf", **VG) == 1.0
    assert value(after, "cellctl_job_wall_time_seconds_count", **VG) == 1.0
    assert 0 < value(after, "cellctl_job_wall_time_seconds_sum", **VG) <= wall
    assert value(after, "cellctl_live_job_id") == 0.0 and value(after, "cellctl_live_job_step", **VG) is None
    # the calibration it made: active, its verification mean, not checked yet (no check: no age)
    cal = result["calibration"]
    labels = {"target": cal["target"], "routine": "virtual-grid"}
    assert value(after, "cellctl_calibration_active_version", **labels) == cal["version"]
    assert value(after, "cellctl_calibration_verification_mean_meters", **labels) == pytest.approx(
        result["stats"]["verification"]["mean_um"] * 1e-6)
    assert value(after, "cellctl_calibration_health", target=cal["target"], verdict="unchecked") == 1.0
    assert value(after, "cellctl_calibration_health", target=cal["target"], verdict="ok") == 0.0
    assert value(after, "cellctl_calibration_last_check_age_seconds", target=cal["target"]) is None
    # requests by outcome: the refused POST, the accepted ones, the polls
    requests = {dict(k[1])["outcome"]: v for k, v in after.items()
                if k[0] == "cellctl_requests_total" and dict(k[1])["front_end"] == "http"}
    assert requests["refused 401"] == 1.0 and requests["ok"] >= 5
    assert d.token not in text and done["state"] == "done"

    # a restart: what the job store knows is still there; the request counters start again
    with DaemonProcess(cell_file).start() as d2, d2.client(token=None) as anon:
        _, again = scrape(anon)
    assert value(again, "cellctl_jobs", state="done", **VG) == 1.0
    assert value(again, "cellctl_job_wall_time_seconds_count", **VG) == 1.0
    assert value(again, "cellctl_calibration_active_version", **labels) == cal["version"]
    assert value(again, "cellctl_requests_total", front_end="http", outcome="refused 401") is None


def test_health_verdict_and_age_of_the_last_check(tmp_path):
    """Read from the stores at scrape time: a drift verdict for the checked target, the age of its check."""
    from prometheus_client import CollectorRegistry, generate_latest

    from cellctl.stores.calibrations import CalibrationStore
    from cellctl.stores.jobs import JobStore

    calstore = CalibrationStore(tmp_path / "store")
    jobs = JobStore(tmp_path / "store" / "daemon.sqlite")
    cam1 = calstore.save("cam1", {"routine": "virtual-grid", "model": {}, "stats": {"verification": {"mean_um": 6.5}}},
                         "cell: {}")
    calstore.save("nozzle", {"routine": "rotation-sweep", "model": {}, "stats": {}}, "cell: {}")
    calstore.save_check({"verdict": "drift", "drifted": ["cam1"], "checked": {"cam1": cam1.id}, "updated": {},
                         "actions": {"cam1": "touch-up"}, "cell_time_s": 1.0, "seed": 1,
                         "stats": {"drift": {"cam1": {"dx_um": 9.0}}, "test": {"cam1": {"p_value": 0.001}}}})
    daemon = SimpleNamespace(jobs=jobs, calstore=calstore, worker=SimpleNamespace(live_job=None),
                             cells=SimpleNamespace(status=lambda: [{"name": "arm", "kind": "arm", "backend": "sim",
                                                                    "state": "faulted"}]))
    registry = CollectorRegistry()
    registry.register(metrics.CellCollector(daemon))
    found = samples(generate_latest(registry).decode())
    assert value(found, "cellctl_calibration_health", target="cam1", verdict="drift") == 1.0
    assert value(found, "cellctl_calibration_health", target="cam1", verdict="ok") == 0.0
    assert value(found, "cellctl_calibration_health", target="nozzle", verdict="unchecked") == 1.0
    assert 0 <= value(found, "cellctl_calibration_last_check_age_seconds", target="cam1") < 60
    assert value(found, "cellctl_calibration_last_check_age_seconds", target="nozzle") is None
    assert value(found, "cellctl_calibration_verification_mean_meters", target="cam1",
                 routine="virtual-grid") == pytest.approx(6.5e-6)
    # a calibration whose routine has no verification points has no mean, rather than a made-up one
    assert value(found, "cellctl_calibration_verification_mean_meters", target="nozzle",
                 routine="rotation-sweep") is None
    assert value(found, "cellctl_device_up", device="arm", kind="arm", backend="sim") == 0.0
    jobs.close()
    calstore.close()


def test_count_request_is_what_other_front_ends_call():
    before = metrics.REQUESTS.labels("opcua", "refused BadUserAccessDenied")._value.get()
    metrics.count_request("opcua", "refused BadUserAccessDenied")
    assert metrics.REQUESTS.labels("opcua", "refused BadUserAccessDenied")._value.get() == before + 1
    with pytest.raises(ValueError, match="front_end: 'mqtt'; allowed: http, opcua"):
        metrics.count_request("mqtt", "ok")
    with pytest.raises(ValueError, match="outcome"):
        metrics.count_request("http", "")
    assert [metrics.http_outcome(s) for s in (200, 201, 304, 401, 423, 500)] == [
        "ok", "ok", "ok", "refused 401", "refused 423", "error"]
