"""Jobs as plain data in SQLite: routine + parameters (+ seed), their state, every state change, the audit log.

A job moves through a small state machine; each change is one transaction that
checks the current state and records the change with who asked and why, so a
refused transition changes nothing. The database (WAL) sits beside the
calibration store, each job's run folder under `jobs/<id>` next to it.

    queued  -> running, paused (daemon restarted), aborted
    running -> paused, faulted, aborted, done
    paused  -> queued (resume: run again from the persisted samples), running (a held pause lifts), aborted
    faulted -> paused (acknowledged), aborted

The audit log keeps every accepted command (outcome `ok`, or `failed` when the work
itself failed) for good. A refused request (no token or a wrong one, another client's lock,
malformed input, a state that did not allow it; outcome `refused NNN: the reason`, or
`refused NNN` alone where the HTTP layer refused it before the service saw it) is kept
REFUSED_KEEP_DAYS days, and of those only the newest REFUSED_KEEP_LAST (pruned every
PRUNE_EVERY refusals and when the store opens), so a client that keeps knocking
cannot grow the table without bound. Pruning deletes the local rows only: a cell in a
fleet recorded each entry in its outbox when it was written (same transaction), and
the plant database keeps its copy.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Collection
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

from calibration.routines import sequences

from cellctl.errors import ServiceError
from cellctl.stores import outbox
from cellctl.stores.run_folder import RunFolder, to_jsonable

DB_FILE = "daemon.sqlite"  # in the store: the jobs, their states and the audit of every command

STATES = ("queued", "running", "paused", "faulted", "aborted", "done")
TRANSITIONS = {
    "queued": {"running", "paused", "aborted"},
    "running": {"paused", "faulted", "aborted", "done"},
    "paused": {"queued", "running", "aborted"},  # running: a pause held at a step boundary lifts
    "faulted": {"paused", "aborted"},
    "aborted": set(),
    "done": set(),
}

SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    routine TEXT NOT NULL,
    params TEXT NOT NULL,
    seed INTEGER,
    save_images INTEGER NOT NULL DEFAULT 0,
    state TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    acknowledged INTEGER NOT NULL DEFAULT 1,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    submitted_by TEXT NOT NULL,
    run_dir TEXT NOT NULL,
    progress TEXT,
    result TEXT
);
CREATE TABLE IF NOT EXISTS job_events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id INTEGER NOT NULL REFERENCES jobs(id),
    at TEXT NOT NULL,
    from_state TEXT,
    to_state TEXT NOT NULL,
    reason TEXT NOT NULL,
    who TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    at TEXT NOT NULL,
    who TEXT NOT NULL,
    client TEXT NOT NULL,
    action TEXT NOT NULL,
    target TEXT NOT NULL,
    detail TEXT NOT NULL,
    outcome TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS audit_refused ON audit (id) WHERE outcome LIKE 'refused%';
CREATE INDEX IF NOT EXISTS job_events_job ON job_events (job_id);
"""

# the audit log's retention of refused requests (accepted commands are never dropped): see the module docstring
REFUSED_KEEP_DAYS = 30.0
REFUSED_KEEP_LAST = 10_000
PRUNE_EVERY = 100


class JobError(ServiceError):
    """A request on a job that its state does not allow (409) or an unknown job (404)."""

    def __init__(self, message: str, status: int = 409):
        super().__init__(message)
        self.status = status


# -- a job in its user's terms: what happened, what it stored, and what can be done now -------------------------

