"""Benchmark of a fleet: N simulated cells on this machine replicating to one PostgreSQL and one Mosquitto.

    .venv/bin/python tools/bench_fleet.py [--cells 20] [--jobs 2] [--realtime 5] [--idle-s 20] [--no-burst]
                                          [--verbose] [--json FILE] [--keep]

Starts a plant database and a broker as the fleet tests do (tests/fleet/servers.py: loopback, free ports,
temporary folders), a persistent QoS 1 subscriber to every cell's job events, and N daemons (cell-01 ...,
each with its own sim seed) whose cell files replicate to both. Then three phases:

1. idle: every daemon up, both sinks connected, nothing running, for --idle-s; nobody polls the daemons;
2. load: each cell runs --jobs small virtual-grid jobs back to back (POST /jobs), until all are done and every
   backlog (GET /metrics) is 0;
3. burst (--no-burst to skip): PostgreSQL stopped, one job per cell, PostgreSQL started again: how long until
   every backlog is drained.

It prints the replication lag of the load phase's job state changes (to PostgreSQL: the plant's `received - at`
of job_states; to MQTT: the subscriber's receive time - the payload's "at"), records and rows per second, each
daemon's CPU (utime+stime of /proc/<pid>/stat) and RSS (VmRSS) per phase, the servers' CPU and memory (PSS), the
job wall times, and how busy the machine was (someone else's processes running beside the benchmark disturb it:
the `others` column).
Everything it starts is stopped when it ends, on Ctrl-C or an error too. Timings are printed, never asserted.

A SMALL job is 11.5 s of cell time and ~4 s of a daemon's CPU (rendering the simulated camera's frames, a cost a
real cell does not have). With the default --realtime 5 (a job ~1 min) 20 cells keep about 1.3 of 2 cores busy, so
the lag measured is the fleet code's, not the CPU queue's, and the run takes about 5 minutes; --realtime 0.3 (the
fleet tests' factor) or 0 saturates the machine and the lag grows with the run queue.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the tests' helpers: tests.support

import httpx
import numpy as np
import paho.mqtt.client as paho
import psycopg
import yaml

from tests.support.daemon import SMALL, DaemonProcess, write_cell_file  # the tests' daemon and cell file
from tests.support.servers import MosquittoServer, PostgresServer  # the tests' plant servers

PREFIX = "bench/plant1/line1"
TABLES = ("jobs", "job_states", "samples", "results", "calibrations", "health_checks", "audit")  # a cell's rows
TICK = os.sysconf("SC_CLK_TCK")
METRIC = re.compile(r'^(cellctl_fleet_\w+)\{sink="(\w+)"\} (\S+)$', re.M)


# -- /proc: CPU and memory of process trees, and of the whole machine --------------------------------------


def _stat(pid: int) -> tuple[int, int] | None:
    """(parent pid, utime+stime+cutime+cstime in ticks), or None if the process is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after the command name, which may hold spaces
    return int(fields[1]), sum(int(f) for f in fields[11:15])


