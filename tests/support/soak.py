"""A soak with faults (issue 30): daemons of three cell kinds run many small jobs while faults fall on a seeded
schedule, and an operator (this code) acknowledges, reconnects and resumes each job until it is done.

The cells: the micro cell on the in-process fakes, and through the UR (ur-rtde) and ABB (socket) protocol
simulators, each one daemon process (`python -m cellctl.startup`) with its store on one small tmpfs, in a fleet
with a real PostgreSQL and a real Mosquitto, its wall clock steppable (tests/support/wall_clock.py).

The faults:
- on the devices, drawn by the simulated world at each move, capture and grip (`sim.faults.random`): link
  drops, protective stops, capture time-outs, corrupt frames, a part lost from the vacuum;
- from outside, one per job at most, drawn from the soak's seed: `kill -9` of the daemon (then started again), a
  plant outage (PostgreSQL stopped until the job ends, the broker restarted), a disk-full episode (the tmpfs
  filled to the last byte, freed once the job has faulted or a new job has been refused), a wall-clock step of
  +-1 h.

What it counts, against an uninterrupted in-process run of each (cell, seed) made before the daemons start:
samples lost or duplicated per job (every measured column and the result compared), records the plant database
misses or holds twice, any change of the arm's reported pose between a fault and the operator's resume (motion
nobody asked for), the daemons' RSS, open files, threads and child processes after every job, and the latency of
GET /cell and GET /jobs/{id} from background readers. Shared by tools/soak.py (the long run, its figures in the
README) and tests/fleet/test_soak.py (the short one in the suite).
"""

from __future__ import annotations

import errno
import os
import random
import subprocess
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import yaml

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.run_folder import RunFolder, csv_cell, read_samples_text

from tests.support.cells import write_abb_cell_file, write_ur_cell_file
from tests.support.daemon import SMALL, DaemonProcess, write_cell_file
from tests.support.plant_records import differences
from tests.support.wait import eventually
from tests.support.wall_clock import SteppedWallClock

KINDS = ("fake", "ur", "abb")
EXTERNAL = ("kill9", "outage", "disk_full", "clock_step")
# the jobs the cells take in turn: a virtual grid (moves and captures), and an on-board camera calibration, which
# also picks and places spheres (the gripper, its vacuum loss)
JOBS = (("virtual-grid", SMALL), ("onboard-camera", {"rows": 3, "cols": 3, "alphas_deg": [0.0, 30.0]}))
NOT_COMPARED = {"image"}  # a sample's columns that differ between runs of one seed: none but the image's name
MIN_FREE_MB = 24.0  # above the daemon's 8 MB reserve file, as in tests/daemon/test_disk_full.py
TERMINAL = {"done", "faulted", "paused", "aborted"}


@dataclass
class SoakSettings:
    jobs: int = 12  # in all, taken in turn by the cells
    seed: int = 0
    kinds: tuple[str, ...] = KINDS
    job_seeds: tuple[int, ...] = (0, 1, 2)  # simulation seeds the jobs (JOBS) cycle through, one reference each
    external_chance: float = 0.25  # per job: one fault from outside (EXTERNAL), the first few forced in turn
    device_faults: dict = field(default_factory=lambda: {"link_drop": 0.004, "protective_stop": 0.004,
                                                         "capture_timeout": 0.003, "corrupt_frame": 0.003,
                                                         "vacuum_loss": 0.01})
    readers: int = 4  # background clients reading GET /cell and the live job
    read_every_s: float = 0.05
    fs_mb: int = 512  # the stores' tmpfs
    ur_host: str = "127.0.0.47"  # the UR cell's robot address, the soak's own (tools/soak.py: another one)
    long_lived: tuple[str, ...] = ()  # kinds whose daemon is never killed: one process through the whole soak
    max_tries: int = 40  # resumptions of one job before it is counted stuck
    keep_stores: bool = False  # copy the stores out of the tmpfs (into the soak's folder) before it goes


