"""The store's integrity, its backups and their restore.

- `check_store`: at start-up, `PRAGMA quick_check` of each SQLite file of the store (and a job database that is
  missing beside run folders). A store that fails is refused with StoreCorrupt, which names the file, the last
  good backup and the command that restores it: the daemon never serves from a store it cannot trust.
- `backup`: each database through SQLite's online backup API (a consistent snapshot, taken beside a running
  daemon as well as without one), then the rest of the store (run folders, calibration samples, token,
  certificates). The databases are copied first: the folders copied after are then at least as new as what
  the databases say of them, and a resumed job goes on from the samples its folder holds. A backup is written
  under a hidden name and renamed once complete, with its manifest (BACKUP_MANIFEST): a folder named
  `cellctl-backup-*` is a whole one.
- `restore`: refused while a process owns the store. The backup is copied and checked beside the store, then
  swapped with it in one rename (renameat2 RENAME_EXCHANGE): a crash leaves the old store or the restored one,
  never half of each. The store it replaced is kept beside it (`<store>.replaced-<time>`).

The plant database's restore (`cellctl fleet restore`) stays the way to rebuild a replaced PC's calibrations.
"""

from __future__ import annotations

import ctypes
import errno
import hashlib
import json
import os
import shutil
import sqlite3
import time
from datetime import datetime, timezone
from pathlib import Path

from cellctl.errors import InsufficientStorage, InvalidRequest, ServiceError

DATABASES = ("daemon.sqlite", "calibrations.sqlite")  # the job store's and the calibration store's files
BACKUP_PREFIX = "cellctl-backup-"
BACKUP_MANIFEST = "backup.json"
# what a backup leaves out: the owner's lock and URLs, the disk reserve, SQLite's side files (the backup API
# copies what they hold), half-written temporary files
_LEFT_OUT = {"owner.lock", "daemon.url", "opcua.url", ".disk-reserve"}
_LEFT_OUT_SUFFIXES = ("-wal", "-shm", "-journal", ".tmp")


class StoreCorrupt(ServiceError):
    """A store file fails its integrity check: the daemon does not start on it."""

    status = 503


def default_backups(store: Path) -> Path:
    """Where backups go unless told: beside the store (not in it), so that a lost store folder leaves them."""
    store = Path(store)
    return store.with_name(f"{store.name}-backups")


# -- integrity ---------------------------------------------------------------------------------------------------

def quick_check(path: Path) -> str | None:
    """None when `path` passes `PRAGMA quick_check`, else what SQLite found (the first few problems). Opened as
    the stores open it (not read-only): a WAL left by a crash is recovered, as the daemon would, before the check."""
    if not Path(path).is_file():
        return "the file is missing"
    try:
        db = sqlite3.connect(path, timeout=30)
        try:
            rows = [r[0] for r in db.execute("PRAGMA quick_check(5)")]
        finally:
            db.close()
    except sqlite3.OperationalError as exc:
        if "unable to open" in str(exc) or "readonly" in str(exc):  # unreadable is not corrupt: say which it is
            raise InvalidRequest(f"{path}: this user cannot open it ({exc}); check the store as the daemon's "
                                 "user") from None
        return str(exc)
    except sqlite3.DatabaseError as exc:  # "file is not a database", "database disk image is malformed", ...
        return str(exc)
    return None if rows == ["ok"] else "; ".join(rows)


def check_store(store: Path, backups: Path | None = None, restore_hint: str = "") -> None:
    """StoreCorrupt naming the file, the last good backup and how to restore it, when a database of the store
    fails its quick check, or the job database is gone while run folders remain (its jobs would be lost and their
    numbers reused); else nothing. `restore_hint`: the options that name the store in the restore command."""
    store = Path(store)
    problem = None
    for name in DATABASES:
        path = store / name
        if path.exists():
            found = quick_check(path)
            if found:
                problem = f"{path} fails SQLite's integrity check ({found})"
                break
    if problem is None and not (store / DATABASES[0]).exists() and any((store / "jobs").glob("[0-9]*")):
        problem = f"{store / DATABASES[0]} is missing, while {store / 'jobs'} holds run folders"
    backups = Path(backups) if backups else default_backups(store)
    lost = problem is None and not any((store / name).exists() for name in DATABASES)
    if lost and backups_in(backups):  # an empty store beside its backups: lost (or a wrong store_dir), not new
        problem = (f"{store} holds no store (no {' or '.join(DATABASES)}), while {backups} holds backups of it "
                   f"(to start the cell empty on purpose, move {backups} aside)")
    if problem is None:
        return
    good = last_good_backup(backups)
    if good is None:
        what = (f"no good backup is in {backups}; rebuild the calibrations from the plant database into a new "
                "store (cellctl fleet restore --cell NAME --config CELL_FILE --store NEW_DIR, then point the cell "
                "file's store_dir at it), or move the store aside to start empty")
    else:
        taken = read_manifest(good).get("taken", "?")
        what = (f"the last good backup is {good} (taken {taken}); restore it with: "
                f"cellctl store restore {good}{restore_hint}")
    raise StoreCorrupt(f"the store cannot be trusted: {problem}. Nothing is served or run from it; {what}")