def _memory_kib(pid: int, pss: bool) -> int:
    """VmRSS, or PSS (shared pages divided among the processes sharing them: a sum over a server's processes
    then counts PostgreSQL's shared buffers once)."""
    path, key = (f"/proc/{pid}/smaps_rollup", "Pss:") if pss else (f"/proc/{pid}/status", "VmRSS:")
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def machine_busy() -> tuple[int, int]:
    """(busy ticks, all ticks) of every core since boot, from /proc/stat."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = values[3] + values[4]  # idle + iowait
    return sum(values[:8]) - idle, sum(values[:8])


class Sampler:
    """Samples, every `period` s, the CPU ticks and memory of named process trees (a root and its live
    descendants: a reaped child's time is in its parent's cutime, so the sum never jumps) and the machine's busy
    ticks."""

    def __init__(self, period: float = 1.0):
        self.period = period
        self.roots: dict[str, tuple[int, bool]] = {}  # name -> root pid, memory as PSS (else VmRSS)
        self.samples: dict[str, list[tuple[float, int, int, int]]] = {}  # name -> [(t, ticks, rss KiB, root)]
        self.machine: list[tuple[float, int, int]] = []
        self._lock = threading.Lock()  # the thread and the phases' edges both sample: keep the order of time
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sampler", daemon=True)

    def watch(self, name: str, pid: int, pss: bool = False) -> None:
        self.roots[name] = pid, pss

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)

    def sample(self) -> None:
        with self._lock:
            self._sample()

    def _sample(self) -> None:
        t = time.time()
        stats = {}
        for entry in os.scandir("/proc"):
            if entry.name.isdigit():
                s = _stat(int(entry.name))
                if s is not None:
                    stats[int(entry.name)] = s
        children: dict[int, list[int]] = {}
        for pid, (ppid, _) in stats.items():
            children.setdefault(ppid, []).append(pid)
        for name, (root, pss) in list(self.roots.items()):
            if root not in stats:
                continue
            tree, ticks, rss = [root], 0, 0
            while tree:
                pid = tree.pop()
                ticks += stats[pid][1]
                rss += _memory_kib(pid, pss)
                tree.extend(children.get(pid, []))
            self.samples.setdefault(name, []).append((t, ticks, rss, root))
        self.machine.append((t, *machine_busy()))

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self.sample()

    def usage(self, name: str, t0: float, t1: float) -> dict:
        """CPU % of one core (mean over [t0, t1]), peak and last RSS (MiB) of a tree in that window. A tree whose
        root changed (a server restarted) counts the CPU of each root's samples only."""
        inside = [s for s in self.samples.get(name, []) if t0 <= s[0] <= t1]
        if len(inside) < 2:
            return {"cpu_pct": None, "rss_peak_mib": None, "rss_last_mib": None}
        ticks = sum(b[1] - a[1] for a, b in zip(inside, inside[1:]) if a[3] == b[3])
        return {"cpu_pct": 100.0 * ticks / TICK / (inside[-1][0] - inside[0][0]),
                "rss_peak_mib": max(s[2] for s in inside) / 1024, "rss_last_mib": inside[-1][2] / 1024}

    def machine_cores(self, t0: float, t1: float) -> float | None:
        """How many cores were busy on average in [t0, t1] (all processes, ours or not)."""
        inside = [s for s in self.machine if t0 <= s[0] <= t1]
        if len(inside) < 2:
            return None
        (_, ba, aa), (_, bb, ab) = inside[0], inside[-1]
        return os.cpu_count() * (bb - ba) / max(ab - aa, 1)


# -- the plant's event stream, as a subscriber sees it --------------------------------------------------------


def parse_at(text: str) -> float:
    return datetime.strptime(text, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=timezone.utc).timestamp()


class Subscriber:
    """A persistent-session (clean_session false) QoS 1 subscriber to every cell's events/job, noting when each
    message came."""

    def __init__(self, broker: MosquittoServer):
        self.got: list[tuple[float, str, str, float, str]] = []  # receive time, cell, key, "at", state
        self.lock = threading.Lock()
        self.subscribed = threading.Event()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id="bench-fleet-subscriber",
                                  protocol=paho.MQTTv311, clean_session=False)
        self.client.username_pw_set(broker.username, broker.password)
        self.client.on_connect = lambda c, *a: c.subscribe(f"{PREFIX}/+/events/job", qos=1)
        self.client.on_subscribe = lambda *a: self.subscribed.set()
        self.client.on_message = self._message
        self.client.connect("127.0.0.1", broker.port, keepalive=30)
        self.client.loop_start()
        if not self.subscribed.wait(10):
            raise RuntimeError("the MQTT subscriber was not subscribed within 10 s")

    def _message(self, client, userdata, message) -> None:
        now = time.time()  # first: the lag is to the moment the message reached us
        body = json.loads(message.payload)
        with self.lock:
            self.got.append((now, body["cell"], body["key"], parse_at(body["at"]), body["to"]))

    def lags(self, t0: float, t1: float) -> list[tuple[str, float]]:
        """(new state, lag s) of each job event received in [t0, t1], a duplicate (same cell and key) once."""
        seen, out = set(), []
        with self.lock:
            for received, cell, key, at, to in self.got:
                if t0 <= received <= t1 and (cell, key) not in seen:
                    seen.add((cell, key))
                    out.append((to, received - at))
        return out

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


# -- the cells ---------------------------------------------------------------------------------------------