@dataclass
class Sample:
    """The daemon process after a job."""

    job: int
    rss_mb: float
    fds: int
    threads: int
    children: int


@dataclass
class SoakReport:
    settings: SoakSettings
    jobs: dict = field(default_factory=lambda: {"done": 0, "faulted": 0, "resumed": 0, "stuck": 0})
    faults: dict = field(default_factory=dict)  # what fell: EXTERNAL by name, and "job faulted: <error>"
    lost: int = 0  # samples of a job missing against its reference
    duplicated: int = 0  # samples present more than once
    different: list = field(default_factory=list)  # (cell, job, what) where a sample or the result differs
    bad_jobs: list = field(default_factory=list)  # per job that lost or changed anything: what, and the faults met
    plant: dict = field(default_factory=dict)  # cell -> differences() at the end
    unasked_motion: list = field(default_factory=list)  # (cell, job, before, after)
    orphans: list = field(default_factory=list)  # (cell, pid, command) a killed daemon's children left running
    refusals: list = field(default_factory=list)  # (cell, status, detail) of jobs refused on a full disk
    lives: dict = field(default_factory=dict)  # cell -> [[Sample, ...] per daemon process]
    latencies: list = field(default_factory=list)  # s
    unavailable: int = 0  # reads that found a daemon down (kill -9 to its restart)
    read_errors: list = field(default_factory=list)
    wall_s: float = 0.0
    skipped: list = field(default_factory=list)  # what could not be done here, and why

    def count(self, what: str) -> None:
        self.faults[what] = self.faults.get(what, 0) + 1

    def growth(self, metric: str, warm_up: int) -> dict[str, float]:
        """Per cell, over its longest daemon life: the metric's relative growth from just after `warm_up` jobs
        (the median of the next 3) to the end (the median of the last 3); 0.0 when the life is too short."""
        out = {}
        for cell, lives in self.lives.items():
            life = max(lives, key=len, default=[])
            if len(life) < warm_up + 6:
                out[cell] = 0.0
                continue
            values = [getattr(s, metric) for s in life]
            start, end = sorted(values[warm_up:warm_up + 3])[1], sorted(values[-3:])[1]
            out[cell] = (end - start) / start if start else 0.0
        return out

    def percentile(self, q: float) -> float:
        v = sorted(self.latencies)
        return v[min(int(q * len(v)), len(v) - 1)] if v else float("nan")

    def problems(self) -> list[str]:
        """What a soak must never show."""
        out = []
        if self.lost or self.duplicated or self.different:
            out.append(f"samples lost {self.lost}, duplicated {self.duplicated}, different {self.different[:5]}")
        for cell, diff in self.plant.items():
            if diff:
                out.append(f"plant database of {cell}: {diff}")
        if self.unasked_motion:
            out.append(f"motion without an acknowledgement: {self.unasked_motion[:5]}")
        if self.orphans:
            out.append(f"processes a killed daemon left running: {self.orphans[:5]}")
        if self.jobs["stuck"]:
            out.append(f"{self.jobs['stuck']} jobs never finished")
        if self.read_errors:
            out.append(f"{len(self.read_errors)} reads failed: {self.read_errors[:5]}")
        return out

    def lines(self, warm_up: int = 5) -> list[str]:
        s = self.settings
        j = self.jobs
        lives = {c: [len(life) for life in ls] for c, ls in self.lives.items()}
        out = [f"soak: {s.jobs} jobs on {', '.join(s.kinds)} (seed {s.seed}) in {self.wall_s:.0f} s",
               f"jobs: {j['done']} done, {j['faulted']} faults met, {j['resumed']} resumptions, {j['stuck']} stuck",
               "faults: " + ", ".join(f"{k} {v}" for k, v in sorted(self.faults.items())),
               f"samples lost {self.lost}, duplicated {self.duplicated}, differing from the reference "
               f"{len(self.different)}",
               "plant database: " + ", ".join(f"{c} {'every record once' if not d else d}"
                                              for c, d in self.plant.items()),
               f"motion without an acknowledgement: {len(self.unasked_motion)}",
               f"children a killed daemon left running: {len(self.orphans)}",
               f"full-disk refusals: {len(self.refusals)}" + (f" ({self.refusals[0][2]})" if self.refusals else ""),
               f"daemon lives (jobs each): {lives}"]
        for metric, unit in (("rss_mb", "MB"), ("fds", ""), ("threads", ""), ("children", "")):
            ends = {c: [getattr(life[-1], metric) for life in ls if life] for c, ls in self.lives.items()}
            growth = self.growth(metric, warm_up)
            spans = {c: [getattr(x, metric) for x in max(ls, key=len, default=[])[warm_up:]] for c, ls in self.lives.items()}
            out.append(f"{metric}: at the end of each life {ends}{unit and ' ' + unit}; growth after "
                       f"{warm_up} jobs " + ", ".join(f"{c} {g:+.1%}" for c, g in growth.items())
                       + "; range over the longest life after them " + ", ".join(
                           f"{c} {min(v):g}-{max(v):g}" for c, v in spans.items() if v))
        out.append(f"API reads: n {len(self.latencies)}, p50 {self.percentile(0.5) * 1e3:.1f} ms, p99 "
                   f"{self.percentile(0.99) * 1e3:.1f} ms, max {max(self.latencies, default=0) * 1e3:.1f} ms; "
                   f"{self.unavailable} found a daemon restarting")
        out += [f"not done: {why}" for why in self.skipped]
        out += [f"job {b['cell']} #{b['job']}: lost {b['lost']}, duplicated {b['duplicated']}, different "
                f"{b['different'][:4]}; met {b['met']}" for b in self.bad_jobs[:10]]
        return out


