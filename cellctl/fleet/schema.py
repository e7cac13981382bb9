"""The plant database's schema: versioned migrations, applied in order, each once, in one transaction.

Every table is keyed by the cell and the record's id in that cell's own store, so a record replicated twice
is written once (`INSERT ... ON CONFLICT DO NOTHING` / `DO UPDATE`): a retry never duplicates. Many cells may
start at once against a new database: the migrations run under an advisory lock, so one of them migrates
and the others find it done.
"""

from __future__ import annotations

import psycopg

# (version, what it adds, SQL); append only: a migration that has run on a plant database is never edited
MIGRATIONS: list[tuple[int, str, str]] = [
    (1, "cells, jobs and their state history, samples, results, calibrations, health checks, audit", """
CREATE TABLE cells (
    name TEXT PRIMARY KEY,
    description TEXT NOT NULL DEFAULT '',
    software_revision TEXT NOT NULL DEFAULT '',
    api_url TEXT NOT NULL DEFAULT '',
    state TEXT NOT NULL DEFAULT 'unknown',
    live_job BIGINT,
    last_seen TIMESTAMPTZ NOT NULL DEFAULT now()
);
CREATE TABLE jobs (
    cell TEXT NOT NULL REFERENCES cells (name),
    id BIGINT NOT NULL,
    routine TEXT NOT NULL,
    params JSONB NOT NULL,
    seed BIGINT,
    state TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    submitted_by TEXT NOT NULL,
    created TIMESTAMPTZ NOT NULL,
    updated TIMESTAMPTZ NOT NULL,
    PRIMARY KEY (cell, id)
);
CREATE TABLE job_states (
    cell TEXT NOT NULL REFERENCES cells (name),
    id BIGINT NOT NULL,                  -- the cell's job_events id: the order of its state changes
    job_id BIGINT NOT NULL,
    at TIMESTAMPTZ NOT NULL,
    from_state TEXT,
    to_state TEXT NOT NULL,
    reason TEXT NOT NULL,
    who TEXT NOT NULL,
    PRIMARY KEY (cell, id)
);
CREATE TABLE samples (
    cell TEXT NOT NULL REFERENCES cells (name),
    job_id BIGINT NOT NULL,
    item TEXT NOT NULL DEFAULT '',       -- a sequence's routine, '' for a single routine
    step BIGINT NOT NULL,
    row_index INTEGER NOT NULL,          -- a step may give several rows
    data JSONB NOT NULL,
    PRIMARY KEY (cell, job_id, item, step, row_index)
);
CREATE TABLE results (
    cell TEXT NOT NULL REFERENCES cells (name),
    job_id BIGINT NOT NULL,
    item TEXT NOT NULL DEFAULT '',
    routine TEXT NOT NULL,
    result JSONB NOT NULL,
    PRIMARY KEY (cell, job_id, item)
);
CREATE TABLE calibrations (
    cell TEXT NOT NULL REFERENCES cells (name),
    id BIGINT NOT NULL,
    target TEXT NOT NULL,
    routine TEXT NOT NULL,
    version INTEGER NOT NULL,
    created TIMESTAMPTZ NOT NULL,
    active BOOLEAN NOT NULL,
    cell_file TEXT NOT NULL,
    result JSONB NOT NULL,               -- model, stats and provenance, as the cell keeps them
    samples TEXT,                        -- its samples.csv, for a restore
    PRIMARY KEY (cell, id),
    UNIQUE (cell, target, version)
);
CREATE TABLE health_checks (
    cell TEXT NOT NULL REFERENCES cells (name),
    id BIGINT NOT NULL,
    created TIMESTAMPTZ NOT NULL,
    verdict TEXT NOT NULL,
    targets JSONB NOT NULL,              -- per target: calibration id, drifted, p-value, drift, action
    PRIMARY KEY (cell, id)
);
CREATE TABLE audit (
    cell TEXT NOT NULL REFERENCES cells (name),
    id BIGINT NOT NULL,
    at TIMESTAMPTZ NOT NULL,
    who TEXT NOT NULL,
    client TEXT NOT NULL,
    action TEXT NOT NULL,
    target TEXT NOT NULL,
    detail TEXT NOT NULL,
    outcome TEXT NOT NULL,
    PRIMARY KEY (cell, id)
);
CREATE INDEX job_states_by_job ON job_states (cell, job_id, id);
CREATE INDEX calibrations_active ON calibrations (cell, target) WHERE active;
"""),
    (2, "jobs keep the id of the state change they show, so an older record replayed never overwrites a newer "
        "one; a cell's live job's state", """
ALTER TABLE jobs ADD COLUMN event BIGINT NOT NULL DEFAULT 0;
ALTER TABLE cells ADD COLUMN cell_state TEXT NOT NULL DEFAULT 'idle';
CREATE INDEX health_checks_by_time ON health_checks (cell, created);
"""),
    (3, "when the plant received each job state change: the replication lag, seen from the plant", """
ALTER TABLE job_states ADD COLUMN received TIMESTAMPTZ NOT NULL DEFAULT clock_timestamp();
"""),
]

LOCK_KEY = 0x63656C6C  # "cell": the advisory lock every cell takes to migrate


def migrate(conn: psycopg.Connection) -> int:
    """Bring the database to the newest schema; returns its version. Safe for many cells at once."""
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(%s)", (LOCK_KEY,))
        conn.execute("CREATE TABLE IF NOT EXISTS schema_migrations (version INTEGER PRIMARY KEY, "
                     "description TEXT NOT NULL, applied TIMESTAMPTZ NOT NULL DEFAULT now())")
        done = {row[0] for row in conn.execute("SELECT version FROM schema_migrations")}
        newest = max(done, default=0)
        known = max(v for v, _, _ in MIGRATIONS)
        if newest > known:
            raise RuntimeError(f"the plant database is at schema version {newest}, newer than this cellctl "
                               f"knows ({known}): upgrade cellctl on this cell")
        for version, description, sql in MIGRATIONS:
            if version not in done:
                conn.execute(sql)
                conn.execute("INSERT INTO schema_migrations (version, description) VALUES (%s, %s)",
                             (version, description))
        return known
