"""The store's integrity check, backups and restore (cellctl/stores/backup.py), on real stores in a temp folder:
a backup beside an open writer holds what was committed; a corrupt page is found and named with the last good
backup; a restore is refused while the store is owned, swaps whole, and numbers new jobs after the replaced
store's; scheduled backups keep the newest N."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
from pathlib import Path

import pytest

from cellctl.cli import main
from cellctl.config import CellFileError, parse_cell_file
from cellctl.errors import InvalidRequest
from cellctl.startup.ownership import CellOwned, own_store
from cellctl.stores import backup as backups
from cellctl.stores.backup import BACKUP_MANIFEST, BackupSchedule, StoreCorrupt
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.jobs import DB_FILE, JobStore

from tests.support.wait import eventually

ROOT = Path(__file__).resolve().parents[2]


def make_store(store: Path, jobs: int = 3) -> JobStore:
    """A store with `jobs` jobs (each with a run folder and a few samples) and a calibration store; the job store
    is left open, as a daemon holds it."""
    calibrations = CalibrationStore(store)
    calibrations.close()
    job_store = JobStore(store / DB_FILE)
    for i in range(jobs):
        job = job_store.submit("virtual-grid", {"rows": 4, "note": "x" * 2000}, i, "test")
        folder = Path(job.run_dir)
        folder.mkdir(parents=True)
        (folder / "samples.csv").write_text("step,x_mm\n0,1.5\n1,2.5\n")
        job_store.audit("test", "unit", "submit", f"job/{job.id}", {"pad": "y" * 3000}, "ok")
    for name in ("owner.lock", "daemon.url", ".disk-reserve"):
        (store / name).write_text("left out\n")
    (store / "daemon.token").write_text("secret\n")
    os.chmod(store / "daemon.token", 0o600)
    return job_store


def corrupt_middle_page(path: Path) -> None:
    """Overwrite the page in the middle of a database file with garbage (a torn write of an SSD)."""
    page = 4096
    pages = path.stat().st_size // page
    assert pages >= 3, f"{path} is too small to corrupt its middle ({pages} pages)"
    with open(path, "r+b") as f:
        f.seek(pages // 2 * page)
        f.write(bytes([0xA5, 0x5A]) * (page // 2))


def job_ids(store: Path) -> list[int]:
    db = sqlite3.connect(store / DB_FILE)
    try:
        return [r[0] for r in db.execute("SELECT id FROM jobs ORDER BY id")]
    finally:
        db.close()


def test_a_backup_beside_an_open_writer_holds_what_was_committed(tmp_path):
    store = tmp_path / "store"
    open_store = make_store(store)
    try:
        assert (store / (DB_FILE + "-wal")).exists()  # the rows are still in the WAL: the backup API reads them
        made = backups.backup(store, tmp_path / "backups", cell="micro")
    finally:
        open_store.close()
    assert made.parent == tmp_path / "backups" and made.name.startswith("cellctl-backup-")
    manifest = json.loads((made / BACKUP_MANIFEST).read_text())
    assert set(manifest["databases"]) == {"daemon.sqlite", "calibrations.sqlite"} and manifest["cell"] == "micro"
    assert job_ids(made) == [1, 2, 3]
    assert (made / "jobs" / "000002" / "samples.csv").read_text() == "step,x_mm\n0,1.5\n1,2.5\n"
    assert (made / "daemon.token").stat().st_mode & 0o777 == 0o600 and made.stat().st_mode & 0o777 == 0o700
    for left_out in ("owner.lock", "daemon.url", ".disk-reserve", DB_FILE + "-wal", DB_FILE + "-shm"):
        assert not (made / left_out).exists(), left_out
    assert not [p for p in made.parent.iterdir() if p.name.startswith(".")]  # no partial backup left
    assert backups.verify(made) == manifest


def test_a_corrupt_page_is_refused_naming_the_file_the_last_good_backup_and_the_restore_command(tmp_path):
    store = tmp_path / "store"
    make_store(store, jobs=20).close()
    backups.check_store(store)  # a sound store passes
    good = backups.backup(store)  # into the default folder beside the store
    assert good.parent == tmp_path / "store-backups"
    corrupt_middle_page(store / DB_FILE)
    with pytest.raises(StoreCorrupt) as refused:
        backups.check_store(store, restore_hint=" --config cell.yaml")
    said = str(refused.value)
    assert str(store / DB_FILE) in said and "integrity check" in said
    assert f"cellctl store restore {good} --config cell.yaml" in said
    # the CLI says the same, exit 2
    assert main(["store", "check", "--store", str(store)]) == 2
    # a backup of a corrupt store is refused: it never hides the good ones
    with pytest.raises(StoreCorrupt):
        backups.backup(store)
    assert backups.backups_in(good.parent) == [good]


def test_with_no_good_backup_the_refusal_points_to_the_plant_database(tmp_path):
    store = tmp_path / "store"
    make_store(store, jobs=20).close()
    bad = backups.backup(store)
    corrupt_middle_page(bad / DB_FILE)  # the backup itself went bad: not "good"
    corrupt_middle_page(store / DB_FILE)
    with pytest.raises(StoreCorrupt, match="no good backup is in .*cellctl fleet restore"):
        backups.check_store(store)


def test_a_lost_job_database_beside_run_folders_is_refused(tmp_path):
    store = tmp_path / "store"
    make_store(store).close()
    (store / DB_FILE).unlink()
    with pytest.raises(StoreCorrupt, match="daemon.sqlite is missing, while .* holds run folders"):
        backups.check_store(store)


def test_restore_is_refused_while_the_store_is_owned_and_swaps_it_whole(tmp_path, capsys):
    store = tmp_path / "store"
    make_store(store).close()
    taken = backups.backup(store)
    later = JobStore(store / DB_FILE)  # two jobs made after the backup: their numbers stay taken
    later.submit("virtual-grid", {}, 7, "test")
    later.submit("virtual-grid", {}, 8, "test")
    later.close()
    with own_store(store, "cellctl serve --config cell.yaml"):
        with pytest.raises(CellOwned, match="stop it first"):
            with own_store(store, "cellctl store restore", verb=None):
                pass
        assert main(["store", "restore", str(taken), "--store", str(store)]) == 2
        assert "is owned by pid" in capsys.readouterr().err
    assert job_ids(store) == [1, 2, 3, 4, 5]  # the refusal changed nothing

    assert main(["store", "restore", str(taken), "--store", str(store)]) == 0
    assert job_ids(store) == [1, 2, 3]
    replaced = [p for p in tmp_path.iterdir() if p.name.startswith("store.replaced-")]
    assert len(replaced) == 1 and job_ids(replaced[0]) == [1, 2, 3, 4, 5]  # nothing thrown away
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".store.restoring")]
    assert json.loads((store / "restored-from.json").read_text())["taken"]
    again = JobStore(store / DB_FILE)
    try:
        assert again.submit("virtual-grid", {}, 9, "test").id == 6  # after the replaced store's, never reused
    finally:
        again.close()


def test_a_backup_that_changed_is_not_restored(tmp_path):
    store = tmp_path / "store"
    make_store(store).close()
    taken = backups.backup(store)
    with open(taken / DB_FILE, "r+b") as f:  # one byte flipped
        f.seek(200)
        byte = f.read(1)[0]
        f.seek(200)
        f.write(bytes([byte ^ 0xFF]))
    with pytest.raises(InvalidRequest, match="changed since the backup was taken"):
        backups.restore(taken, store)
    assert job_ids(store) == [1, 2, 3]
    with pytest.raises(InvalidRequest, match="not a complete cellctl backup"):
        backups.restore(tmp_path, store)


def test_a_lost_store_is_restored_in_its_place(tmp_path):
    store = tmp_path / "store"
    make_store(store).close()
    taken = backups.backup(store, tmp_path / "elsewhere")
    for path in sorted(store.rglob("*"), reverse=True):
        path.rmdir() if path.is_dir() else path.unlink()
    store.rmdir()
    assert main(["store", "restore", str(taken), "--store", str(store)]) == 0
    assert job_ids(store) == [1, 2, 3] and (store / "daemon.token").read_text() == "secret\n"


def test_scheduled_backups_keep_the_newest_n(tmp_path):
    store = tmp_path / "store"
    make_store(store, jobs=1).close()
    cell = parse_cell_file((ROOT / "config" / "sim-microcell.yaml").read_text()
                           + "\nstore:\n  backup: {every_h: 0.0001, keep: 2, to: " + str(tmp_path / "b") + "}\n")
    schedule = BackupSchedule(cell.store.backup, store, "micro")
    assert schedule.first_wait_s() == 0.0  # no backup yet: one at once
    taken: set[str] = set()
    schedule.start()
    try:
        def four_taken():
            if schedule.last is not None:
                taken.add(schedule.last.name)
            return len(taken) >= 4
        eventually(four_taken, timeout=60, what="four scheduled backups")
    finally:
        schedule.stop()
    assert len(backups.backups_in(tmp_path / "b")) == 2
    assert 0 < BackupSchedule(cell.store.backup, store, "micro").first_wait_s() <= 0.36  # the newest is recent


def test_the_cell_file_backup_section_is_checked():
    text = (ROOT / "config" / "sim-microcell.yaml").read_text()
    with pytest.raises(CellFileError, match="every_h"):
        parse_cell_file(text + "\nstore:\n  backup: {every_h: 0, keep: 3}\n")
    with pytest.raises(CellFileError, match="keep"):
        parse_cell_file(text + "\nstore:\n  backup: {every_h: 24, keep: 0}\n")
    with pytest.raises(CellFileError, match="often"):
        parse_cell_file(text + "\nstore:\n  backup: {every_h: 24, often: 1}\n")


def test_a_backup_that_would_eat_the_space_the_store_keeps_free_is_refused(tmp_path):
    from cellctl.errors import InsufficientStorage

    store = tmp_path / "store"
    make_store(store).close()
    with pytest.raises(InsufficientStorage, match=r"into .* is refused: .* MB free, and 1e\+07 MB are to stay free"):
        backups.backup(store, tmp_path / "b", min_free_mb=10_000_000)
    assert not list((tmp_path / "b").iterdir())  # nothing half-written


def test_prune_keeps_the_newest_and_clears_what_a_crash_left_long_ago(tmp_path):
    store = tmp_path / "store"
    make_store(store, jobs=1).close()
    made = [backups.backup(store, tmp_path / "b") for _ in range(3)]
    stale, fresh = tmp_path / "b" / ".cellctl-backup-1.partial", tmp_path / "b" / ".cellctl-backup-2.partial"
    stale.mkdir()
    fresh.mkdir()
    os.utime(stale, (0, 0))
    assert sorted(backups.prune(tmp_path / "b", 2)) == sorted([made[0], stale])
    assert backups.backups_in(tmp_path / "b") == made[1:] and fresh.exists()


def test_an_empty_store_beside_its_backups_is_refused_as_lost(tmp_path):
    store = tmp_path / "store"
    make_store(store).close()
    taken = backups.backup(store)
    shutil.rmtree(store)
    store.mkdir()  # as the daemon makes it at start
    with pytest.raises(StoreCorrupt, match=f"holds no store .*move {taken.parent} aside.*cellctl store restore {taken}"):
        backups.check_store(store)
    backups.check_store(tmp_path / "new")  # a new store, with no backups: nothing to refuse
