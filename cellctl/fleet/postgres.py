"""The plant database as a sink: each outbox record written with the cell's name and its own key, so a record
delivered twice is kept once (`ON CONFLICT`), and a batch is one transaction: all of it or none.

The cell's row (`cells`) is written at each connection (name, description, software revision, API URL,
online) and its `last_seen` at every batch and heartbeat; a cell that stops says `offline`.
"""

from __future__ import annotations

import psycopg
from psycopg.types.json import Jsonb

from cellctl.fleet.replicator import SinkDown
from cellctl.fleet.schema import migrate
from cellctl.fleet.secrets import scrub
from cellctl.stores.outbox import Record


class PostgresSink:
    name = "postgres"

    def __init__(self, dsn: str, cell: str, info: dict | None = None, connect_timeout_s: int = 5):
        self.dsn, self.cell, self.info = dsn, cell, dict(info or {})
        self.connect_timeout_s = connect_timeout_s
        self.conn: psycopg.Connection | None = None

    def _down(self, exc: Exception, doing: str) -> SinkDown:
        return SinkDown(f"plant database: {doing}: " + scrub(str(exc).strip() or type(exc).__name__, self.dsn))

    def connect(self) -> None:
        try:
            # keepalives: a plant database that vanished without closing the link is noticed in seconds
            self.conn = psycopg.connect(self.dsn, connect_timeout=self.connect_timeout_s, keepalives=1,
                                        keepalives_idle=5, keepalives_interval=2, keepalives_count=3,
                                        options="-c statement_timeout=30000", application_name=f"cellctl {self.cell}")
            migrate(self.conn)
            with self.conn.transaction():
                self.conn.execute(
                    "INSERT INTO cells (name, description, software_revision, api_url, state, last_seen) "
                    "VALUES (%s, %s, %s, %s, 'online', now()) ON CONFLICT (name) DO UPDATE SET "
                    "description = EXCLUDED.description, software_revision = EXCLUDED.software_revision, "
                    "api_url = EXCLUDED.api_url, state = 'online', last_seen = now()",
                    (self.cell, self.info.get("description", ""), self.info.get("software_revision", ""),
                     self.info.get("api_url", "")))
        except (psycopg.Error, OSError) as exc:
            self.close(graceful=False)
            raise self._down(exc, "cannot connect") from None
        except RuntimeError as exc:  # a database newer than this cellctl: say so, and keep trying (it may be undone)
            self.close(graceful=False)
            raise SinkDown(f"plant database: {exc}") from None

    def deliver(self, records: list[Record]) -> None:
        if self.conn is None:
            raise SinkDown("plant database: not connected")
        try:
            with self.conn.transaction(), self.conn.cursor() as cur:
                for record in records:
                    write = WRITERS.get(record.kind)
                    if write is not None:
                        write(cur, self.cell, record.body)
                cur.execute("UPDATE cells SET last_seen = now() WHERE name = %s", (self.cell,))
        except (psycopg.OperationalError, psycopg.InterfaceError, OSError) as exc:
            self.close(graceful=False)
            raise self._down(exc, "writing records") from None

    def heartbeat(self) -> None:
        if self.conn is None:
            raise SinkDown("plant database: not connected")
        try:
            with self.conn.transaction():
                self.conn.execute("UPDATE cells SET last_seen = now(), state = CASE WHEN state = 'offline' THEN "
                                  "'online' ELSE state END WHERE name = %s", (self.cell,))
        except (psycopg.Error, OSError) as exc:
            self.close(graceful=False)
            raise self._down(exc, "heartbeat") from None

    def close(self, graceful: bool) -> None:
        conn, self.conn = self.conn, None
        if conn is None:
            return
        try:
            if graceful and not conn.closed:
                with conn.transaction():
                    conn.execute("UPDATE cells SET state = 'offline', live_job = NULL, cell_state = 'idle', "
                                 "last_seen = now() WHERE name = %s", (self.cell,))
        except (psycopg.Error, OSError):
            pass  # the database is gone: it will see last_seen stand still
        finally:
            conn.close()


# -- one writer per record kind (outbox.py's table) ---------------------------------------------------


