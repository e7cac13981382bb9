"""Versioned calibrations: every result kept with its samples, the cell file and the time.

One SQLite database (WAL) per store directory; the samples of each calibration are
copied beside it. Each target (a camera such as `cam1`, a tool such as `nozzle`)
has at most one active calibration; older versions stay, and any can be made
active again.
"""

from __future__ import annotations

import json
import os
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from cellctl.errors import InvalidRequest, NotFound
from cellctl.stores import outbox
from cellctl.stores.run_folder import to_jsonable, write_atomic

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
CREATE TABLE IF NOT EXISTS checks (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    created TEXT NOT NULL,
    verdict TEXT NOT NULL,
    run_dir TEXT,
    result TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS check_targets (
    check_id INTEGER NOT NULL REFERENCES checks (id),
    target TEXT NOT NULL,
    calibration_id INTEGER REFERENCES calibrations (id),
    drifted INTEGER NOT NULL,
    p_value REAL,
    drift TEXT NOT NULL,
    action TEXT NOT NULL,
    PRIMARY KEY (check_id, target)
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
    """`replicate`: every new version, activation and check is also written to the outbox, in its transaction
    (cellctl.stores.outbox)."""

    FILE = "calibrations.sqlite"

    def __init__(self, path: str | Path, replicate: bool = False):
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        self.outbox = outbox.Recorder(replicate)
        self._db = sqlite3.connect(self.path / self.FILE, isolation_level=None, check_same_thread=False, timeout=30)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")  # a calibration reported stored survives a power cut
        self._db.executescript(SCHEMA)
        outbox.create(self._db)

    def close(self) -> None:
        self._db.close()

    def save(self, target: str, result: dict, cell_text: str, run_dir: str | Path | None = None,
             activate: bool = True) -> Calibration:
        """Store a new version for `target` (and its samples), active unless told otherwise. The samples' copy is
        written before the version is committed (under a temporary name, renamed after), so a full disk leaves no
        version without its samples."""
        created = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        body = json.dumps(to_jsonable(result), allow_nan=False)
        source = Path(run_dir) / "samples.csv" if run_dir else None
        samples = source.read_bytes() if source is not None and source.exists() else None
        pending = self.path / "samples" / f".pending-{os.getpid()}-{time.time_ns()}.csv"
        if samples is not None:
            pending.parent.mkdir(exist_ok=True)
            write_atomic(pending, samples)
        try:
            cal_id = self._insert(target, result, body, created, cell_text, run_dir, activate, samples)
        except BaseException:
            pending.unlink(missing_ok=True)
            raise
        if samples is not None:
            os.replace(pending, self.path / "samples" / f"{cal_id}.csv")  # a rename: it needs no new space
        return self.get(cal_id)

    def saved_from(self, target: str, run_dir: str | Path) -> Calibration | None:
        """The version of `target` a run folder stored already, if any (a resumed run whose end failed part way,
        e.g. on a full disk, stores it once)."""
        row = self._db.execute("SELECT id FROM calibrations WHERE target = ? AND run_dir = ? ORDER BY id LIMIT 1",
                               (target, str(run_dir))).fetchone()
        return self.get(row[0]) if row is not None else None

    def check_from(self, run_dir: str | Path) -> int | None:
        """The check a run folder kept already, if any (as `saved_from`)."""
        row = self._db.execute("SELECT id FROM checks WHERE run_dir = ? ORDER BY id LIMIT 1",
                               (str(run_dir),)).fetchone()
        return row[0] if row is not None else None

    def _insert(self, target: str, result: dict, body: str, created: str, cell_text: str, run_dir, activate: bool,
                samples: bytes | None) -> int:
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
            self.outbox.record(db, "calibration", f"calibration/{cal_id}", {
                "id": cal_id, "target": target, "routine": result["routine"], "version": version, "created": created,
                "active": bool(activate), "cell_file": cell_text, "result": json.loads(body),
                "samples": samples.decode() if samples is not None else None})
        self.outbox.committed()
        return cal_id

    def _keep_samples(self, cal_id: int, samples: bytes) -> None:
        folder = self.path / "samples"
        folder.mkdir(exist_ok=True)
        write_atomic(folder / f"{cal_id}.csv", samples)

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
            self.outbox.record(db, "activation", f"activation/{cal.id}", {"id": cal.id, "target": cal.target})
        self.outbox.committed()
        return self.get(cal_id)

    def deactivate(self, cal_id: int) -> Calibration:
        """Take this version out of use: its target then has no active version (an `arm` calibration off: moves go
        as the controller's own table says). Replicated as an activation of nothing for the target."""
        cal = self.get(cal_id)
        with self._transaction() as db:
            db.execute("UPDATE calibrations SET active = 0 WHERE id = ?", (cal.id,))
            if cal.active:
                self.outbox.record(db, "activation", f"deactivation/{cal.id}/{time.time_ns()}",
                                   {"id": None, "target": cal.target})
        self.outbox.committed()
        return self.get(cal_id)

    # -- health: every check, kept with the calibrations it checked ------------------------------
    def save_check(self, result: dict, run_dir: str | Path | None = None) -> int:
        """Keep a check's verdict, per target: the calibration checked, its drift estimate, p-value and action."""
        created = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        keep = {k: result.get(k) for k in ("verdict", "drifted", "checked", "updated", "actions", "cell_time_s", "seed")}
        keep["drift"], keep["test"] = result["stats"]["drift"], result["stats"]["test"]
        targets = {target: {"calibration_id": cal_id, "drifted": target in result["drifted"],
                            "p_value": result["stats"]["test"][target]["p_value"],
                            "drift": to_jsonable(result["stats"]["drift"][target]),
                            "action": result["actions"][target]}
                   for target, cal_id in result["checked"].items()}
        with self._transaction() as db:
            check_id = db.execute("INSERT INTO checks (created, verdict, run_dir, result) VALUES (?, ?, ?, ?)",
                                  (created, result["verdict"], str(run_dir) if run_dir else None,
                                   json.dumps(to_jsonable(keep), allow_nan=False))).lastrowid
            self._insert_targets(db, check_id, targets)
            self.outbox.record(db, "health_check", f"health_check/{check_id}",
                               {"id": check_id, "created": created, "verdict": result["verdict"], "targets": targets})
        self.outbox.committed()
        return check_id

    @staticmethod
    def _insert_targets(db, check_id: int, targets: dict[str, dict]) -> None:
        for target, t in targets.items():
            db.execute("INSERT INTO check_targets (check_id, target, calibration_id, drifted, p_value, drift, "
                       "action) VALUES (?, ?, ?, ?, ?, ?, ?)",
                       (check_id, target, t["calibration_id"], int(t["drifted"]), t["p_value"],
                        json.dumps(t["drift"], allow_nan=False), t["action"]))

    # -- a replaced cell PC: its versions and checks back from the plant database -------------------
    def restore(self, calibrations: list[dict], checks: list[dict]) -> int:
        """Put calibration versions (each as the outbox's calibration body, with `active`) and the checks of them
        (as health_check bodies) into this store, which must be empty, under their own ids, so that every
        reference (a touch-up's parent, a check's calibration) still holds. Not recorded for the plant again:
        it has them. Returns how many versions were restored."""
        with self._transaction() as db:
            if db.execute("SELECT COUNT(*) FROM calibrations").fetchone()[0]:
                raise InvalidRequest(f"{self.path} already holds calibrations: restore into an empty store "
                                     "(a new store folder), so nothing of this cell's is overwritten")
            for c in calibrations:
                db.execute("INSERT INTO calibrations (id, target, routine, version, created, active, cell, cell_file, "
                           "run_dir, result) VALUES (?, ?, ?, ?, ?, ?, ?, ?, NULL, ?)",
                           (c["id"], c["target"], c["routine"], c["version"], c["created"], int(c["active"]),
                            c["result"].get("cell", ""), c["cell_file"], json.dumps(c["result"], allow_nan=False)))
            for check in checks:
                keep = {"verdict": check["verdict"], "restored": True}
                db.execute("INSERT INTO checks (id, created, verdict, run_dir, result) VALUES (?, ?, ?, NULL, ?)",
                           (check["id"], check["created"], check["verdict"], json.dumps(keep)))
                self._insert_targets(db, check["id"], check["targets"])
        for c in calibrations:
            if c.get("samples") is not None:
                self._keep_samples(c["id"], c["samples"].encode())
        return len(calibrations)

    def checks(self, target: str | None = None, limit: int = 1000) -> list[dict]:
        """Per target and check, oldest first: when, the calibration checked, drifted, p-value, drift, action."""
        query = ("SELECT c.id, c.created, c.verdict, c.run_dir, t.target, t.calibration_id, t.drifted, t.p_value, "
                 "t.drift, t.action FROM check_targets t JOIN checks c ON c.id = t.check_id"
                 + (" WHERE t.target = ?" if target else "") + " ORDER BY c.id DESC LIMIT ?")
        rows = self._db.execute(query, ((target,) if target else ()) + (int(limit),)).fetchall()
        return [{"check": r[0], "created": r[1], "verdict": r[2], "run_dir": r[3], "target": r[4],
                 "calibration_id": r[5], "drifted": bool(r[6]), "p_value": r[7], "drift": json.loads(r[8]),
                 "action": r[9]} for r in reversed(rows)]

    def health(self) -> dict:
        """Per target with an active calibration: that version, its last check (if any) and every check of it."""
        history = {}
        for row in self.checks():
            history.setdefault(row["target"], []).append(row)
        out = {}
        for cal in sorted((c for c in self.list() if c.active), key=lambda c: c.target):
            checks = history.get(cal.target, [])
            own = [c for c in checks if c["calibration_id"] == cal.id]
            out[cal.target] = {"active": {"id": cal.id, "version": cal.version, "routine": cal.routine,
                                          "created": cal.created},
                               "last_check": checks[-1] if checks else None,
                               "verdict": ("unchecked" if not own else "drift" if own[-1]["drifted"] else "ok"),
                               "history": checks}
        return out

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
        try:
            self.db.execute("ROLLBACK" if exc_type else "COMMIT")
        except BaseException:  # a COMMIT that failed (the disk full) is rolled back: the connection stays usable
            if self.db.in_transaction:
                self.db.execute("ROLLBACK")
            raise
        return False


_COLUMNS = "id, target, routine, version, created, active, cell, run_dir, result"


def _calibration(row) -> Calibration:
    cal_id, target, routine, version, created, active, cell, run_dir, result = row
    return Calibration(cal_id, target, routine, version, created, bool(active), cell, run_dir, json.loads(result))
