"""Reading the plant database: what `cellctl fleet` prints and the fleet page shows, one query per question.

Every function takes an open psycopg connection and returns plain JSON-ready data. Times are ISO 8601 strings
in UTC. A cell's state is `offline` when it said so (it stopped), else what it last reported (idle, running,
paused).
"""

from __future__ import annotations

import math
from datetime import datetime, timezone
from typing import Any

import psycopg
from psycopg.rows import dict_row

from cellctl.errors import NotFound, Unreachable
from cellctl.fleet.secrets import scrub


def connect(dsn: str, timeout_s: int = 5) -> psycopg.Connection:
    """A connection to the plant database; Unreachable, with the DSN's password taken out of the reason (libpq
    quotes a malformed DSN back in its message), if there is none."""
    try:
        return psycopg.connect(dsn, connect_timeout=timeout_s)
    except (psycopg.Error, OSError) as exc:
        raise Unreachable("the plant database cannot be reached: "
                          + " ".join(scrub(str(exc).strip() or type(exc).__name__, dsn).split())) from None


def _iso(t: datetime | None) -> str | None:
    return t.astimezone(timezone.utc).isoformat() if t is not None else None


def _rows(conn: psycopg.Connection, sql: str, args: tuple = ()) -> list[dict[str, Any]]:
    with conn.cursor(row_factory=dict_row) as cur:
        cur.execute(sql, args)
        return cur.fetchall()


def _where_cell(cell: str | None, column: str = "cell") -> tuple[str, tuple]:
    return (f" WHERE {column} = %s", (cell,)) if cell else ("", ())


def known_cell(conn: psycopg.Connection, cell: str | None) -> None:
    """NotFound naming the cells there are, for a --cell the plant database does not know."""
    if cell is None:
        return
    names = [r["name"] for r in _rows(conn, "SELECT name FROM cells ORDER BY name")]
    if cell not in names:
        raise NotFound(f"cell: {cell!r} is not in the plant database (cells: {', '.join(names) or 'none yet'})")


def verification_mean_um(result: dict) -> float | None:
    value = ((result.get("stats") or {}).get("verification") or {}).get("mean_um")
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def active_calibrations(conn: psycopg.Connection, cell: str | None = None) -> dict[str, dict[str, dict]]:
    """Per cell, per target: the active version, its verification mean (µm) and its health (unchecked, ok, drift:
    from the last check of that very version)."""
    where, args = _where_cell(cell, "c.cell")
    rows = _rows(conn, f"""
        SELECT c.cell, c.target, c.id, c.version, c.routine, c.created, c.result,
               (SELECT (h.targets -> c.target ->> 'drifted')::boolean FROM health_checks h
                 WHERE h.cell = c.cell AND (h.targets -> c.target ->> 'calibration_id')::bigint = c.id
                 ORDER BY h.id DESC LIMIT 1) AS drifted
          FROM calibrations c {where + (' AND' if where else ' WHERE')} c.active
         ORDER BY c.cell, c.target""", args)
    out: dict[str, dict[str, dict]] = {}
    for r in rows:
        out.setdefault(r["cell"], {})[r["target"]] = {
            "id": r["id"], "version": r["version"], "routine": r["routine"], "created": _iso(r["created"]),
            "verification_mean_um": verification_mean_um(r["result"]),
            "health": "unchecked" if r["drifted"] is None else "drift" if r["drifted"] else "ok"}
    return out


def status(conn: psycopg.Connection, cell: str | None = None) -> dict:
    """`{"cells": [{name, state, last_seen, live_job, calibrations: {target: {version, verification_mean_um,
    health}}, ...}]}`."""
    known_cell(conn, cell)
    where, args = _where_cell(cell, "name")
    cals = active_calibrations(conn, cell)
    cells = []
    for r in _rows(conn, f"SELECT * FROM cells{where} ORDER BY name", args):
        cells.append({"name": r["name"], "state": "offline" if r["state"] == "offline" else r["cell_state"],
                      "last_seen": _iso(r["last_seen"]), "live_job": r["live_job"],
                      "calibrations": {t: {k: c[k] for k in ("version", "verification_mean_um", "health")}
                                       for t, c in cals.get(r["name"], {}).items()},
                      "description": r["description"], "software_revision": r["software_revision"],
                      "api_url": r["api_url"]})
    return {"cells": cells}


def jobs(conn: psycopg.Connection, cell: str | None = None, limit: int = 1000) -> dict:
    """`{"jobs": [{cell, id, routine, state, samples, reason, created, updated}]}`, newest first."""
    known_cell(conn, cell)
    where, args = _where_cell(cell, "j.cell")
    rows = _rows(conn, f"""
        SELECT j.cell, j.id, j.routine, j.state, j.reason, j.created, j.updated,
               (SELECT COUNT(*) FROM samples s WHERE s.cell = j.cell AND s.job_id = j.id) AS samples
          FROM jobs j{where} ORDER BY j.updated DESC, j.cell, j.id DESC LIMIT %s""", args + (int(limit),))
    return {"jobs": [dict(r, created=_iso(r["created"]), updated=_iso(r["updated"])) for r in rows]}


