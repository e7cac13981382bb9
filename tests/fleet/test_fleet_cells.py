"""Issue 15 as judged: three simulated cells (three daemons, their own names and seeds) share one real
PostgreSQL and one real Mosquitto. Every record of each cell is in the plant database exactly once, the plant's
view agrees with each cell's own API, an outage of both servers while jobs run changes no result and loses
nothing, a daemon killed between its local commit and the upload loses and duplicates nothing, a stopped
cell's retained status says offline, and a replaced cell PC gets its calibrations back."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import paho.mqtt.client as paho
import psycopg
import pytest
import yaml

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine

from tests.support.daemon import SMALL, DaemonProcess, wait_for, wait_step, write_cell_file
from tests.support.plant_records import local_records, plant_records
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py

ROOT = Path(__file__).resolve().parents[2]
SEEDS = {"cell-a": 11, "cell-b": 12, "cell-c": 13}
PREFIX = "acme/plant1/line3"
KEEPALIVE_S = 5
REALTIME = 0.3  # a small virtual grid (11.5 s of cell time) takes a few seconds: long enough to be caught running


class Historian:
    """The plant's persistent-session QoS 1 subscriber to every cell's job events and statuses."""

    def __init__(self, broker):
        self.events: list[dict] = []
        self.status: dict[str, list[tuple[float, dict]]] = {}
        self.lock = threading.Lock()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id="plant-historian",
                                  protocol=paho.MQTTv311, clean_session=False)
        self.client.username_pw_set(broker.username, broker.password)
        self.client.reconnect_delay_set(0.2, 1.0)
        self.client.on_connect = lambda c, *a: c.subscribe([(f"{PREFIX}/+/events/job", 1),
                                                             (f"{PREFIX}/+/status", 1)])
        self.client.on_message = self._message
        self.client.connect("127.0.0.1", broker.port, keepalive=10)
        self.client.loop_start()

    def _message(self, client, userdata, message) -> None:
        body = json.loads(message.payload)
        with self.lock:
            if message.topic.endswith("/events/job"):
                self.events.append(body)
            else:
                self.status.setdefault(message.topic.split("/")[-2], []).append((time.monotonic(), body))

    def job_events(self, cell: str) -> list[int]:
        """The job_state ids received from `cell` in arrival order, a duplicate (same key) dropped."""
        seen, out = set(), []
        with self.lock:
            for e in self.events:
                if e["cell"] == cell and e["key"] not in seen:
                    seen.add(e["key"])
                    out.append(e["id"])
        return out

    def last_status(self, cell: str) -> dict | None:
        with self.lock:
            return self.status[cell][-1][1] if self.status.get(cell) else None

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


class Plant:
    """The three cells' daemons, the plant's servers, the credentials (owner-only files) and the historian."""

    def __init__(self, folder: Path, postgres, mosquitto):
        self.folder, self.postgres, self.mosquitto = folder, postgres, mosquitto
        self.dsn_file = self.secret("plant.dsn", postgres.dsn)
        self.password_file = self.secret("mqtt.password", mosquitto.password)
        self.historian = Historian(mosquitto)
        self.files = {name: self.cell_file(name, folder / name) for name in SEEDS}
        self.daemons = {name: DaemonProcess(path).start() for name, path in self.files.items()}

    def secret(self, name: str, value: str) -> Path:
        path = self.folder / name
        path.write_text(value + "\n")
        os.chmod(path, 0o600)
        return path

    def cell_file(self, name: str, folder: Path, store: Path | None = None) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        path = write_cell_file(folder, realtime_factor=REALTIME)
        data = yaml.safe_load(path.read_text())
        data["sim"]["seed"] = SEEDS[name]
        if store is not None:
            data["store_dir"] = str(store)
        data["fleet"] = {"cell_id": name, "heartbeat_s": 1, "postgres": {"dsn_file": str(self.dsn_file)},
                         "mqtt": {"host": "127.0.0.1", "port": self.mosquitto.port, "topic_prefix": PREFIX,
                                  "username": self.mosquitto.username, "password_file": str(self.password_file),
                                  "keepalive_s": KEEPALIVE_S, "progress_interval_s": 0.5}}
        path.write_text(yaml.safe_dump(data))
        return path

    def restart(self, name: str) -> DaemonProcess:
        self.daemons[name] = DaemonProcess(self.files[name]).start()
        return self.daemons[name]

    def run(self, name: str, routine: str, params: dict | None = None) -> int:
        with self.daemons[name].client() as c:
            answer = c.post("/jobs", json={"routine": routine, "params": params or {}})
            assert answer.status_code == 201, answer.text
            return answer.json()["id"]

    def fleet(self, *args: str) -> dict:
        out = subprocess.run([sys.executable, "-m", "cellctl.cli", "fleet", *args, "--dsn-file", str(self.dsn_file),
                              "--json"], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout)

    def close(self) -> None:
        for d in self.daemons.values():
            if d.proc is not None and d.proc.poll() is None:
                d.terminate()
            d.log.close()
        self.historian.close()


@pytest.fixture(scope="module")
def plant(postgres, mosquitto, tmp_path_factory):
    p = Plant(tmp_path_factory.mktemp("plant"), postgres, mosquitto)
    yield p
    p.close()


# -- the cell's own records, and the plant database's -----------------------------------------------------


def assert_replicated(plant: Plant, cells=tuple(SEEDS), timeout: float = 30.0) -> float:
    """Wait until the plant database holds every record of each cell, once; returns how long that took (s)."""
    t0 = time.monotonic()
    while True:
        differences = {}
        for name in cells:
            local = local_records(plant.daemons[name].store)
            remote, rows = plant_records(plant.postgres.dsn, name)
            for table, keys in local.items():
                if keys != remote[table]:
                    differences[(name, table)] = (len(keys), len(remote[table]))
                assert rows[table] == len(remote[table])  # keys are unique in the plant: once each
        if not differences:
            return time.monotonic() - t0
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"not replicated in {timeout} s (local, plant): {differences}")
        time.sleep(0.2)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """What a small virtual grid gives on each cell's seed without a fleet: in-process, `cellctl run`."""
    out = {}
    for name, seed in SEEDS.items():
        folder = tmp_path_factory.mktemp(f"reference-{name}")
        config, text = load_cell_file(write_cell_file(folder, realtime_factor=0.0))
        out[name] = run_routine("virtual-grid", config, text, folder / "run", seed=seed, overrides=SMALL)
    return out