def _job(cur, cell: str, b: dict) -> None:
    cur.execute("INSERT INTO jobs (cell, id, routine, params, seed, state, reason, submitted_by, created, updated, "
                "event) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s) ON CONFLICT (cell, id) DO UPDATE SET "
                "state = EXCLUDED.state, reason = EXCLUDED.reason, updated = EXCLUDED.updated, event = EXCLUDED.event "
                "WHERE jobs.event < EXCLUDED.event",
                (cell, b["id"], b["routine"], Jsonb(b["params"]), b["seed"], b["state"], b["reason"],
                 b["submitted_by"], b["created"], b["updated"], b["event"]))


def _job_state(cur, cell: str, b: dict) -> None:
    cur.execute("INSERT INTO job_states (cell, id, job_id, at, from_state, to_state, reason, who) "
                "VALUES (%s, %s, %s, %s, %s, %s, %s, %s) ON CONFLICT (cell, id) DO NOTHING",
                (cell, b["id"], b["job"], b["at"], b["from"], b["to"], b["reason"], b["who"]))


def _samples(cur, cell: str, b: dict) -> None:
    cur.executemany("INSERT INTO samples (cell, job_id, item, step, row_index, data) VALUES (%s, %s, %s, %s, %s, %s) "
                    "ON CONFLICT (cell, job_id, item, step, row_index) DO NOTHING",
                    [(cell, b["job"], b["item"], b["step"], i, Jsonb(row)) for i, row in enumerate(b["rows"])])


def _result(cur, cell: str, b: dict) -> None:
    cur.execute("INSERT INTO results (cell, job_id, item, routine, result) VALUES (%s, %s, %s, %s, %s) "
                "ON CONFLICT (cell, job_id, item) DO NOTHING",
                (cell, b["job"], b["item"], b["routine"], Jsonb(b["result"])))


def _calibration(cur, cell: str, b: dict) -> None:
    cur.execute("INSERT INTO calibrations (cell, id, target, routine, version, created, active, cell_file, result, "
                "samples) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s) ON CONFLICT (cell, id) DO NOTHING "
                "RETURNING id", (cell, b["id"], b["target"], b["routine"], b["version"], b["created"], b["active"],
                                 b["cell_file"], Jsonb(b["result"]), b["samples"]))
    if cur.fetchone() is not None and b["active"]:  # new and active: the target's other versions are not
        cur.execute("UPDATE calibrations SET active = false WHERE cell = %s AND target = %s AND id <> %s AND active",
                    (cell, b["target"], b["id"]))


def _activation(cur, cell: str, b: dict) -> None:
    """The target's active version is b["id"]; none (a deactivation) when it is null."""
    if b["id"] is None:
        cur.execute("UPDATE calibrations SET active = false WHERE cell = %s AND target = %s", (cell, b["target"]))
        return
    cur.execute("UPDATE calibrations SET active = (id = %s) WHERE cell = %s AND target = %s",
                (b["id"], cell, b["target"]))


def _health_check(cur, cell: str, b: dict) -> None:
    cur.execute("INSERT INTO health_checks (cell, id, created, verdict, targets) VALUES (%s, %s, %s, %s, %s) "
                "ON CONFLICT (cell, id) DO NOTHING", (cell, b["id"], b["created"], b["verdict"], Jsonb(b["targets"])))


def _audit(cur, cell: str, b: dict) -> None:
    cur.execute("INSERT INTO audit (cell, id, at, who, client, action, target, detail, outcome) "
                "VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s) ON CONFLICT (cell, id) DO NOTHING",
                (cell, b["id"], b["at"], b["who"], b["client"], b["action"], b["target"], b["detail"], b["outcome"]))


def _cell(cur, cell: str, b: dict) -> None:
    cur.execute("UPDATE cells SET cell_state = %s, live_job = %s, state = 'online' WHERE name = %s",
                (b["state"], b["live_job"], cell))


WRITERS = {"job": _job, "job_state": _job_state, "samples": _samples, "result": _result, "calibration": _calibration,
           "activation": _activation, "health_check": _health_check, "audit": _audit, "cell": _cell}