# -- backups -----------------------------------------------------------------------------------------------------

def backups_in(folder: Path) -> list[Path]:
    """The complete backups in `folder`, oldest first (their names sort by the time they were taken)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.name.startswith(BACKUP_PREFIX) and (p / BACKUP_MANIFEST).exists())


def last_good_backup(folder: Path) -> Path | None:
    """The newest complete backup whose databases pass their quick check."""
    for candidate in reversed(backups_in(folder)):
        try:
            verify(candidate)
        except InvalidRequest:
            continue
        return candidate
    return None


def read_manifest(backup_dir: Path) -> dict:
    try:
        return json.loads((Path(backup_dir) / BACKUP_MANIFEST).read_text())
    except (OSError, ValueError) as exc:
        raise InvalidRequest(f"{backup_dir} is not a complete cellctl backup (its {BACKUP_MANIFEST} cannot be "
                             f"read: {exc}); backups are the cellctl-backup-* folders `cellctl store backup` "
                             "writes") from None


def backup(store: Path, to: Path | None = None, cell: str = "", keep: int | None = None,
           min_free_mb: float = 0.0) -> Path:
    """A backup of `store` in a new folder of `to` (default: default_backups); `keep`: then only the newest
    `keep` backups there are kept. Refused (InsufficientStorage) when the copy would leave less than
    `min_free_mb` free where it goes: a backup on the store's disk must not fill it under a running job.
    Returns the backup's folder."""
    store = Path(store)
    to = Path(to) if to else default_backups(store)
    if not (store / DATABASES[0]).exists() and not (store / DATABASES[1]).exists():
        raise InvalidRequest(f"{store} holds no cellctl store (no {' or '.join(DATABASES)}): nothing to back up")
    to.mkdir(parents=True, exist_ok=True)
    _require_room(store, to, min_free_mb)
    taken = datetime.now(timezone.utc)
    name = BACKUP_PREFIX + taken.strftime("%Y%m%dT%H%M%S.%fZ")
    partial = to / f".{name}.partial"
    partial.mkdir(mode=0o700)  # it holds the token and keys
    try:
        databases = {}
        for db_name in DATABASES:  # first: the folders copied after are at least as new as the databases
            if (store / db_name).exists():
                databases[db_name] = _snapshot(store / db_name, partial / db_name)
        files, size = _copy_files(store, partial, skip=to.resolve())
        manifest = {"format": 1, "cell": cell, "store": str(store.resolve()), "taken": taken.isoformat(),
                    "databases": databases, "files": files, "bytes": size}
        (partial / BACKUP_MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
        _fsync_tree(partial)
        os.rename(partial, to / name)  # complete, or not there at all
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if keep:
        prune(to, keep)
    return to / name


def _require_room(store: Path, to: Path, min_free_mb: float) -> None:
    from cellctl.stores.disk_space import MB, RESERVE_FILE, free_bytes, tree_size

    inside = to.resolve().is_relative_to(store.resolve())  # earlier backups inside the store are not copied
    need = tree_size(store) - tree_size(store / RESERVE_FILE) - (tree_size(to) if inside else 0)
    free = free_bytes(to)
    if free - need < min_free_mb * MB:
        raise InsufficientStorage(f"a backup of {store} ({need / MB:.1f} MB) into {to} is refused: {to} has "
                                  f"{free / MB:.1f} MB free, and {min_free_mb:g} MB are to stay free "
                                  "(store.min_free_mb); back up to another disk (--to DIR), or free space there")


def _snapshot(source: Path, target: Path) -> dict:
    """One database through the online backup API (all pages in one step: one read transaction, so a consistent
    snapshot while the daemon writes), checked, with its size and hash."""
    src = sqlite3.connect(f"file:{source}?mode=ro", uri=True, timeout=30)
    dst = sqlite3.connect(target)
    try:
        src.backup(dst)
        dst.execute("PRAGMA journal_mode=DELETE")  # a backup read later makes no -wal/-shm beside it
    finally:
        dst.close()
        src.close()
    problem = quick_check(target)
    if problem:
        raise StoreCorrupt(f"{source} fails SQLite's integrity check ({problem}): it is not backed up; restore "
                           "an earlier backup (cellctl store restore)")
    return {"bytes": target.stat().st_size, "sha256": _sha256(target)}


def _copy_files(store: Path, into: Path, skip: Path) -> tuple[int, int]:
    """Copy everything else of the store (modes kept); the number of files and their bytes."""
    count = size = 0
    for root, dirs, names in os.walk(store):
        here = Path(root)
        dirs[:] = sorted(d for d in dirs if (here / d).resolve() != skip)
        rel = here.relative_to(store)
        (into / rel).mkdir(exist_ok=True)
        if rel != Path("."):  # the backup's own folder stays 0700
            shutil.copymode(here, into / rel)
        for name in names:
            if rel == Path(".") and (name in DATABASES or name in _LEFT_OUT):
                continue
            if name.endswith(_LEFT_OUT_SUFFIXES) or name.startswith(".pending-"):
                continue
            try:
                shutil.copy2(here / name, into / rel / name)  # samples.csv as far as written: a cut line is dropped
            except FileNotFoundError:  # replaced or removed meanwhile (a temporary file renamed into place)
                continue
            count += 1
            size += (into / rel / name).stat().st_size
    return count, size


def prune(folder: Path, keep: int) -> list[Path]:
    """Delete all but the newest `keep` complete backups in `folder`, and what a backup cut short (a crash, a
    full disk) left there over a day ago (a younger one may still be being written); the deleted ones."""
    old = backups_in(folder)[:-keep] if keep > 0 else []
    old += [p for p in Path(folder).glob(f".{BACKUP_PREFIX}*.partial") if time.time() - p.stat().st_mtime > 86400]
    for path in old:
        shutil.rmtree(path)
    return old


def verify(backup_dir: Path) -> dict:
    """The backup's manifest, once its databases are there, whole (size and hash) and pass their quick check;
    else InvalidRequest naming what is wrong."""
    manifest = read_manifest(backup_dir)
    for name, expected in manifest.get("databases", {}).items():
        path = Path(backup_dir) / name
        if not path.exists() or path.stat().st_size != expected["bytes"] or _sha256(path) != expected["sha256"]:
            raise InvalidRequest(f"{path} is missing or changed since the backup was taken: it cannot be restored")
        problem = quick_check(path)
        if problem:
            raise InvalidRequest(f"{path} fails SQLite's integrity check ({problem}): it cannot be restored")
    return manifest


# -- restore -----------------------------------------------------------------------------------------------------

def restore(backup_dir: Path, store: Path) -> Path | None:
    """Put the backup in place of `store` (whose owner the caller holds: see cellctl.startup.ownership); returns
    where the replaced store was kept (None when there was none). Job numbers go on after the replaced store's,
    where it can still be read: a job made after the backup keeps its number, here and in the plant database."""
    backup_dir, store = Path(backup_dir), Path(store)
    verify(backup_dir)
    staging = store.with_name(f".{store.name}.restoring-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    replacing = _holds_a_store(store)
    try:
        shutil.copytree(backup_dir, staging, ignore=shutil.ignore_patterns(BACKUP_MANIFEST, "*-wal", "*-shm"))
        shutil.copy2(backup_dir / BACKUP_MANIFEST, staging / "restored-from.json")
        _continue_numbers(store / DATABASES[0], staging / DATABASES[0])
        if store.is_dir():
            shutil.copymode(store, staging)  # the store's folder keeps who may read it
        _fsync_tree(staging)
        if replacing:
            _exchange(staging, store)  # one step: the old store or the restored one, never half of each
        else:
            shutil.rmtree(store, ignore_errors=True)  # a lost store: at most its empty folder and lock file are left
            os.rename(staging, store)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)  # only the copy: the store is as it was
        raise
    if not replacing:
        return None
    # the staging name now holds the replaced store: kept, under a name that says what it is
    kept = store.with_name(f"{store.name}.replaced-{datetime.now(timezone.utc):%Y%m%dT%H%M%SZ}")
    try:
        os.rename(staging, kept)
    except OSError:  # restored all the same: the replaced store stays under the staging name
        return staging
    return kept


def _holds_a_store(store: Path) -> bool:
    return store.is_dir() and any(p.name != "owner.lock" for p in store.iterdir())


def _continue_numbers(old_db: Path, new_db: Path) -> None:
    """Number the restored store's jobs, state changes and audit entries after the replaced store's highest."""
    if not old_db.exists() or not new_db.exists():
        return
    try:
        old = sqlite3.connect(f"file:{old_db}?mode=ro", uri=True)
        try:
            seqs = dict(old.execute("SELECT name, seq FROM sqlite_sequence"))
        finally:
            old.close()
    except sqlite3.DatabaseError:  # the replaced store is the corrupt one: its numbers are not known
        return
    new = sqlite3.connect(new_db)
    try:
        with new:
            for name, seq in seqs.items():
                new.execute("UPDATE sqlite_sequence SET seq = MAX(seq, ?) WHERE name = ?", (seq, name))
    finally:
        new.close()


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> None:
    """Swap two paths atomically (Linux renameat2 RENAME_EXCHANGE)."""
    libc = ctypes.CDLL(None, use_errno=True)
    renameat2 = getattr(libc, "renameat2", None)
    if renameat2 is None:
        raise OSError(errno.ENOSYS, "this system cannot swap two folders in one step (no renameat2)")
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) != 0:
        code = ctypes.get_errno()
        raise OSError(code, f"cannot swap {a} and {b}: {os.strerror(code)}")