class Cell:
    def __init__(self, name: str, seed: int, folder: Path, dsn_file: Path, password_file: Path,
                 broker: MosquittoServer, realtime: float):
        folder.mkdir(parents=True)
        path = write_cell_file(folder, realtime_factor=realtime)
        data = yaml.safe_load(path.read_text())
        data["sim"]["seed"] = seed
        # the fleet settings' defaults otherwise (heartbeat, keep-alive, progress interval): what a plant runs
        data["fleet"] = {"cell_id": name, "postgres": {"dsn_file": str(dsn_file)},
                         "mqtt": {"host": "127.0.0.1", "port": broker.port, "topic_prefix": PREFIX,
                                  "username": broker.username, "password_file": str(password_file)}}
        path.write_text(yaml.safe_dump(data))
        self.name, self.seed = name, seed
        self.daemon = DaemonProcess(path)
        self.http: httpx.Client | None = None
        self.pending: list[tuple[int, str]] = []  # (job id, phase) submitted, not seen done yet
        self.jobs: list[dict] = []  # per job done: id, phase, wall_s (submitted -> done), running_s, cell_time_s

    def start(self, timeout: float) -> None:
        self.daemon.start(timeout=timeout)
        self.http = self.client()

    def client(self) -> httpx.Client:
        # a longer timeout than the tests': 20 daemons busy on 2 cores answer slowly; a new connection for each
        # request: polled less often than uvicorn's 5 s keep-alive, a kept one can be reset as we send on it
        return httpx.Client(base_url=self.daemon.url, headers={"Authorization": f"Bearer {self.daemon.token}"},
                            timeout=30.0, limits=httpx.Limits(max_keepalive_connections=0))

    def fleet(self) -> dict[tuple[str, str], float]:
        """(metric, sink) -> value of the daemon's cellctl_fleet_* metrics."""
        text = self.http.get("/metrics").text
        return {(m, sink): float(v) for m, sink, v in METRIC.findall(text)}

    def submit(self, n: int, phase: str) -> None:
        """Submit n small virtual grids at once: the worker runs them back to back."""
        for _ in range(n):
            answer = self.http.post("/jobs", json={"routine": "virtual-grid", "params": SMALL})
            if answer.status_code != 201:
                raise RuntimeError(f"{self.name}: POST /jobs answered {answer.status_code}: {answer.text[:300]}")
            self.pending.append((answer.json()["id"], phase))

    def poll(self) -> bool:
        """Look at the oldest job not yet done (they run in order); True once none is left."""
        while self.pending:
            job_id, phase = self.pending[0]
            job = self.http.get(f"/jobs/{job_id}").json()
            if job["state"] in ("queued", "running"):
                return False
            if job["state"] != "done":
                raise RuntimeError(f"{self.name}: job {job_id} {job['state']}: {job.get('reason')}")
            times = {h["to"]: parse_at(h["at"]) for h in job["history"]}  # the job's own times (ms)
            self.jobs.append({"id": job_id, "phase": phase, "wall_s": times["done"] - times["queued"],
                              "running_s": times["done"] - times["running"],
                              "cell_time_s": job["result"]["cell_time_s"]})
            self.pending.pop(0)
        return True


def run_jobs(cells: list[Cell], n: int, phase: str, deadline: float) -> None:
    """n jobs on every cell at once, until all are done. Polled once a second from this thread (nothing to stop
    on Ctrl-C): the daemons' time goes to the jobs, not to us."""
    for c in cells:
        c.submit(n, phase)
    while not all([c.poll() for c in cells]):
        if time.time() > deadline:
            raise TimeoutError(f"{phase}: jobs not done by the deadline: "
                               f"{ {c.name: len(c.pending) for c in cells if c.pending} }")
        time.sleep(1.0)


def fleet_of(cells: list[Cell]) -> dict[str, dict[tuple[str, str], float]]:
    return {c.name: c.fleet() for c in cells}