# (command, state the job is in) -> what can be done instead: the one table of the refusals of a job command
REFUSED = {
    ("pause", "done"): "there is nothing to pause",
    ("pause", "aborted"): "there is nothing to pause",
    ("pause", "faulted"): "it has stopped already: acknowledge it, then resume or abort it",
    ("pause", "paused"): "it is paused already: resume it or abort it",
    ("pause", "running"): "it is already pausing or aborting: wait until it has stopped",
    ("resume", "done"): "there is nothing to resume; to repeat it, submit it again as a new job",
    ("resume", "aborted"): "an aborted job cannot be resumed; submit it again as a new job (it runs from the start)",
    ("resume", "faulted"): "acknowledge it first (nothing moves), then resume it",
    ("resume", "paused"): "it was faulted: acknowledge it first (nothing moves), then resume it",
    ("resume", "queued"): "it is waiting for the cell already: there is nothing to resume",
    ("resume", "running"): "pause it first",
    ("resume", "stopping"): "it is stopping: resume it once it is paused",
    ("acknowledge", "done"): "there is no fault to acknowledge",
    ("acknowledge", "aborted"): "there is no fault to acknowledge",
    ("acknowledge", "paused"): "there is no fault to acknowledge: resume it to continue",
    ("acknowledge", "queued"): "there is no fault to acknowledge",
    ("acknowledge", "running"): "there is no fault to acknowledge",
    ("abort", "done"): "there is nothing to abort; its results stay",
    ("abort", "aborted"): "it is aborted already; its samples are kept",
}


def refusal(job: "Job", command: str, situation: str | None = None) -> "JobError":
    """The JobError (409) for `command` on `job`: what happened to the job, then what can be done now.
    `situation`: a key of REFUSED finer than the job's state (e.g. "stopping")."""
    now = REFUSED.get((command, situation or job.state), f"{command} does not apply to it now")
    return JobError(f"{what_happened(job)}; {now}")


def what_happened(job: "Job") -> str:
    """The job's state in words, with its reason, and for a job that ran: the routines that finished (of a
    sequence) and the calibrations they stored and activated."""
    name = f"job {job.id} ({job.routine})"
    why = f" ({job.reason})" if job.reason else ""
    said = {"queued": f"{name} is queued{why}", "running": f"{name} is running", "paused": f"{name} is paused{why}",
            "faulted": f"{name} faulted{why}", "aborted": f"{name} was aborted{why}",
            "done": f"{name} has finished (done)"}.get(job.state, f"{name} is {job.state}")
    if job.state in ("queued", "running"):
        return said
    results = finished_results(job)
    sequence = sequences().get(job.routine)
    items = sequence.names if sequence is not None else None
    if items is not None and job.state != "done":
        said += (f"; {len(results)} of its {len(items)} routines finished ({', '.join(results)})" if results else
                 f"; none of its {len(items)} routines finished")
    stored = [c for r in results.values() for c in stored_calibrations(r)]
    if stored:
        return said + "; it stored and activated " + ", ".join(stored)
    return said + ("; it stored no calibration" if job.state == "done" else
                   "; nothing was stored (a routine stores its calibration when it finishes)")


def finished_results(job: "Job") -> dict[str, dict]:
    """The results of the routines of `job` that ran to their end: a sequence's by item (from their run folders),
    a single routine's (its result once done) under its own name."""
    sequence = sequences().get(job.routine)
    if sequence is None:
        return {job.routine: job.result} if job.state == "done" and job.result else {}
    out = {}
    for item in sequence.names:
        path = Path(job.run_dir) / sequence.folder(item) / "result.json"
        try:
            out[item] = json.loads(path.read_text())
        except (OSError, ValueError):  # not run, or not to its end
            continue
    return out


def stored_calibrations(result: dict) -> list[str]:
    """The calibrations one routine's result says it stored (each made active as it was stored), in words."""
    out = []
    cal = result.get("calibration")
    if cal:
        out.append(f"calibration {cal['id']} ({cal['target']} version {cal['version']})")
    out += [f"calibration {cal_id} ({target}, a touch-up)" for target, cal_id in (result.get("updated") or {}).items()]
    return out


def folder_records(job: "Job") -> tuple[dict[tuple[str, int], list[dict]], dict[str, dict]]:
    """What a job's run folders hold: its samples by (item, step), and the results of a sequence's routines (for
    `JobStore.resend`, when a step may have reached its folder and not its record)."""
    steps: dict[tuple[str, int], list[dict]] = {}
    results: dict[str, dict] = {}
    run_dir = Path(job.run_dir)
    sequence = sequences().get(job.routine)
    folders = ([(item, run_dir / sequence.folder(item)) for item in sequence.names] if sequence is not None
               else [("", run_dir)])
    for item, folder in folders:
        run = RunFolder(folder)
        if not run.exists():
            continue
        for row in run.samples():
            steps.setdefault((item, int(row["step"])), []).append(row)
        if item and (folder / "result.json").exists():
            results[item] = json.loads((folder / "result.json").read_text())
    return steps, results


