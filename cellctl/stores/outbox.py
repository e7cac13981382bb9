"""The outbox: every change a cell records, written beside the change in the same local transaction, for the
replicator to carry to the plant (replicator.py).

Each store (the job database, the calibration store) keeps an `outbox` table in its own SQLite file. A store
calls `enqueue` inside the transaction that makes the change, so a change and its record are kept together or
not at all. Each sink (the plant database, the event stream) has a cursor: every record up to it has reached
that sink. A record is deleted once every configured sink has passed it.

Records, each a kind, a key (the record's identity in this cell: delivering it twice writes it once) and a JSON
body:

| kind         | key                          | body                                                                  |
|--------------|------------------------------|-----------------------------------------------------------------------|
| job          | job/<id>                     | id, routine, params, seed, state, reason, submitted_by, created,      |
|              |                              | updated, event (the job_state id of this change: newer wins)         |
| job_state    | job_state/<event id>         | id, job, routine, at, from, to, reason, who                           |
| samples      | samples/<job>/<item>/<step>  | job, item ('' unless a sequence's routine), step, rows [dict]         |
| progress     | progress/<job>/<item>/<step> | job, routine, item, step, total, cell_time_s, eta_cell_s, residual_um |
| result       | result/<job>/<item>          | job, item, routine, result (result.json as the cell keeps it)         |
| calibration  | calibration/<id>             | id, target, routine, version, created, active, cell_file, result,     |
|              |                              | samples (its samples.csv text, or null)                               |
| activation   | activation/<id>              | id, target (this version is now the target's active one; id null:    |
|              | deactivation/<id>/<ns>       | the target has none, its version <id> was taken out of use)           |
| health_check | health_check/<id>            | id, created, verdict, targets {target: calibration_id, drifted,       |
|              |                              | p_value, drift, action}                                               |
| audit        | audit/<id>                   | id, at, who, client, action, target, detail, outcome                  |
| cell         | cell                         | state (idle, running, paused), live_job (id or null)                  |

`at` is the time (s since the epoch) the record was made, for the replication lag.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from cellctl.stores.run_folder import to_jsonable

KINDS = ("job", "job_state", "samples", "progress", "result", "calibration", "activation", "health_check", "audit",
         "cell")

SCHEMA = """
CREATE TABLE IF NOT EXISTS outbox (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    key TEXT NOT NULL,
    body TEXT NOT NULL,
    at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS outbox_cursors (
    sink TEXT PRIMARY KEY,
    delivered INTEGER NOT NULL
);
"""


@dataclass(frozen=True)
class Record:
    seq: int  # order within its outbox (one per store)
    kind: str
    key: str
    body: dict
    at: float
    source: str = ""  # which store's outbox: "jobs" or "calibrations"


def enqueue(db: sqlite3.Connection, kind: str, key: str, body: dict[str, Any]) -> None:
    """Write one record; call it inside the transaction that makes the change it records."""
    if kind not in KINDS:
        raise ValueError(f"outbox: unknown record kind {kind!r} (kinds: {', '.join(KINDS)})")
    db.execute("INSERT INTO outbox (kind, key, body, at) VALUES (?, ?, ?, ?)",
               (kind, key, json.dumps(to_jsonable(body), allow_nan=False), time.time()))


class Outbox:
    """The replicator's side of one store's outbox: its own connection to the store's file (WAL: reads beside the
    store's writes), the records a sink has not had yet, and its cursor."""

    def __init__(self, path: str | Path, source: str):
        self.path, self.source = Path(path), source
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=30)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")  # as the store's own connection: a delivery marked stays marked
        self._db.executescript(SCHEMA)
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def delivered(self, sink: str) -> int:
        with self._lock:
            row = self._db.execute("SELECT delivered FROM outbox_cursors WHERE sink = ?", (sink,)).fetchone()
        return row[0] if row else 0

    def pending(self, sink: str, limit: int = 500) -> list[Record]:
        """The oldest records `sink` has not had, in order."""
        after = self.delivered(sink)
        with self._lock:
            rows = self._db.execute("SELECT seq, kind, key, body, at FROM outbox WHERE seq > ? ORDER BY seq LIMIT ?",
                                    (after, int(limit))).fetchall()
        return [Record(seq, kind, key, json.loads(body), at, self.source) for seq, kind, key, body, at in rows]

    def backlog(self, sink: str) -> int:
        after = self.delivered(sink)
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM outbox WHERE seq > ?", (after,)).fetchone()[0]

    def mark(self, sink: str, upto: int, sinks: tuple[str, ...]) -> None:
        """`sink` has every record up to `upto`; records every one of `sinks` has are deleted."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute("INSERT INTO outbox_cursors (sink, delivered) VALUES (?, ?) ON CONFLICT (sink) "
                                 "DO UPDATE SET delivered = MAX(delivered, excluded.delivered)", (sink, int(upto)))
                marks = dict(self._db.execute("SELECT sink, delivered FROM outbox_cursors"))
                floor = min(marks.get(s, 0) for s in sinks)
                self._db.execute("DELETE FROM outbox WHERE seq <= ?", (floor,))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise


class Recorder:
    """What a store holds to write its outbox: on or off (a cell in no fleet keeps no outbox), and whom to tell
    after a commit that wrote a record (the replicator's wake-up)."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.on_commit: Callable[[], None] | None = None

    def record(self, db: sqlite3.Connection, kind: str, key: str, body: dict[str, Any]) -> None:
        if self.enabled:
            enqueue(db, kind, key, body)

    def committed(self) -> None:
        if self.enabled and self.on_commit is not None:
            self.on_commit()


def create(db: sqlite3.Connection) -> None:
    """The outbox's tables in a store's database (made whether or not the cell is in a fleet)."""
    db.executescript(SCHEMA)