class SoakCell:
    """One cell kind: its cell file, its daemon, its reference runs."""

    def __init__(self, kind: str, folder: Path, store: Path, fleet: dict, faults: dict, wall: SteppedWallClock,
                 ur_host: str):
        self.kind, self.name = kind, f"soak-{kind}"
        folder.mkdir(parents=True, exist_ok=True)
        self.plain = {"fake": lambda f: write_cell_file(f, realtime_factor=0.0), "ur": write_ur_cell_file,
                      "abb": write_abb_cell_file}[kind](folder)
        data = yaml.safe_load(self.plain.read_text())
        if kind == "ur":  # a robot address of the soak's own: the suite's UR cells take turns on 127.0.0.7
            data.update(arm={"host": ur_host}, gripper={"host": ur_host},
                        sim={"servers": [{"protocol": "ur", "host": ur_host},
                                         {"protocol": "epick", "host": ur_host, "port": 54321}]})
            self.plain.write_text(yaml.safe_dump(data))
        data["store_dir"] = str(store)
        data.setdefault("store", {})["min_free_mb"] = MIN_FREE_MB
        data["fleet"] = {"cell_id": self.name, "heartbeat_s": 1, **fleet}
        data.setdefault("sim", {}).setdefault("faults", {})["random"] = faults
        self.cell_file = folder / "soak.yaml"
        self.cell_file.write_text(yaml.safe_dump(data))
        self.references: dict[tuple[str, int], tuple[dict, list[dict]]] = {}
        self.daemon = DaemonProcess(self.cell_file)
        self.daemon.extra_env = wall.env()

    def reference(self, routine: str, params: dict, seed: int, folder: Path) -> None:
        """The uninterrupted in-process run of a job, on the cell file without faults or fleet."""
        config, text = load_cell_file(self.plain)
        run = folder / f"reference-{self.kind}-{routine}-{seed}"
        result = run_routine(routine, config, text, run, seed=seed, overrides=params)
        self.references[(routine, seed)] = (result, RunFolder(run).samples())

    def client(self) -> httpx.Client:
        return self.daemon.client()