def calibrations(conn: psycopg.Connection, cell: str | None = None, target: str | None = None) -> dict:
    """`{"calibrations": [{cell, id, target, routine, version, created, active, verification_mean_um,
    provenance}]}`, every version, oldest first."""
    known_cell(conn, cell)
    clauses, args = [], []
    for column, value in (("cell", cell), ("target", target)):
        if value:
            clauses.append(f"{column} = %s")
            args.append(value)
    where = " WHERE " + " AND ".join(clauses) if clauses else ""
    rows = _rows(conn, f"SELECT cell, id, target, routine, version, created, active, result FROM calibrations{where} "
                       "ORDER BY cell, target, version", tuple(args))
    return {"calibrations": [{"cell": r["cell"], "id": r["id"], "target": r["target"], "routine": r["routine"],
                              "version": r["version"], "created": _iso(r["created"]), "active": r["active"],
                              "verification_mean_um": verification_mean_um(r["result"]),
                              "provenance": r["result"].get("provenance")} for r in rows]}


def health(conn: psycopg.Connection, cell: str | None = None) -> dict:
    """`{"health": [{cell, target, version, verdict, last_check: {id, created, drifted, p_value, drift, action}}]}`
    for every active calibration."""
    known_cell(conn, cell)
    cals = active_calibrations(conn, cell)
    where, args = _where_cell(cell)
    last: dict[tuple[str, str], dict] = {}
    for r in _rows(conn, f"SELECT cell, id, created, targets FROM health_checks{where} ORDER BY id", args):
        for target, t in r["targets"].items():
            last[(r["cell"], target)] = {"id": r["id"], "created": _iso(r["created"]), **t}
    out = []
    for name in sorted(cals):
        for target, c in sorted(cals[name].items()):
            out.append({"cell": name, "target": target, "version": c["version"], "verdict": c["health"],
                        "last_check": last.get((name, target))})
    return {"health": out}


def trend(conn: psycopg.Connection) -> dict:
    """Per target, per cell, over time: each version's verification mean (µm), and each check's drift (µm, the
    size of the estimated shift) with its verdict: what the fleet page plots. Each cell's series in the order the
    cell made them (its ids), not by their stamps: a step of the cell's wall clock must not reorder them."""
    out: dict[str, dict[str, dict[str, list]]] = {}
    # only the figure, not the whole result: the page asks every few seconds
    for r in _rows(conn, "SELECT cell, target, version, created, result -> 'stats' -> 'verification' -> 'mean_um' "
                         "AS mean_um FROM calibrations ORDER BY cell, id"):
        mean = r["mean_um"] if isinstance(r["mean_um"], (int, float)) and math.isfinite(r["mean_um"]) else None
        if mean is not None:
            out.setdefault(r["target"], {}).setdefault(r["cell"], {"calibrations": [], "checks": []})[
                "calibrations"].append({"t": _iso(r["created"]), "version": r["version"], "mean_um": mean})
    for r in _rows(conn, "SELECT cell, created, targets FROM health_checks ORDER BY cell, id"):
        for target, t in r["targets"].items():
            d = t.get("drift") or {}
            if isinstance(d.get("dx_um"), (int, float)) and isinstance(d.get("dy_um"), (int, float)):
                out.setdefault(target, {}).setdefault(r["cell"], {"calibrations": [], "checks": []})[
                    "checks"].append({"t": _iso(r["created"]), "drift_um": math.hypot(d["dx_um"], d["dy_um"]),
                                      "drifted": bool(t.get("drifted")), "calibration_id": t.get("calibration_id")})
    return {"targets": out}


def last_ids(conn: psycopg.Connection, cell: str) -> dict[str, int]:
    """The highest job, job state change and audit number the plant holds of a cell: a replaced cell PC numbers
    on from there."""
    return {local: conn.execute(f"SELECT COALESCE(MAX(id), 0) FROM {table} WHERE cell = %s", (cell,)).fetchone()[0]
            for local, table in (("jobs", "jobs"), ("job_events", "job_states"), ("audit", "audit"))}


def restore_records(conn: psycopg.Connection, cell: str) -> tuple[list[dict], list[dict]]:
    """A cell's calibration versions (with their samples) and checks, as its outbox sent them: for a restore."""
    known_cell(conn, cell)
    cals = _rows(conn, "SELECT id, target, routine, version, created, active, cell_file, result, samples "
                       "FROM calibrations WHERE cell = %s ORDER BY id", (cell,))
    checks = _rows(conn, "SELECT id, created, verdict, targets FROM health_checks WHERE cell = %s ORDER BY id",
                   (cell,))
    for c in cals:
        c["created"] = c["created"].strftime("%Y-%m-%dT%H:%M:%S%z")
    for c in checks:
        c["created"] = c["created"].strftime("%Y-%m-%dT%H:%M:%S%z")
    return cals, checks