def wait_for(what: str, check, timeout: float, interval: float = 0.5):
    """Call `check` until it returns something true; TimeoutError naming `what` after `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        got = check()
        if got:
            return got
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:g} s")
        time.sleep(interval)


def all_replicated(cells: list[Cell], sinks=("postgres", "mqtt")):
    """Every sink up and every backlog 0 on every cell: the metrics then, else None."""
    state = fleet_of(cells)
    for metrics in state.values():
        for sink in sinks:
            if metrics.get(("cellctl_fleet_sink_up", sink)) != 1 or metrics.get(
                    ("cellctl_fleet_backlog_records", sink)) != 0:
                return None
    return state


def delivered(state: dict, sink: str) -> float:
    return sum(m.get(("cellctl_fleet_delivered_records_total", sink), 0) for m in state.values())


def plant_rows(dsn: str) -> int:
    with psycopg.connect(dsn) as conn:
        return sum(conn.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in TABLES)


def stats(values: list[float]) -> dict:
    if not values:
        return {"n": 0, "min": None, "median": None, "p99": None, "max": None}
    a = np.asarray(values, dtype=float)
    return {"n": len(a), "min": float(a.min()), "median": float(np.median(a)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max())}


# -- the benchmark -----------------------------------------------------------------------------------------


class Bench:
    def __init__(self, args):
        self.args = args
        self.folder = Path(tempfile.mkdtemp(prefix="cellctl-bench-fleet-"))
        self.pg: PostgresServer | None = None
        self.mq: MosquittoServer | None = None
        self.subscriber: Subscriber | None = None
        self.cells: list[Cell] = []
        self.sampler = Sampler(args.sample_s)
        self.phases: dict[str, tuple[float, float]] = {}
        self.out: dict = {"settings": {k: v for k, v in vars(args).items() if k != "json"}}
        self._closed = False

    def secret(self, name: str, value: str) -> Path:
        path = self.folder / name
        path.write_text(value + "\n")
        os.chmod(path, 0o600)  # the daemon refuses a credential file others can read
        return path

    def setup(self) -> None:
        a = self.args
        self.pg, self.mq = PostgresServer(), MosquittoServer()  # known before they start: close() stops them
        self.pg.start()
        self.mq.start()
        with psycopg.connect(self.pg.dsn) as conn:
            self.out["postgres_version"] = conn.execute("SHOW server_version").fetchone()[0]
        self.subscriber = Subscriber(self.mq)
        dsn_file = self.secret("plant.dsn", self.pg.dsn)
        password_file = self.secret("mqtt.password", self.mq.password)
        self.cells = [Cell(f"cell-{i:02d}", 100 + i, self.folder / f"cell-{i:02d}", dsn_file, password_file, self.mq,
                           a.realtime) for i in range(1, a.cells + 1)]
        t0 = time.time()
        # one after the other: on 2 cores starting them at once is no faster (imports are CPU-bound)
        for c in self.cells:
            c.start(timeout=120)
        self.out["start_s"] = time.time() - t0
        for c in self.cells:
            self.sampler.watch(c.name, c.daemon.proc.pid)
        self.sampler.watch("postgres", self.pg.proc.pid, pss=True)
        self.sampler.watch("mosquitto", self.mq.proc.pid, pss=True)
        self.sampler.watch("everything", os.getpid())  # this process, its daemons and servers
        self.sampler.start()
        wait_for("every cell connected to both sinks, nothing pending", lambda: all_replicated(self.cells),
                 a.timeout_s)

    def idle(self) -> None:
        time.sleep(3)  # start-up work (imports, first connections) settles
        t0 = time.time()
        self.sampler.sample()
        time.sleep(self.args.idle_s)  # nobody asks the daemons anything: their own idle work only
        self.sampler.sample()
        self.phases["idle"] = (t0, time.time())

    def load(self) -> None:
        a = self.args
        rows0, before = plant_rows(self.pg.dsn), fleet_of(self.cells)
        t0 = time.time()
        self.sampler.sample()
        deadline = t0 + a.timeout_s
        run_jobs(self.cells, a.jobs, "load", deadline)
        t_jobs = time.time()
        after = wait_for("every backlog drained after the load", lambda: all_replicated(self.cells),
                         max(deadline - time.time(), 1), interval=0.2)
        t1 = time.time()
        self.sampler.sample()
        self.phases["load"] = (t0, t1)
        rows = plant_rows(self.pg.dsn) - rows0
        with psycopg.connect(self.pg.dsn) as conn:
            pg_lags = conn.execute("SELECT to_state, EXTRACT(EPOCH FROM received - at)::float8 FROM job_states "
                                   "WHERE at >= to_timestamp(%s) AND at <= to_timestamp(%s)", (t0, t1)).fetchall()
        mqtt_lags = self.subscriber.lags(t0, t1)
        self.out["load"] = {
            "duration_s": t1 - t0, "jobs_done_s": t_jobs - t0, "rows": rows, "rows_per_s": rows / (t1 - t0),
            "records": {s: delivered(after, s) - delivered(before, s) for s in ("postgres", "mqtt")},
            "lag_postgres_s": stats([lag for _, lag in pg_lags]), "lag_mqtt_s": stats([lag for _, lag in mqtt_lags]),
            # by the job's new state (queued, running, done): where the outliers are
            "lag_by_state_s": {sink: {state: stats([lag for to, lag in lags if to == state])
                                      for state in sorted({to for to, _ in lags})}
                               for sink, lags in (("postgres", pg_lags), ("mqtt", mqtt_lags))}}
        self.out["load"]["records_per_s"] = {s: n / (t1 - t0) for s, n in self.out["load"]["records"].items()}

    def burst(self) -> None:
        a = self.args
        rows0 = plant_rows(self.pg.dsn)
        t0 = time.time()
        self.sampler.sample()
        deadline = t0 + a.timeout_s
        self.pg.stop()  # a fast shutdown: the plant database's outage as the cells see it
        run_jobs(self.cells, 1, "burst", deadline)
        # the MQTT sink keeps up; the records wait for PostgreSQL
        wait_for("the MQTT backlogs drained during the outage", lambda: all(
            m.get(("cellctl_fleet_backlog_records", "mqtt")) == 0 for m in fleet_of(self.cells).values()),
            max(deadline - time.time(), 1))
        state = fleet_of(self.cells)
        backlog = {name: m[("cellctl_fleet_backlog_records", "postgres")] for name, m in state.items()}
        t_down = time.time() - t0
        self.pg.resume()
        t_up = time.time()
        self.sampler.watch("postgres", self.pg.proc.pid, pss=True)  # a new server process
        # how long until every backlog is drained (the plant database is accepting connections from t_up)
        wait_for("every backlog drained after the outage", lambda: all_replicated(self.cells),
                 max(deadline - time.time(), 60), interval=0.2)
        t1 = time.time()
        self.sampler.sample()
        self.phases["burst"] = (t0, t1)
        with psycopg.connect(self.pg.dsn) as conn:
            # per cell: when the plant received its first and last job state of the outage (one transaction of up
            # to 500 records after the cell reconnected): the reconnection delay, and the drain itself
            spans = conn.execute("SELECT cell, EXTRACT(EPOCH FROM min(received))::float8, "
                                 "EXTRACT(EPOCH FROM max(received))::float8 FROM job_states "
                                 "WHERE at >= to_timestamp(%s) GROUP BY cell", (t0,)).fetchall()
        records = sum(backlog.values())
        first, last = min(f for _, f, _ in spans), max(la for _, _, la in spans)
        self.out["burst"] = {
            "outage_s": t_down, "backlog_records": records, "rows": plant_rows(self.pg.dsn) - rows0,
            "drained_s": t1 - t_up, "records_per_s": records / (t1 - t_up),
            "reconnect_s": stats([f - t_up for _, f, _ in spans]),
            "drain_span_s": stats([la - f for _, f, la in spans]),
            # the plant's intake once the cells were back: from its first job state row to its last
            "intake_s": last - first, "intake_records_per_s": records / max(last - first, 1e-3),
            "backlog_per_cell": stats(list(backlog.values()))}

    def usage(self) -> None:
        """Per phase: each daemon's CPU and RSS, the servers', and how busy the machine was."""
        out = self.out["usage"] = {}
        self.out["phases_s"] = {phase: t1 - t0 for phase, (t0, t1) in self.phases.items()}
        for phase, (t0, t1) in self.phases.items():
            daemons = {c.name: self.sampler.usage(c.name, t0, t1) for c in self.cells}
            ours = self.sampler.usage("everything", t0, t1)["cpu_pct"]
            busy = self.sampler.machine_cores(t0, t1)
            out[phase] = {"daemons": daemons, "postgres": self.sampler.usage("postgres", t0, t1),
                          "mosquitto": self.sampler.usage("mosquitto", t0, t1), "machine_cores": busy,
                          "ours_cores": ours / 100 if ours is not None else None,
                          "others_cores": busy - ours / 100 if busy is not None and ours is not None else None}
        self.out["jobs"] = {c.name: c.jobs for c in self.cells}

    def close(self) -> None:
        """Stop everything started, whatever state it is in (also from atexit); once."""
        if self._closed:
            return
        self._closed = True
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):  # a second Ctrl-C must not leave the servers running
                signal.signal(sig, signal.SIG_IGN)
        self.sampler.stop()
        running = [c for c in self.cells if c.daemon.proc is not None and c.daemon.proc.poll() is None]
        for c in running:  # all at once: each says offline and drains for up to 3 s
            c.daemon.proc.terminate()
        for c in running:
            try:
                c.daemon.proc.wait(20)
            except Exception:  # noqa: BLE001 - stuck: kill it
                c.daemon.proc.kill()
                c.daemon.proc.wait(5)
        for c in self.cells:
            if c.http is not None:
                c.http.close()
            if getattr(c.daemon, "log", None):
                c.daemon.log.close()
        if self.subscriber is not None:
            self.subscriber.close()
        for server in (self.mq, self.pg):
            if server is not None:
                try:
                    server.close()
                except Exception as exc:  # noqa: BLE001 - stop the others anyway
                    print(f"stopping {type(server).__name__}: {exc}", file=sys.stderr)
        if self.args.keep:
            print(f"kept {self.folder} (daemon logs: */daemon.log)")
        else:
            shutil.rmtree(self.folder, ignore_errors=True)


# -- the report --------------------------------------------------------------------------------------------


def fmt(v, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def spread(values: list, spec: str = ".1f") -> str:
    """median / max of the values that are known."""
    known = [v for v in values if v is not None]
    return f"{fmt(float(np.median(known)) if known else None, spec)} / {fmt(max(known, default=None), spec)}"


def lag_row(label: str, x: dict) -> str:
    return f"  {label:44s} {x['n']:5d}  {fmt(x['median'], '8.3f')}  {fmt(x['p99'], '6.3f')}  {fmt(x['max'], '6.3f')}"


def rate_row(label: str, records, rows, seconds: float) -> str:
    per_s = [fmt(None if n is None else n / max(seconds, 1e-3)) for n in (records, rows)]
    return (f"  {label:44s} {fmt(records, '.0f'):>7s}  {fmt(rows, 'd'):>6s}  {seconds:7.1f}  {per_s[0]:>9s}  "
            f"{per_s[1]:>7s}")


def report(out: dict, verbose: bool) -> None:
    s, usage = out["settings"], out["usage"]
    print(f"\nfleet: {s['cells']} cells, {s['jobs']} small virtual-grid job(s) each, realtime_factor "
          f"{s['realtime']:g}; PostgreSQL {out['postgres_version'].split()[0]} and Mosquitto on loopback; "
          f"{os.cpu_count()} cores; daemons started in {out['start_s']:.0f} s")

    print("\nphase        wall s   cores busy: all   ours   others")
    for phase, u in usage.items():
        print(f"  {phase:8s} {out['phases_s'][phase]:8.1f}   {fmt(u['machine_cores'], '15.2f')}  "
              f"{fmt(u['ours_cores'], '5.2f')}  {fmt(u['others_cores'], '7.2f')}")

    load = out["load"]
    print(f"\n{'replication lag of the load phase job states':46s} {'n':>5s}  {'median s':>8s}  {'p99 s':>6s}  "
          f"{'max s':>6s}")
    print(lag_row("to PostgreSQL (plant's received - at)", load["lag_postgres_s"]))
    print(lag_row('to MQTT (subscriber receive time - "at")', load["lag_mqtt_s"]))
    if verbose:
        for sink, states in load["lag_by_state_s"].items():
            for state, x in states.items():
                print(lag_row(f"  {sink}, to {state}", x))

    print(f"\n{'throughput':46s} {'records':>7s}  {'rows':>6s}  {'s':>7s}  {'records/s':>9s}  {'rows/s':>7s}")
    print(rate_row("load phase, to PostgreSQL", load["records"]["postgres"], load["rows"], load["duration_s"]))
    print(rate_row("load phase, to MQTT", load["records"]["mqtt"], None, load["duration_s"]))
    if "burst" in out:
        b = out["burst"]
        r, d = b["reconnect_s"], b["drain_span_s"]
        print(rate_row("burst: PostgreSQL back -> every backlog 0", b["backlog_records"], b["rows"], b["drained_s"]))
        print(rate_row("burst: plant's first -> last row received", b["backlog_records"], None, b["intake_s"]))
        print(f"    PostgreSQL was down {b['outage_s']:.0f} s; backlog per cell: median "
              f"{b['backlog_per_cell']['median']:.0f} records; cells reconnected {r['min']:.1f} / {r['median']:.1f} / "
              f"{r['max']:.1f} s (min / median / max) after it was back;\n    one cell's drain (its first to last "
              f"job state received): median {d['median'] * 1e3:.0f} ms, max {d['max'] * 1e3:.0f} ms")

    title = f"per daemon (median / max over {s['cells']})"
    print(f"\n{title:46s} {'CPU % of a core':>16s}  {'RSS MiB peak':>12s}  {'RSS MiB end':>11s}")
    for phase, u in usage.items():
        d = list(u["daemons"].values())
        cpu, peak, end = ([x[k] for x in d] for k in ("cpu_pct", "rss_peak_mib", "rss_last_mib"))
        print(f"  {phase:44s} {spread(cpu):>16s}  {spread(peak, '.0f'):>12s}  {spread(end, '.0f'):>11s}")
    print("servers (all their processes; memory: PSS, MiB)")
    for server in ("postgres", "mosquitto"):
        print(f"  {server:10s} " + "   ".join(f"{phase}: CPU {fmt(u[server]['cpu_pct'])} %, "
                                          f"{fmt(u[server]['rss_last_mib'], '.0f')} MiB" for phase, u in usage.items()))

    jobs = [j for js in out["jobs"].values() for j in js]
    if jobs:
        title = f"job wall times (cell time {jobs[0]['cell_time_s']:.1f} s each)"
        print(f"\n{title:46s} {'n':>4s}  {'median s':>8s}  {'max s':>6s}")
    for phase in ("load", "burst"):
        mine = [j for j in jobs if j["phase"] == phase]
        for label, key in (("submitted -> done (queue included)", "wall_s"), ("running -> done", "running_s")):
            if mine:
                x = stats([j[key] for j in mine])
                print(f"  {phase + ', ' + label:44s} {x['n']:4d}  {x['median']:8.1f}  {x['max']:6.1f}")

    if verbose:
        phases = list(usage)
        print("\nper daemon " + "".join(f"{p + ' CPU %':>13s}{p + ' RSS':>11s}" for p in phases) +
              "   load jobs, running -> done s")
        for name in out["jobs"]:
            row = "".join(f"{fmt(usage[p]['daemons'][name]['cpu_pct'], '13.1f')}"
                          f"{fmt(usage[p]['daemons'][name]['rss_last_mib'], '11.0f')}" for p in phases)
            walls = ", ".join(f"{j['running_s']:.1f}" for j in out["jobs"][name] if j["phase"] == "load")
            print(f"  {name:9s}{row}   {walls}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="daemons to run (1-100)")
    parser.add_argument("--jobs", type=int, default=2, help="small virtual-grid jobs per cell in the load phase")
    parser.add_argument("--realtime", type=float, default=5.0,
                        help="the sim's realtime_factor (wall s per cell s; 5: 20 cells do not saturate 2 cores)")
    parser.add_argument("--idle-s", type=float, default=20.0, help="length of the idle phase")
    parser.add_argument("--burst", action=argparse.BooleanOptionalAction, default=True,
                        help="stop PostgreSQL, run one job per cell, and time the drain (default: on)")
    parser.add_argument("--sample-s", type=float, default=1.0, help="CPU and RSS sampling period")
    parser.add_argument("--timeout-s", type=float, default=900.0, help="the longest any phase may take")
    parser.add_argument("--json", type=Path, help="also save the numbers here")
    parser.add_argument("--verbose", action="store_true", help="a table per daemon")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder (cell files, daemon logs)")
    args = parser.parse_args()
    if not 1 <= args.cells <= 100 or not 1 <= args.jobs <= 50 or not 1 <= args.idle_s <= 3600:
        parser.error("--cells 1-100, --jobs 1-50, --idle-s 1-3600")

    bench = Bench(args)
    atexit.register(bench.close)  # also when something below fails in a way `finally` does not see
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # SystemExit: the finally below runs
    t_start = time.time()
    try:
        print(f"starting PostgreSQL, Mosquitto and {args.cells} daemons ...", flush=True)
        bench.setup()
        print(f"idle for {args.idle_s:g} s ...", flush=True)
        bench.idle()
        print(f"load: {args.jobs} job(s) per cell ...", flush=True)
        bench.load()
        if args.burst:
            print("burst: PostgreSQL stopped, one job per cell, PostgreSQL back ...", flush=True)
            bench.burst()
        bench.usage()
    finally:
        bench.close()
    bench.out["wall_s"] = time.time() - t_start
    report(bench.out, args.verbose)
    print(f"\nwall time of the benchmark: {bench.out['wall_s']:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(bench.out, indent=2))
        print(f"saved {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