def same_result(result: dict, expected: dict) -> None:
    assert result["stats"] == expected["stats"]
    assert result["cell_time_s"] == expected["cell_time_s"]
    assert result["model"] == expected["model"]


# -- the judged scenarios ----------------------------------------------------------------------------------


def test_three_cells_one_plant_database_every_record_once(plant, reference):
    jobs = {name: [plant.run(name, "virtual-grid", SMALL)] for name in SEEDS}
    for name in SEEDS:
        with plant.daemons[name].client() as c:
            assert wait_for(c, jobs[name][0], {"done"}, timeout=180)["state"] == "done"
        jobs[name].append(plant.run(name, "calibration-check", {"targets": "cam1"}))
    for name in SEEDS:
        with plant.daemons[name].client() as c:
            wait_for(c, jobs[name][1], {"done"}, timeout=180)
            same_result(c.get(f"/jobs/{jobs[name][0]}/result").json(), reference[name])
    assert_replicated(plant)

    status = {c["name"]: c for c in plant.fleet("status")["cells"]}
    assert set(status) == set(SEEDS)
    for name in SEEDS:
        with plant.daemons[name].client() as c:
            cell, cals, health = c.get("/cell").json(), c.get("/calibrations").json()["calibrations"], c.get(
                "/health/calibrations").json()["targets"]
        mine = status[name]
        assert mine["state"] == "idle" and mine["live_job"] == cell["job"] is None
        active = {k["target"]: k for k in cals if k["active"]}
        assert set(mine["calibrations"]) == set(active)
        for target, k in active.items():
            seen = mine["calibrations"][target]
            assert seen["version"] == k["version"]
            assert seen["verification_mean_um"] == k["stats"]["verification"]["mean_um"]
            assert seen["health"] == health[target]["verdict"]
        assert mine["calibrations"]["cam1"]["health"] in ("ok", "drift")  # the check ran on it
    listed = plant.fleet("jobs")["jobs"]
    for name in SEEDS:
        mine = {j["id"]: j for j in listed if j["cell"] == name}
        assert {i: (j["routine"], j["state"]) for i, j in mine.items()} == {
            jobs[name][0]: ("virtual-grid", "done"), jobs[name][1]: ("calibration-check", "done")}
        assert mine[jobs[name][0]]["samples"] == len(folder_rows(plant, name, jobs[name][0]))


def folder_rows(plant: Plant, cell: str, job_id: int) -> list:
    with plant.daemons[cell].client() as c:
        text = c.get(f"/jobs/{job_id}/samples").text
    return text.strip().splitlines()[1:]


def test_an_outage_of_both_servers_while_jobs_run_changes_nothing_and_loses_nothing(plant, reference):
    plant.postgres.stop()
    t_down = time.monotonic()
    try:
        jobs = {name: [plant.run(name, "virtual-grid", SMALL) for _ in range(2)] for name in SEEDS}
        with plant.daemons["cell-a"].client() as c:
            wait_step(c, jobs["cell-a"][0], 4)
        plant.mosquitto.stop()  # restarted while the jobs run
        time.sleep(2)
        plant.mosquitto.resume()
        for name in SEEDS:
            with plant.daemons[name].client() as c:
                for job_id in jobs[name]:
                    assert wait_for(c, job_id, {"done", "faulted"}, timeout=240)["state"] == "done"
                    same_result(c.get(f"/jobs/{job_id}/result").json(), reference[name])
        assert time.monotonic() - t_down < 60, "the jobs outlasted the database's outage: make them shorter"
        time.sleep(max(0.0, 60 - (time.monotonic() - t_down)))
    finally:
        plant.postgres.resume()
        if plant.mosquitto.proc is None:
            plant.mosquitto.resume()
    assert_replicated(plant, timeout=30)

    # the historian was away from nothing: every job state change of every cell, in order
    def missing() -> dict:
        gaps = {}
        for name in SEEDS:
            with sqlite3.connect(plant.daemons[name].store / "daemon.sqlite") as db:
                local = [r[0] for r in db.execute("SELECT id FROM job_events ORDER BY id")]
            got = plant.historian.job_events(name)
            assert got == sorted(got), f"{name}: job events out of order: {got}"
            if got != local:
                gaps[name] = sorted(set(local) - set(got))
        return gaps

    eventually(lambda: not missing(), timeout=15, every=0.2,
               what=lambda: f"every job event at the historian (missing: {missing()})")