def now() -> str:
    t = time.time()
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


@dataclass
class Job:
    id: int
    routine: str
    params: dict
    seed: int | None
    save_images: bool  # every camera frame kept as PNG under the run folder's images/
    state: str
    reason: str
    acknowledged: bool
    created: str
    updated: str
    submitted_by: str
    run_dir: str
    progress: dict | None
    result: dict | None

    def to_dict(self, with_result: bool = False) -> dict:
        d = asdict(self)
        if not with_result:
            d.pop("result")
        return d


_COLUMNS = ("id, routine, params, seed, save_images, state, reason, acknowledged, created, updated, submitted_by, "
            "run_dir, progress, result")


def _running_s(events: list[tuple[str, str]]) -> float:
    """Seconds spent in 'running' over a job's state changes (time, new state), oldest first. From the stored
    wall-clock stamps (a run the daemon died under has no other): a wall step during a run skews that run's figure,
    and one backwards never makes it negative."""
    total, since = 0.0, None
    for at, state in events:
        t = datetime.fromisoformat(at).timestamp()
        if since is not None:
            total += max(t - since, 0.0)
        since = t if state == "running" else None
    return total


def _job(row) -> Job:
    (id_, routine, params, seed, save_images, state, reason, ack, created, updated, who, run_dir, progress,
     result) = row
    return Job(id_, routine, json.loads(params), seed, bool(save_images), state, reason, bool(ack), created, updated,
               who, run_dir, json.loads(progress) if progress else None, json.loads(result) if result else None)


