"""Jobs as plain data in SQLite: routine + parameters (+ seed), their state, every state change, the audit log.

A job moves through a small state machine; each change is one transaction that
checks the current state and records the change with who asked and why, so a
refused transition changes nothing. The database (WAL) sits beside the
calibration store, each job's run folder under `jobs/<id>` next to it.

    queued  -> running, paused (daemon restarted), aborted
    running -> paused, faulted, aborted, done
    paused  -> queued (resume: run again from the persisted samples), running (a held pause lifts), aborted
    faulted -> paused (acknowledged), aborted
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

from ..errors import ServiceError
from ..store import to_jsonable

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
"""


class JobError(ServiceError):
    """A request on a job that its state does not allow (409) or an unknown job (404)."""

    def __init__(self, message: str, status: int = 409):
        super().__init__(message)
        self.status = status


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
    """Seconds spent in 'running' over a job's state changes (time, new state), oldest first."""
    total, since = 0.0, None
    for at, state in events:
        t = datetime.fromisoformat(at).timestamp()
        if since is not None:
            total += t - since
        since = t if state == "running" else None
    return total


def _job(row) -> Job:
    (id_, routine, params, seed, save_images, state, reason, ack, created, updated, who, run_dir, progress,
     result) = row
    return Job(id_, routine, json.loads(params), seed, bool(save_images), state, reason, bool(ack), created, updated,
               who, run_dir, json.loads(progress) if progress else None, json.loads(result) if result else None)


class JobStore:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.jobs_dir = self.path.parent / "jobs"
        self._lock = threading.RLock()  # one connection shared by the API and the worker thread
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")  # a state change reported is a state change kept
        self._db.executescript(SCHEMA)
        self._migrate()

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
        with self._lock:
            row = self._db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE state = 'queued' ORDER BY updated, id "
                                   "LIMIT 1").fetchone()
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

    # -- for the metrics (cellctl.daemon.metrics) ------------------------------------

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
            db.execute("INSERT INTO job_events (job_id, at, from_state, to_state, reason, who) VALUES (?, ?, NULL, "
                       "'queued', 'submitted', ?)", (job_id, stamp, who))
        return self.get(job_id)

    def transition(self, job_id: int, to: str, reason: str, who: str, *, allowed_from: set[str] | None = None,
                   acknowledged: bool | None = None, result: dict | None = None) -> Job:
        """Check and change the state in one transaction; JobError (nothing changed) if not allowed."""
        with self._transaction() as db:
            row = db.execute("SELECT state, acknowledged FROM jobs WHERE id = ?", (int(job_id),)).fetchone()
            if row is None:
                raise JobError(f"no job {job_id}", status=404)
            state = row[0]
            permitted = {s for s, targets in TRANSITIONS.items() if to in targets}
            if allowed_from is not None:
                permitted &= allowed_from
            if state not in permitted:
                raise JobError(f"job {job_id} is {state}; it must be {' or '.join(sorted(permitted))} to become {to}")
            stamp = now()
            ack = row[1] if acknowledged is None else int(acknowledged)
            db.execute("UPDATE jobs SET state = ?, reason = ?, acknowledged = ?, updated = ?"
                       + (", result = ?" if result is not None else "") + " WHERE id = ?",
                       (to, reason, ack, stamp) + ((json.dumps(to_jsonable(result)),) if result is not None else ())
                       + (int(job_id),))
            db.execute("INSERT INTO job_events (job_id, at, from_state, to_state, reason, who) VALUES (?, ?, ?, ?, ?, ?)",
                       (int(job_id), stamp, state, to, reason, who))
        return self.get(job_id)

    def set_progress(self, job_id: int, progress: dict) -> None:
        with self._lock:
            self._db.execute("UPDATE jobs SET progress = ? WHERE id = ?", (json.dumps(to_jsonable(progress)), job_id))

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

    def audit(self, who: str, client: str, action: str, target: str, detail: dict | str, outcome: str) -> None:
        text = detail if isinstance(detail, str) else json.dumps(to_jsonable(detail), sort_keys=True)
        with self._lock:
            self._db.execute("INSERT INTO audit (at, who, client, action, target, detail, outcome) VALUES "
                             "(?, ?, ?, ?, ?, ?, ?)", (now(), who, client, action, target, text, outcome))

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
            self.db.execute("ROLLBACK" if exc_type else "COMMIT")
        finally:
            self.lock.release()
        return False