def test_a_daemon_killed_between_its_commit_and_the_upload_loses_and_duplicates_nothing(plant):
    name = "cell-a"
    plant.postgres.stop()  # the upload waits; the cell commits locally
    try:
        job_id = plant.run(name, "virtual-grid", SMALL)
        with plant.daemons[name].client() as c:
            wait_for(c, job_id, {"done"}, timeout=120)
        plant.daemons[name].kill9()
    finally:
        plant.postgres.resume()
    plant.restart(name)
    assert_replicated(plant, cells=(name,))

    # killed while a job runs and its records are being sent: the job is faulted, then resumed to the end
    job_id = plant.run(name, "virtual-grid", SMALL)
    with plant.daemons[name].client() as c:
        wait_step(c, job_id, 10)
    plant.daemons[name].kill9()
    d = plant.restart(name)
    with d.client() as c:
        assert c.get(f"/jobs/{job_id}").json()["state"] == "faulted"
        assert c.post(f"/jobs/{job_id}/ack").status_code == 200
        assert c.post(f"/jobs/{job_id}/resume").status_code == 200
        wait_for(c, job_id, {"done"}, timeout=120)
    assert_replicated(plant, cells=(name,))
    with psycopg.connect(plant.postgres.dsn) as conn:
        kept = conn.execute("SELECT step, row_index, data FROM samples WHERE cell = %s AND job_id = %s "
                            "ORDER BY step, row_index", (name, job_id)).fetchall()
    assert len(kept) == len(folder_rows(plant, name, job_id))


def test_a_stopped_cell_says_offline(plant):
    name = "cell-c"
    plant.daemons[name].terminate()  # stopped: it says so itself
    def state() -> str | None:
        return (plant.historian.last_status(name) or {}).get("state")

    eventually(lambda: state() == "offline", timeout=5, every=0.05,
               what=lambda: f"{name} offline (last status {plant.historian.last_status(name)})")
    assert plant.historian.last_status(name)["reason"] == "cell stopped"
    with psycopg.connect(plant.postgres.dsn) as conn:
        assert conn.execute("SELECT state FROM cells WHERE name = %s", (name,)).fetchone()[0] == "offline"

    plant.restart(name)
    eventually(lambda: state() == "online", timeout=15, every=0.05, what=f"{name} online again")
    plant.daemons[name].kill9()  # dead without a word: the broker's Last Will says it
    eventually(lambda: state() == "offline", timeout=1.5 * KEEPALIVE_S + 1, every=0.05,
               what="an offline status within the keep-alive")
    assert plant.historian.last_status(name)["reason"] == "connection lost"
    plant.restart(name)


def test_a_replaced_cell_pc_gets_its_calibrations_back(plant, tmp_path):
    name = "cell-b"
    pixels = [(400.5, 300.25), (1224.0, 1025.0), (2000.0, 1700.5)]
    with plant.daemons[name].client() as c:
        before = [c.get("/locate", params={"camera": "cam1", "u_px": u, "v_px": v}).json() for u, v in pixels]
    assert all(b.get("x_mm") is not None for b in before), before
    plant.daemons[name].terminate()

    store = tmp_path / "new-pc-store"
    out = subprocess.run([sys.executable, "-m", "cellctl.cli", "fleet", "restore", "--cell", name,
                          "--dsn-file", str(plant.dsn_file), "--store", str(store)], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "restored" in out.stdout
    again = subprocess.run([sys.executable, "-m", "cellctl.cli", "fleet", "restore", "--cell", name,
                            "--dsn-file", str(plant.dsn_file), "--store", str(store)], cwd=ROOT,
                           capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "restore into an empty store" in again.stderr, again.stderr

    new_pc = DaemonProcess(plant.cell_file(name, tmp_path / "new-pc", store=store)).start()
    try:
        with new_pc.client() as c:
            after = [c.get("/locate", params={"camera": "cam1", "u_px": u, "v_px": v}).json() for u, v in pixels]
            restored = {k["id"]: k for k in c.get("/calibrations").json()["calibrations"]}
    finally:
        new_pc.terminate()
        new_pc.log.close()
    assert after == before
    with psycopg.connect(plant.postgres.dsn) as conn:
        ids = {r[0] for r in conn.execute("SELECT id FROM calibrations WHERE cell = %s", (name,))}
    assert set(restored) == ids
    plant.restart(name)