# -- helpers -----------------------------------------------------------------------------------------------------

def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _fsync_tree(folder: Path) -> None:
    """Everything under `folder` on the disk before it is renamed into place (a power cut keeps it whole)."""
    for root, _dirs, names in os.walk(folder):
        for name in [*names, "."]:
            fd = os.open(os.path.join(root, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


def age_s(backup_dir: Path) -> float:
    """How long ago (wall clock, seconds) the backup was taken; 0 if its manifest does not say."""
    try:
        taken = datetime.fromisoformat(read_manifest(backup_dir)["taken"])
    except (InvalidRequest, KeyError, ValueError):
        return 0.0
    return max(0.0, time.time() - taken.timestamp())


# -- on a schedule -----------------------------------------------------------------------------------------------

class BackupSchedule:
    """The daemon's backups every `every_h` hours (cell file `store: {backup: ...}`), the newest `keep` kept.

    Intervals run on the monotonic clock (a wall-clock step neither skips a backup nor takes two); only the first
    wait reads the last backup's time, so that a restarted daemon does not take one at each start."""

    def __init__(self, settings, store: Path, cell: str, min_free_mb: float = 0.0):
        import logging
        import threading

        self.min_free_mb = min_free_mb  # what the store's disk keeps free (store.min_free_mb)
        self.every_s = settings.every_h * 3600.0
        self.keep = settings.keep
        self.to = settings.folder(store)
        self.store, self.cell = Path(store), cell
        self.log = logging.getLogger("cellctl.backup")
        self.last: Path | None = None  # the newest backup this daemon took
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="store-backup", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30)

    def first_wait_s(self) -> float:
        taken = backups_in(self.to)
        return min(self.every_s, max(0.0, self.every_s - age_s(taken[-1]))) if taken else 0.0

    def _run(self) -> None:
        wait = self.first_wait_s()
        while not self._stop.wait(wait):
            started = time.monotonic()
            try:
                self.last = backup(self.store, self.to, self.cell, keep=self.keep, min_free_mb=self.min_free_mb)
                self.log.info("store backed up", extra={"backup": str(self.last), "keep": self.keep})
            except Exception as exc:  # noqa: BLE001 - a failed backup (a full disk) is logged; the next one tries again
                self.log.error("store backup failed", extra={"to": str(self.to), "error": f"{type(exc).__name__}: "
                                                                                           f"{exc}"})
            wait = max(0.0, self.every_s - (time.monotonic() - started))