class Soak:
    def __init__(self, folder: Path, settings: SoakSettings, postgres, mosquitto, log=print):
        self.folder, self.settings, self.postgres, self.mosquitto = folder, settings, postgres, mosquitto
        self.log = log
        self.report = SoakReport(settings)
        self.rng = random.Random(settings.seed)
        self.stop_readers = threading.Event()
        self.live: tuple[SoakCell, int] | None = None  # the cell and job the readers follow
        self.restarting: set[str] = set()
        self.kills: dict[str, int] = {}  # cell -> how often its daemon was killed: a read that spans one is not an error

    # -- set-up ---------------------------------------------------------------------------------------------
    def _mount(self, stack: ExitStack) -> Path:
        mount = self.folder / "fs"
        mount.mkdir(parents=True, exist_ok=True)
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={self.settings.fs_mb}m", "tmpfs", str(mount)],
                              capture_output=True, text=True)
        if done.returncode != 0:
            self.report.skipped.append(f"disk-full episodes: cannot mount a tmpfs ({done.stderr.strip()}); the "
                                       "stores are on the ordinary disk")
            self.mounted = False
            return self.folder / "stores"
        self.mounted = True
        stack.callback(lambda: subprocess.run(["umount", "-l", str(mount)], check=False))
        return mount

    def _secret(self, name: str, value: str) -> Path:
        path = self.folder / name
        path.write_text(value + "\n")
        os.chmod(path, 0o600)
        return path

    def _fleet(self) -> dict:
        return {"postgres": {"dsn_file": str(self._secret("plant.dsn", self.postgres.dsn))},
                "mqtt": {"host": "127.0.0.1", "port": self.mosquitto.port, "topic_prefix": "acme/soak",
                         "username": self.mosquitto.username,
                         "password_file": str(self._secret("mqtt.password", self.mosquitto.password)),
                         "keepalive_s": 5}}

    def _schedule(self) -> list[str | None]:
        """The fault from outside each job meets (None: none): every kind once first, in a seeded order (each
        fault is tried even in a short soak), then drawn at `external_chance`."""
        s = self.settings
        kinds = [k for k in EXTERNAL if k != "disk_full" or self.mounted]
        first = self.rng.sample(kinds, len(kinds))
        plan: list[str | None] = []
        for i in range(s.jobs):
            if i % 2 == 1 and first:  # every other job, so that each cell meets them
                plan.append(first.pop())
            else:
                plan.append(self.rng.choice(kinds) if self.rng.random() < s.external_chance else None)
        return plan

    # -- the run --------------------------------------------------------------------------------------------
    def run(self) -> SoakReport:
        s = self.settings
        t0 = self.t0 = time.monotonic()
        with ExitStack() as stack:
            store_root = self._mount(stack)
            if s.keep_stores and self.mounted:  # runs before the unmount (callbacks run last first)
                stack.callback(lambda: subprocess.run(["cp", "-a", str(store_root), str(self.folder / "stores")]))
            self.ballast = store_root / "ballast"
            stack.callback(lambda: self.ballast.unlink(missing_ok=True))
            self.wall = SteppedWallClock(self.folder)
            fleet = self._fleet()
            faults = {"seed": s.seed, **s.device_faults}
            self.cells = [SoakCell(k, self.folder / k, store_root / k, fleet, faults, self.wall, s.ur_host) for k in s.kinds]
            for cell in self.cells:  # before any daemon: a UR cell's simulator holds its fixed ports
                for routine, params in JOBS:
                    for seed in s.job_seeds:
                        cell.reference(routine, params, seed, self.folder)
            self.log(f"references: {len(self.cells) * len(JOBS) * len(s.job_seeds)} runs in "
                     f"{time.monotonic() - t0:.0f} s")
            for cell in self.cells:
                cell.daemon.start(timeout=180)
                stack.callback(self._stop, cell)
                self.report.lives[cell.name] = [[]]
            readers = [threading.Thread(target=self._reader, daemon=True) for _ in range(s.readers)]
            for r in readers:
                r.start()
            stack.callback(lambda: [r.join(30) for r in readers])
            stack.callback(self.stop_readers.set)
            for i, outside in enumerate(self._schedule()):
                cell = self.cells[i % len(self.cells)]
                if outside == "kill9" and cell.kind in s.long_lived:
                    outside = "clock_step"  # this daemon lives through the soak: another fault from outside
                turn = i // len(self.cells)  # each cell's jobs: the routines in turn, then the next seed
                routine, params = JOBS[turn % len(JOBS)]
                self._job(cell, i, routine, params, s.job_seeds[turn // len(JOBS) % len(s.job_seeds)], outside)
            self.stop_readers.set()
            if self.postgres.proc is None:
                self.postgres.resume()
            for cell in self.cells:
                self.report.plant[cell.name] = self._replicated(cell)
        self.report.wall_s = time.monotonic() - t0
        return self.report

    def _stop(self, cell: SoakCell) -> None:
        if cell.daemon.proc is not None and cell.daemon.proc.poll() is None:
            cell.daemon.terminate(timeout=60)
        cell.daemon.log.close()

    def _job(self, cell: SoakCell, index: int, routine: str, params: dict, seed: int, outside: str | None) -> None:
        rep = self.report
        with cell.client() as c:
            answer = c.post("/jobs", json={"routine": routine, "params": params, "seed": seed})
        if answer.status_code != 201:
            raise AssertionError(f"{cell.name}: job {index} refused: {answer.status_code} {answer.text}")
        job = answer.json()["id"]
        self.live = (cell, job)
        self.log(f"job {index}: {cell.name} #{job} {routine} seed {seed}" + (f", {outside}" if outside else ""))
        self.met: list[str] = []  # the faults this job met, in order
        if outside is not None:
            rep.count(outside)
            self.met.append(outside)
            self._outside(cell, job, outside)
        tries = 0
        while True:
            state = self._settled(cell, job)
            if state["state"] == "done":
                break
            tries += 1
            if tries > self.settings.max_tries:
                rep.jobs["stuck"] += 1
                rep.bad_jobs.append({"cell": cell.name, "job": job, "lost": 0, "duplicated": 0,
                                     "different": [f"stuck: {state['state']}: {state.get('reason')}"],
                                     "met": list(self.met)})
                self.log(f"  stuck: {state}")
                return
            self._operator(cell, job, state)
        rep.jobs["done"] += 1
        if self.postgres.proc is None:  # the outage lasted the job
            self.postgres.resume()
        self._compare(cell, job, cell.references[(routine, seed)])
        self._measure(cell, job)

    def _settled(self, cell: SoakCell, job: int, timeout: float = 300.0) -> dict:
        def settled():
            with cell.client() as c:
                got = c.get(f"/jobs/{job}").json()
            return got if got["state"] in TERMINAL else None

        return eventually(settled, timeout=timeout, every=0.05, what=f"{cell.name} job {job} to settle")

    def _pose(self, cell: SoakCell):
        with cell.client() as c:
            pose = c.get("/cell").json().get("arm_pose")
        if pose:
            pose.pop("read_at", None)
        return pose

    def _operator(self, cell: SoakCell, job: int, state: dict) -> None:
        """What an operator does with a job that stopped: a faulted one is acknowledged (its devices
        reconnected when one is down), then resumed; the arm's pose must not change on the way."""
        rep = self.report
        with cell.client() as c:
            if state["state"] == "faulted":
                rep.jobs["faulted"] += 1
                reason = state.get("reason") or ""
                what = reason.split(":")[0] if "daemon stopped" not in reason else "daemon stopped"
                rep.count("job faulted: " + what)
                self.met.append(what)
                before = self._pose(cell)
                r = c.post(f"/jobs/{job}/ack")
                assert r.status_code == 200, r.text
                after = self._pose(cell)
                if before is not None and after != before:
                    rep.unasked_motion.append((cell.name, job, before, after))
                if any(d["state"] != "ready" for d in c.get("/cell").json()["devices"]):
                    r = c.post("/cell/reconnect", json={})
                    assert r.status_code == 200, r.text
            r = c.post(f"/jobs/{job}/resume")
            if r.status_code == 507:  # still short of space: an episode not yet over
                rep.refusals.append((cell.name, r.status_code, r.json().get("detail")))
                self._free()
                r = c.post(f"/jobs/{job}/resume")
            assert r.status_code == 200, (r.status_code, r.text)
            rep.jobs["resumed"] += 1

    # -- faults from outside --------------------------------------------------------------------------------
    def _outside(self, cell: SoakCell, job: int, kind: str) -> None:
        step = self.rng.randint(2, 18)  # the fault falls around this step, or when the job has settled
        self._reach(cell, job, step)
        if kind == "kill9":
            self.restarting.add(cell.name)
            self.kills[cell.name] = self.kills.get(cell.name, 0) + 1
            children = _children(cell.daemon.proc.pid)
            cell.daemon.kill9()
            for pid in children:  # a driver's process (ur-rtde's) must end with its daemon, not outlive it
                try:
                    eventually(lambda pid=pid: not _running(pid), timeout=30, what=f"process {pid} to end")
                except AssertionError:
                    self.report.orphans.append((cell.name, pid, _command(pid)))
            cell.daemon.log.close()
            cell.daemon.start(timeout=180)
            self.restarting.discard(cell.name)
            self.report.lives[cell.name].append([])
        elif kind == "outage":
            self.postgres.stop()  # resumed once the job is done
            self.mosquitto.stop()
            self.mosquitto.resume()
        elif kind == "clock_step":
            self.wall.step(3600 if self.wall.offset_s <= 0 else -3600)
        elif kind == "disk_full":
            self._fill()
            with cell.client() as c:  # a new job is refused, naming the free space and the floor
                r = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": 0})
            if r.status_code != 507:
                raise AssertionError(f"{cell.name}: a job submitted on a full disk got {r.status_code} {r.text}")
            self.report.refusals.append((cell.name, r.status_code, r.json().get("detail")))
            self._settled(cell, job)  # faulted (DiskFull) if it wrote meanwhile, else done
            self._free()

    def _reach(self, cell: SoakCell, job: int, step: int) -> None:
        def there() -> bool:
            with cell.client() as c:
                got = c.get(f"/jobs/{job}").json()
            return got["state"] in TERMINAL or (got.get("progress") or {}).get("step", 0) >= step

        eventually(there, timeout=300, every=0.02, what=f"{cell.name} job {job} at step {step}")

    def _fill(self) -> None:
        """The stores' filesystem filled to the last byte: its free space taken at once, then what the daemons
        freed meanwhile written until the filesystem says ENOSPC."""
        with open(self.ballast, "ab") as f:
            free = os.statvfs(self.ballast.parent)
            try:
                os.posix_fallocate(f.fileno(), 0, free.f_bavail * free.f_frsize)
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
            f.seek(0, os.SEEK_END)
            chunk = b"\0" * (1 << 20)
            try:
                while True:
                    f.write(chunk)
                    f.flush()
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise

    def _free(self) -> None:
        self.ballast.unlink(missing_ok=True)

    # -- what is counted ------------------------------------------------------------------------------------
    def _compare(self, cell: SoakCell, job: int, reference: tuple[dict, list[dict]]) -> None:
        rep = self.report
        ref_result, ref_rows = reference
        with cell.client() as c:
            rows = read_samples_text(c.get(f"/jobs/{job}/samples").text)
            result = c.get(f"/jobs/{job}/result").json()
        got, expected = _by_step(rows), _by_step(ref_rows)  # a step may keep several rows
        lost = duplicated = 0
        different = []
        for step, want in expected.items():
            have = got.get(step, [])
            lost += max(len(want) - len(have), 0)
            duplicated += max(len(have) - len(want), 0)
            if any(csv_cell(v) != csv_cell(g.get(k)) for w, g in zip(want, have) for k, v in w.items()
                   if k not in NOT_COMPARED):
                different.append(f"step {step}")
        duplicated += sum(len(have) for step, have in got.items() if step not in expected)
        different += [key for key in ("stats", "model", "cell_time_s")
                      if _plain(result.get(key)) != _plain(ref_result.get(key))]
        rep.lost += lost
        rep.duplicated += duplicated
        rep.different += [(cell.name, job, what) for what in different]
        if lost or duplicated or different:
            rep.bad_jobs.append({"cell": cell.name, "job": job, "lost": lost, "duplicated": duplicated,
                                 "different": different, "met": list(self.met)})

    def _measure(self, cell: SoakCell, job: int) -> None:
        pid = cell.daemon.proc.pid
        status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
        sample = Sample(job, int(status["VmRSS"].split()[0]) / 1024, len(os.listdir(f"/proc/{pid}/fd")),
                        int(status["Threads"]), len(_children(pid)))
        self.report.lives[cell.name][-1].append(sample)

    def _replicated(self, cell: SoakCell, timeout: float = 120.0) -> dict:
        """The plant database's differences from the cell, once replication has caught up (or at the time-out)."""
        last: dict = {}

        def caught_up() -> bool:
            nonlocal last
            last = differences(cell.daemon.store, self.postgres.dsn, cell.name)
            return not last

        try:
            eventually(caught_up, timeout=timeout, every=0.25, what=f"{cell.name} replicated")
        except AssertionError:
            pass
        return last

    def _reader(self) -> None:
        """A background client: GET /cell and the live job, timed; a daemon being restarted is counted apart.
        One connection per daemon, kept, as a dashboard keeps one."""
        rep = self.report
        clients: dict[str, httpx.Client] = {}
        try:
            while not self.stop_readers.is_set():
                live = self.live
                if live is None:
                    self.stop_readers.wait(self.settings.read_every_s)
                    continue
                cell, job = live
                for path in ("/cell", f"/jobs/{job}"):
                    if cell.name in self.restarting:
                        rep.unavailable += 1
                        continue
                    url, kills = cell.daemon.url, self.kills.get(cell.name, 0)
                    if url not in clients:
                        clients[url] = httpx.Client(base_url=url, timeout=30, headers={
                            "Authorization": f"Bearer {cell.daemon.token}"})
                    t = time.monotonic()
                    try:
                        r = clients[url].get(path)
                        if r.status_code != 200:
                            rep.read_errors.append((cell.name, path, r.status_code))
                        else:
                            rep.latencies.append(time.monotonic() - t)
                    except (httpx.HTTPError, OSError) as exc:
                        clients.pop(url).close()
                        if (cell.name in self.restarting or cell.daemon.proc.poll() is not None
                                or self.kills.get(cell.name, 0) != kills):
                            rep.unavailable += 1
                        else:  # what failed, and when (s into the soak), to find it in the daemon's log
                            rep.read_errors.append((cell.name, path, f"{type(exc).__name__}: {exc}"[:120],
                                                    round(time.monotonic() - self.t0, 1)))
                self.stop_readers.wait(self.settings.read_every_s)
        finally:
            for c in clients.values():
                c.close()


def _by_step(rows: list[dict]) -> dict[int, list[dict]]:
    out: dict[int, list[dict]] = {}
    for r in rows:
        out.setdefault(int(r["step"]), []).append(r)
    return out


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(p) for p in (task / "children").read_text().split()]
        except OSError:  # the thread ended meanwhile
            pass
    return out


def _running(pid: int) -> bool:
    """Alive and not a zombie (a zombie has ended; only its parent has not collected it yet)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _command(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ").strip()
    except OSError:
        return "?"


def _plain(value):
    """JSON as it comes back over the API (tuples as lists, floats as they print)."""
    import json

    return json.loads(json.dumps(value))
