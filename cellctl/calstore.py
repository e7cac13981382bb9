"""Versioned calibrations: every result kept with its samples, the cell file and the time.

One SQLite database (WAL) per store directory; the samples of each calibration are
copied beside it. Each target (a camera such as `cam1`, a tool such as `nozzle`)
has at most one active calibration; older versions stay, and any can be made
active again.
"""

from __future__ import annotations

import json
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from .errors import NotFound
from .store import to_jsonable, write_atomic

SCHEMA = """
CREATE TABLE IF NOT EXISTS calibrations (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    target TEXT NOT NULL,
    routine TEXT NOT NULL,
    version INTEGER NOT NULL,
    created TEXT NOT NULL,
    active INTEGER NOT NULL DEFAULT 0,
    cell TEXT NOT NULL,
    cell_file TEXT NOT NULL,
    run_dir TEXT,
    result TEXT NOT NULL,
    UNIQUE (target, version)
);
"""


class CalibrationStoreError(NotFound, LookupError):
    pass


@dataclass(frozen=True)
class Calibration:
    id: int
    target: str
    routine: str
    version: int
    created: str
    active: bool
    cell: str
    run_dir: str | None
    result: dict

    @property
    def model(self) -> dict:
        return self.result["model"]


class CalibrationStore:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path / "calibrations.sqlite", isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        self._db.close()

    def save(self, target: str, result: dict, cell_text: str, run_dir: str | Path | None = None,
             activate: bool = True) -> Calibration:
        """Store a new version for `target` (and its samples), active unless told otherwise."""
        created = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        body = json.dumps(to_jsonable(result), allow_nan=False)
        with self._transaction() as db:
            version = db.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM calibrations WHERE target = ?",
                                 (target,)).fetchone()[0]
            if activate:
                db.execute("UPDATE calibrations SET active = 0 WHERE target = ?", (target,))
            cur = db.execute(
                "INSERT INTO calibrations (target, routine, version, created, active, cell, cell_file, run_dir, result)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (target, result["routine"], version, created, int(activate), result.get("cell", ""), cell_text,
                 str(run_dir) if run_dir else None, body))
            cal_id = cur.lastrowid
        if run_dir and (Path(run_dir) / "samples.csv").exists():
            folder = self.path / "samples"
            folder.mkdir(exist_ok=True)
            write_atomic(folder / f"{cal_id}.csv", (Path(run_dir) / "samples.csv").read_bytes())
        return self.get(cal_id)

    def get(self, cal_id: int) -> Calibration:
        row = self._db.execute(f"SELECT {_COLUMNS} FROM calibrations WHERE id = ?", (int(cal_id),)).fetchone()
        if row is None:
            raise CalibrationStoreError(f"no calibration with id {cal_id} in {self.path}")
        return _calibration(row)

    def active(self, target: str) -> Calibration | None:
        row = self._db.execute(f"SELECT {_COLUMNS} FROM calibrations WHERE target = ? AND active = 1",
                               (target,)).fetchone()
        return _calibration(row) if row else None

    def active_models(self) -> dict[str, dict]:
        rows = self._db.execute(f"SELECT {_COLUMNS} FROM calibrations WHERE active = 1").fetchall()
        return {c.target: dict(c.model, calibration_id=c.id) for c in map(_calibration, rows)}

    def list(self, target: str | None = None) -> list[Calibration]:
        query = f"SELECT {_COLUMNS} FROM calibrations" + (" WHERE target = ?" if target else "") + " ORDER BY id"
        return [_calibration(r) for r in self._db.execute(query, (target,) if target else ())]

    def activate(self, cal_id: int) -> Calibration:
        cal = self.get(cal_id)
        with self._transaction() as db:
            db.execute("UPDATE calibrations SET active = 0 WHERE target = ?", (cal.target,))
            db.execute("UPDATE calibrations SET active = 1 WHERE id = ?", (cal.id,))
        return self.get(cal_id)

    def samples_path(self, cal_id: int) -> Path | None:
        path = self.path / "samples" / f"{int(cal_id)}.csv"
        return path if path.exists() else None

    def _transaction(self):
        return _Transaction(self._db)


class _Transaction:
    def __init__(self, db):
        self.db = db

    def __enter__(self):
        self.db.execute("BEGIN IMMEDIATE")
        return self.db

    def __exit__(self, exc_type, *exc):
        self.db.execute("ROLLBACK" if exc_type else "COMMIT")
        return False


_COLUMNS = "id, target, routine, version, created, active, cell, run_dir, result"


def _calibration(row) -> Calibration:
    cal_id, target, routine, version, created, active, cell, run_dir, result = row
    return Calibration(cal_id, target, routine, version, created, bool(active), cell, run_dir, json.loads(result))
