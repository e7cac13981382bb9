"""A cell's records as its own stores keep them, and as the plant database holds them, by the plant's keys: what
the fleet tests and the soak compare to count what replication lost or sent twice."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import psycopg

from cellctl.startup.daemon import folder_records
from cellctl.stores.jobs import Job


def local_records(store: Path) -> dict[str, set]:
    """Every record a cell keeps (its source of truth), by the plant database's keys."""
    with sqlite3.connect(store / "daemon.sqlite") as db:
        jobs = [Job(*row[:7], bool(row[7]), *row[8:12], None, None) for row in db.execute(
            "SELECT id, routine, params, seed, save_images, state, reason, acknowledged, created, updated, "
            "submitted_by, run_dir FROM jobs")]
        out = {"jobs": {(j.id, j.state) for j in jobs},
               "job_states": {r for r in db.execute("SELECT id, job_id, to_state FROM job_events")},
               "audit": {r[0] for r in db.execute("SELECT id FROM audit")}}
    with sqlite3.connect(store / "calibrations.sqlite") as db:
        out["calibrations"] = {r for r in db.execute("SELECT id, target, version, active FROM calibrations")}
        out["health_checks"] = {r[0] for r in db.execute("SELECT id FROM checks")}
    out["samples"], out["results"] = set(), set()
    for job in jobs:
        steps, results = folder_records(job)
        out["samples"] |= {(job.id, item, step, i) for (item, step), rows in steps.items() for i in range(len(rows))}
        out["results"] |= {(job.id, item) for item in results}
        if job.state == "done":
            out["results"].add((job.id, ""))
    return out


def plant_records(dsn: str, cell: str) -> tuple[dict[str, set], dict[str, int]]:
    """The same from the plant database, and how many rows each table holds for the cell."""
    queries = {"jobs": "SELECT id, state FROM jobs", "job_states": "SELECT id, job_id, to_state FROM job_states",
               "audit": "SELECT id FROM audit", "calibrations": "SELECT id, target, version, active FROM calibrations",
               "health_checks": "SELECT id FROM health_checks",
               "samples": "SELECT job_id, item, step, row_index FROM samples",
               "results": "SELECT job_id, item FROM results"}
    out, rows = {}, {}
    with psycopg.connect(dsn) as conn:
        for name, sql in queries.items():
            got = conn.execute(sql + " WHERE cell = %s", (cell,)).fetchall()
            rows[name] = len(got)
            out[name] = {r[0] if len(r) == 1 else tuple(r) for r in got}
    return out, rows


def differences(store: Path, dsn: str, cell: str) -> dict[str, dict[str, int]]:
    """Per table where the plant differs from the cell: how many records the plant misses, holds that the cell
    does not, and holds more than once. Empty when the plant has every record exactly once."""
    local = local_records(store)
    remote, rows = plant_records(dsn, cell)
    out = {}
    for table, keys in local.items():
        missing, extra, twice = len(keys - remote[table]), len(remote[table] - keys), rows[table] - len(remote[table])
        if missing or extra or twice:
            out[table] = {"missing": missing, "extra": extra, "duplicated": twice}
    return out