class JobStore:
    """`replicate`: every change is also written to the outbox, in its transaction (cellctl.stores.outbox)."""

    def __init__(self, path: str | Path, replicate: bool = False, refused_keep_days: float = REFUSED_KEEP_DAYS,
                 refused_keep_last: int = REFUSED_KEEP_LAST):
        self.path = Path(path)
        self.refused_keep_days, self.refused_keep_last = refused_keep_days, refused_keep_last
        self._refused_since_prune = 0
        self.outbox = outbox.Recorder(replicate)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.jobs_dir = self.path.parent / "jobs"
        self._lock = threading.RLock()  # one connection shared by the API and the worker thread
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")  # a state change reported is a state change kept
        self._db.executescript(SCHEMA)
        outbox.create(self._db)
        self._migrate()
        with self._transaction() as db:
            self._prune_refused(db)

    def _migrate(self) -> None:
        """Bring a database made by an older cellctl up to SCHEMA (columns added since, with their defaults)."""
        with self._transaction() as db:  # checked and added in one transaction: two openers cannot both add it
            columns = {row[1] for row in db.execute("PRAGMA table_info(jobs)")}
            if "save_images" not in columns:
                db.execute("ALTER TABLE jobs ADD COLUMN save_images INTEGER NOT NULL DEFAULT 0")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # -- reading ------------------------------------------------------------------

    def get(self, job_id: int) -> Job:
        with self._lock:
            row = self._db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE id = ?", (int(job_id),)).fetchone()
        if row is None:
            raise JobError(f"no job {job_id}", status=404)
        return _job(row)

    def list(self, state: str | None = None, limit: int = 100) -> list[Job]:
        query = f"SELECT {_COLUMNS} FROM jobs" + (" WHERE state = ?" if state else "") + " ORDER BY id DESC LIMIT ?"
        with self._lock:
            rows = self._db.execute(query, ((state,) if state else ()) + (int(limit),)).fetchall()
        return [_job(r) for r in rows]

    def next_queued(self) -> Job | None:
        """The job queued first (a resumed one queues anew), by the order of the changes, never by their wall-clock
        stamps: a clock step must not let a job overtake another."""
        with self._lock:
            row = self._db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE state = 'queued' ORDER BY (SELECT MAX(e.id) "
                                   "FROM job_events e WHERE e.job_id = jobs.id), id LIMIT 1").fetchone()
        return _job(row) if row else None

    def history(self, job_id: int) -> list[dict]:
        self.get(job_id)
        with self._lock:
            rows = self._db.execute("SELECT at, from_state, to_state, reason, who FROM job_events WHERE job_id = ? "
                                    "ORDER BY id", (int(job_id),)).fetchall()
        return [dict(zip(("at", "from", "to", "reason", "who"), r)) for r in rows]

    def audit_log(self, limit: int = 200) -> list[dict]:
        with self._lock:
            rows = self._db.execute("SELECT at, who, client, action, target, detail, outcome FROM audit "
                                    "ORDER BY id DESC LIMIT ?", (int(limit),)).fetchall()
        keys = ("at", "who", "client", "action", "target", "detail", "outcome")
        return [dict(zip(keys, r)) for r in reversed(rows)]

    # -- for the metrics (cellctl.http.metrics) ------------------------------------

    def counts(self) -> dict[tuple[str, str], int]:
        """How many jobs there are of each (routine, state)."""
        with self._lock:
            rows = self._db.execute("SELECT routine, state, COUNT(*) FROM jobs GROUP BY routine, state").fetchall()
        return {(routine, state): n for routine, state, n in rows}

    def done_times(self, known: Collection[int] = ()) -> dict[int, tuple[str, float | None, float]]:
        """Per job done, but those in `known` (done is final: their times do not change): its routine, its cell
        time (s, from its result) and the wall time (s) it spent running, pauses left out (a run the daemon died
        under counts until the restart marked it faulted)."""
        with self._lock:
            done = [row for row in self._db.execute("SELECT id, routine, json_extract(result, '$.cell_time_s') "
                                                    "FROM jobs WHERE state = 'done'") if row[0] not in known]
            events: dict[int, list[tuple[str, str]]] = {}
            for i in range(0, len(done), 500):  # SQLite's limit on parameters
                ids = [row[0] for row in done[i:i + 500]]
                for job_id, at, to in self._db.execute(
                        f"SELECT job_id, at, to_state FROM job_events WHERE job_id IN ({','.join('?' * len(ids))}) "
                        "ORDER BY id", ids):
                    events.setdefault(job_id, []).append((at, to))
        return {job_id: (routine, cell_s, _running_s(events.get(job_id, []))) for job_id, routine, cell_s in done}

    # -- changing -------------------------------------------------------------------

    def submit(self, routine: str, params: dict, seed: int | None, who: str, *, save_images: bool = False) -> Job:
        stamp = now()
        with self._transaction() as db:
            cur = db.execute("INSERT INTO jobs (routine, params, seed, save_images, state, created, updated, "
                             "submitted_by, run_dir) VALUES (?, ?, ?, ?, 'queued', ?, ?, ?, '')",
                             (routine, json.dumps(to_jsonable(params)), seed, int(bool(save_images)), stamp, stamp,
                              who))
            job_id = cur.lastrowid
            db.execute("UPDATE jobs SET run_dir = ? WHERE id = ?", (str(self.jobs_dir / f"{job_id:06d}"), job_id))
            event = db.execute("INSERT INTO job_events (job_id, at, from_state, to_state, reason, who) VALUES (?, ?, "
                               "NULL, 'queued', 'submitted', ?)", (job_id, stamp, who)).lastrowid
            self._record_change(db, job_id, event)
        self.outbox.committed()
        return self.get(job_id)

    def transition(self, job_id: int, to: str, reason: str, who: str, *, allowed_from: set[str] | None = None,
                   acknowledged: bool | None = None, result: dict | None = None, command: str | None = None) -> Job:
        """Check and change the state in one transaction; JobError (nothing changed) if not allowed, said in the
        user's terms (`refusal`) when `command` names the user's command."""
        with self._transaction() as db:
            row = db.execute("SELECT state, acknowledged FROM jobs WHERE id = ?", (int(job_id),)).fetchone()
            if row is None:
                raise JobError(f"no job {job_id}", status=404)
            state = row[0]
            permitted = {s for s, targets in TRANSITIONS.items() if to in targets}
            if allowed_from is not None:
                permitted &= allowed_from
            if state not in permitted:
                if command is not None:
                    raise refusal(self.get(job_id), command)
                raise JobError(f"job {job_id} is {state}; it must be {' or '.join(sorted(permitted))} to become {to}")
            stamp = now()
            ack = row[1] if acknowledged is None else int(acknowledged)
            db.execute("UPDATE jobs SET state = ?, reason = ?, acknowledged = ?, updated = ?"
                       + (", result = ?" if result is not None else "") + " WHERE id = ?",
                       (to, reason, ack, stamp) + ((json.dumps(to_jsonable(result)),) if result is not None else ())
                       + (int(job_id),))
            event = db.execute("INSERT INTO job_events (job_id, at, from_state, to_state, reason, who) VALUES "
                               "(?, ?, ?, ?, ?, ?)", (int(job_id), stamp, state, to, reason, who)).lastrowid
            self._record_change(db, int(job_id), event)
            if result is not None and to == "done":
                self._record_result(db, int(job_id), "", result)
        self.outbox.committed()
        return self.get(job_id)

    def set_progress(self, job_id: int, progress: dict) -> None:
        with self._lock:
            self._db.execute("UPDATE jobs SET progress = ? WHERE id = ?", (json.dumps(to_jsonable(progress)), job_id))

    def record_step(self, job_id: int, item: str | None, step: int, rows: list[dict], progress: dict,
                    announce: bool) -> None:
        """A step's samples (already in the run folder's samples.csv) and the job's progress, in one transaction;
        `announce`: the progress also goes to the plant's event stream (the caller limits how often)."""
        with self._transaction() as db:
            db.execute("UPDATE jobs SET progress = ? WHERE id = ?", (json.dumps(to_jsonable(progress)), job_id))
            self._record_samples(db, job_id, item, step, rows)
            if announce:
                self.outbox.record(db, "progress", f"progress/{job_id}/{item or ''}/{step}", progress)
        self.outbox.committed()

    def record_result(self, job_id: int, item: str, result: dict) -> None:
        """A sequence's routine finished: its result, for the plant (the job's own comes with its last state)."""
        with self._transaction() as db:
            self._record_result(db, job_id, item, result)
        self.outbox.committed()

    def resend(self, job_id: int, steps: dict[tuple[str, int], list[dict]], results: dict[str, dict]) -> None:
        """Record again what a job's run folders hold (after the daemon died between a step's samples reaching
        the folder and their record): the plant keeps each once, whatever it had already."""
        if not self.outbox.enabled:
            return
        with self._transaction() as db:
            for (item, step), rows in sorted(steps.items()):
                self._record_samples(db, job_id, item, step, rows)
            for item, result in results.items():
                self._record_result(db, job_id, item, result)
        self.outbox.committed()

    def record_cell(self, state: str, live_job: int | None) -> None:
        """What the cell is doing (idle, running, paused) and its live job: the plant's view of it."""
        if not self.outbox.enabled:
            return
        with self._transaction() as db:
            self.outbox.record(db, "cell", "cell", {"state": state, "live_job": live_job})
        self.outbox.committed()

    # -- the outbox's records (inside the change's transaction) ----------------------------------

    def _record_change(self, db, job_id: int, event: int) -> None:
        if not self.outbox.enabled:
            return
        (routine, params, seed, state, reason, created, updated, who) = db.execute(
            "SELECT routine, params, seed, state, reason, created, updated, submitted_by FROM jobs WHERE id = ?",
            (job_id,)).fetchone()
        self.outbox.record(db, "job", f"job/{job_id}", {
            "id": job_id, "routine": routine, "params": json.loads(params), "seed": seed, "state": state,
            "reason": reason, "submitted_by": who, "created": created, "updated": updated, "event": event})
        at, from_state, to_state, why, by = db.execute(
            "SELECT at, from_state, to_state, reason, who FROM job_events WHERE id = ?", (event,)).fetchone()
        self.outbox.record(db, "job_state", f"job_state/{event}", {
            "id": event, "job": job_id, "routine": routine, "at": at, "from": from_state, "to": to_state,
            "reason": why, "who": by})

    def _record_samples(self, db, job_id: int, item: str | None, step: int, rows: list[dict]) -> None:
        self.outbox.record(db, "samples", f"samples/{job_id}/{item or ''}/{step}",
                           {"job": job_id, "item": item or "", "step": step, "rows": rows})

    def _record_result(self, db, job_id: int, item: str, result: dict) -> None:
        self.outbox.record(db, "result", f"result/{job_id}/{item}",
                           {"job": job_id, "item": item, "routine": result.get("routine", ""), "result": result})

    def recover(self) -> list[Job]:
        """At start-up: a job that was running when the daemon died is faulted and needs an acknowledgement;
        a queued one is held (paused) so that nothing moves until an operator says so."""
        changed = []
        for job in self.list(limit=1_000_000):
            if job.state == "running":
                changed.append(self.transition(job.id, "faulted", "daemon stopped while running", "daemon",
                                               acknowledged=False))
            elif job.state == "queued":
                changed.append(self.transition(job.id, "paused", "daemon restarted before the job started; "
                                                                  "resume it to run", "daemon"))
        return changed

    def continue_after(self, last: dict[str, int]) -> None:
        """On a replaced cell PC: number its jobs, state changes and audit entries after the old PC's (`last`: the
        highest of each the plant database holds), since the plant keys them by the cell's numbers."""
        with self._transaction() as db:
            if db.execute("SELECT COUNT(*) FROM jobs").fetchone()[0]:
                raise JobError(f"{self.path} already holds jobs: restore into a new store")
            for table in ("jobs", "job_events", "audit"):
                db.execute("DELETE FROM sqlite_sequence WHERE name = ?", (table,))
                db.execute("INSERT INTO sqlite_sequence (name, seq) VALUES (?, ?)", (table, int(last.get(table) or 0)))

    def audit(self, who: str, client: str, action: str, target: str, detail: dict | str, outcome: str) -> None:
        text = detail if isinstance(detail, str) else json.dumps(to_jsonable(detail), sort_keys=True)
        entry = {"at": now(), "who": who, "client": client, "action": action, "target": target, "detail": text,
                 "outcome": outcome}
        with self._transaction() as db:
            entry["id"] = db.execute("INSERT INTO audit (at, who, client, action, target, detail, outcome) VALUES "
                                     "(:at, :who, :client, :action, :target, :detail, :outcome)", entry).lastrowid
            self.outbox.record(db, "audit", f"audit/{entry['id']}", entry)
            if outcome.startswith("refused"):
                self._refused_since_prune += 1
                if self._refused_since_prune >= PRUNE_EVERY:
                    self._prune_refused(db)
        self.outbox.committed()

    def _prune_refused(self, db) -> int:
        """Delete the refused requests beyond the retention (older than refused_keep_days, or older than the
        newest refused_keep_last); never an accepted command. Local only: the plant keeps its copy."""
        self._refused_since_prune = 0
        t = time.time() - self.refused_keep_days * 86400
        cutoff = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"
        return db.execute("DELETE FROM audit WHERE outcome LIKE 'refused%' AND (at < :cutoff OR id <= (SELECT id "
                          "FROM audit WHERE outcome LIKE 'refused%' ORDER BY id DESC LIMIT 1 OFFSET :keep))",
                          {"cutoff": cutoff, "keep": int(self.refused_keep_last)}).rowcount

    def _transaction(self):
        return _Transaction(self._db, self._lock)


class _Transaction:
    def __init__(self, db, lock):
        self.db, self.lock = db, lock

    def __enter__(self):
        self.lock.acquire()
        self.db.execute("BEGIN IMMEDIATE")
        return self.db

    def __exit__(self, exc_type, *exc):
        try:
            _end(self.db, exc_type)
        finally:
            self.lock.release()
        return False


def _end(db, failed) -> None:
    """COMMIT, or ROLLBACK when the work failed; a COMMIT that fails (the disk full: SQLITE_FULL) is rolled back
    too, so the connection is never left inside a transaction the next one would trip on."""
    try:
        db.execute("ROLLBACK" if failed else "COMMIT")
    except BaseException:
        if db.in_transaction:
            db.execute("ROLLBACK")
        raise
