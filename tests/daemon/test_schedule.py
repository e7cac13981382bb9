"""Calibration checks on a schedule, through the real daemon: submitted by the schedule only when the cell is idle
and nobody holds the operator lock, audited as such; a drift verdict is an event and shows in the health."""

from __future__ import annotations

import json
import shutil
import time

import httpx
import yaml

from tests.support.daemon import DaemonProcess, wait_for, write_cell_file
from tests.support.wait import eventually

EVERY_H = 0.0015  # 5.4 s between checks
REPEATABILITY = {"positions": 2, "cycles": 3, "drift_cycles": 1}


def scheduled_cell(tmp_path, calibrated_cell):
    path = write_cell_file(tmp_path, realtime_factor=0.05)
    data = yaml.safe_load(path.read_text())
    data["health"] = {"every_h": EVERY_H, "targets": ["cam1"]}
    data["sim"]["seed"] = calibrated_cell.seed
    data["sim"]["drift"] = {"cam1": {"map_shift_um": [8.0, 0.0]}}  # the camera was bumped since calibrate-cell
    path.write_text(yaml.safe_dump(data))
    shutil.copytree(calibrated_cell.store_path, tmp_path / "store")  # the daemon's store: the calibrations
    return path


def scheduled_jobs(client) -> list[dict]:
    return [j for j in client.get("/jobs").json()["jobs"] if j["routine"] == "calibration-check"]


def idle_poses(client, seconds: float) -> list[list[dict]]:
    """The arm's reported pose polled while no job is live, in runs of polls between which no job ran."""
    runs, last, deadline = [], None, time.monotonic() + seconds
    while time.monotonic() < deadline:
        jobs = client.get("/jobs").json()["jobs"]
        cell = client.get("/cell").json()
        idle = cell["job"] is None and all(j["state"] in ("done", "aborted", "faulted") for j in jobs)
        after = client.get("/jobs").json()["jobs"]
        key = [(j["id"], j["state"]) for j in jobs]
        if idle and key == [(j["id"], j["state"]) for j in after]:
            if key != last:
                runs.append([])
            runs[-1].append({k: v for k, v in cell["arm_pose"].items() if k != "read_at"})
            last = key
        else:
            last = None
        time.sleep(0.05)
    return runs


def test_scheduled_checks_wait_for_an_idle_cell_and_a_free_lock(tmp_path, calibrated_cell):
    with DaemonProcess(scheduled_cell(tmp_path, calibrated_cell)).start() as daemon, daemon.client() as c:
        lock = c.post("/lock", json={"holder": "engineer", "ttl_s": 60}).json()["lock_id"]
        schedule = c.get("/cell").json()["health_schedule"]
        assert schedule["every_h"] == EVERY_H and schedule["next_check"]
        time.sleep(EVERY_H * 3600 + 2.5)  # due, but the lock is held
        assert scheduled_jobs(c) == []
        assert "lock" in c.get("/cell").json()["health_schedule"]["waiting_for"]
        # the engineer runs a job (one that calibrates nothing): the check stays away while it runs
        job = c.post("/jobs", json={"routine": "repeatability", "params": REPEATABILITY},
                     headers={"X-Cellctl-Lock": lock}).json()
        assert c.delete("/lock", headers={"X-Cellctl-Lock": lock}).status_code == 200
        wait_for(c, job["id"], {"running"})
        running = c.get(f"/jobs/{job['id']}").json()
        assert scheduled_jobs(c) == [], running
        wait_for(c, job["id"], {"done"})
        # idle and free: the schedule submits its check, which finds the drift
        check = eventually(lambda: scheduled_jobs(c), timeout=10, every=0.1, what="the scheduled check")[0]
        assert check["submitted_by"] == "schedule"
        done = wait_for(c, check["id"], {"done", "faulted"})
        assert done["state"] == "done", done
        result = c.get(f"/jobs/{check['id']}/result").json()
        assert result["verdict"] == "drift" and result["drifted"] == ["cam1"]
        assert c.get("/health/calibrations").json()["targets"]["cam1"]["verdict"] == "drift"
        audit = c.get("/audit").json()["audit"]
        assert any(a["client"] == "schedule" and a["action"] == "schedule: calibration check" for a in audit), audit[-3:]
        # nothing moves between jobs (the schedule's next check may run meanwhile: a job of its own)
        runs = idle_poses(c, 3.0)
        assert runs and all(p == run[0] for run in runs for p in run)
        events = events_until(daemon, "health")
        assert events and events[0]["drifted"] == ["cam1"] and events[0]["job"] == check["id"]


def events_until(daemon: DaemonProcess, kind: str, timeout: float = 5.0) -> list[dict]:
    """The `kind` events in the daemon's event stream from its start."""
    found = []
    with httpx.Client(base_url=daemon.url, headers={"Authorization": f"Bearer {daemon.token}"}, timeout=timeout) as c:
        with c.stream("GET", "/events", params={"since": 0}) as stream:
            event = None
            deadline = time.monotonic() + timeout
            for line in stream.iter_lines():
                if line.startswith("event:"):
                    event = line.split(":", 1)[1].strip()
                elif line.startswith("data:") and event == kind:
                    found.append(json.loads(line.split(":", 1)[1]))
                    break
                if time.monotonic() > deadline:
                    break
    return found
