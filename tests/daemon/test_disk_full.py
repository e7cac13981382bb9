"""A full disk, for real: the store on a small tmpfs the test mounts, filled to the last byte by a ballast file
beside the store at one of three moments of a job (an image save, a sample write, the calibration store's write
at the job's end; and a step's record in the job database).

Each time: the job faults with DiskFull naming the filesystem and what fills it; every sample written before is
intact (against an uninterrupted run of the same seed); both SQLite stores pass `PRAGMA integrity_check`; the
daemon serves reads throughout and refuses new jobs, naming the free space and the floor; once the ballast is
deleted, ack + resume end the job with the uninterrupted run's samples and result, its calibration stored once;
and the outbox (a fleet whose sinks were never reached) holds every step's samples for the plant.

The moment is chosen by wrapping the store's own write (in-process daemon, FastAPI's TestClient): the failure is
the filesystem's ENOSPC (SQLite's SQLITE_FULL), not a simulated one. Needs root to mount; skipped, saying so,
where mounting is impossible.
"""

from __future__ import annotations

import csv
import errno
import io
import json
import logging
import os
import sqlite3
import subprocess
import threading
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml

from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.disk_space import RESERVE_FILE
from cellctl.stores.jobs import JobStore
from cellctl.stores.run_folder import RunFolder, csv_cell, read_samples_text

from tests.support.daemon import SEED, SMALL, wait_for, write_cell_file

pytestmark = pytest.mark.long  # run first: see conftest.py

FS_MB = 256  # the tmpfs: the job's 24 saved images fit, with the reserve file and the floor
MIN_FREE_MB = 24.0  # the floor: above the reserve file (8 MB), so a filled disk stays refused once it is freed
MEASURED = ("step", "set", "status", "camera", "frame_id", "cmd_x_mm", "cmd_y_mm", "x_mm", "y_mm", "u_px", "v_px",
            "diameter_px")


@pytest.fixture
def small_fs(tmp_path):
    """A FS_MB tmpfs mounted at tmp_path/fs for the test, unmounted after."""
    mount = tmp_path / "fs"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={FS_MB}m", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs for the store (needs root, or CAP_SYS_ADMIN): {done.stderr.strip()}")
    try:
        yield mount
    finally:
        if subprocess.run(["umount", str(mount)]).returncode != 0:
            subprocess.run(["umount", "-l", str(mount)], check=True)  # never left mounted


def cell_file(tmp_path: Path, mount: Path, min_free_mb: float = MIN_FREE_MB) -> Path:
    """The micro cell with its store on the tmpfs, in a fleet whose sink is never reached (the outbox keeps all)."""
    path = write_cell_file(tmp_path, realtime_factor=0.0)
    data = yaml.safe_load(path.read_text())
    data["store_dir"] = str(mount / "store")
    data["store"] = {"min_free_mb": min_free_mb}
    data["fleet"] = {"mqtt": {"host": "127.0.0.1", "port": 9, "topic_prefix": "plant/test"}}
    path.write_text(yaml.safe_dump(data))
    return path


@contextmanager
def daemon_on(path: Path, monkeypatch):
    """The daemon in this process, its replicator trying a sink that is not there, and a client of its HTTP API."""
    from fastapi.testclient import TestClient

    from cellctl.http.api import create_app
    from cellctl.startup.daemon import Daemon

    monkeypatch.delenv("CELLCTL_STORE", raising=False)  # the cell file's store_dir: on the small filesystem
    daemon = Daemon(path)
    daemon.start()
    daemon.start_fleet("http://127.0.0.1:9")
    try:
        app = create_app(daemon)
        yield daemon, app, TestClient(app, headers={"Authorization": f"Bearer {daemon.token}"})
    finally:
        daemon.stop("test over")


class Reader(threading.Thread):
    """Reads the cell, the job and the metrics over and over until stopped; every answer's status is kept."""

    def __init__(self, app, job_id: int):
        from fastapi.testclient import TestClient

        super().__init__(daemon=True)
        self.client, self.job_id = TestClient(app), job_id
        self.statuses: list[tuple[str, int]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            for path in ("/cell", f"/jobs/{self.job_id}", "/metrics"):
                self.statuses.append((path, self.client.get(path).status_code))
            self.stop.wait(0.05)


def fill(mount: Path) -> None:
    """A ballast file beside the store that takes every free byte of the filesystem."""
    fd = os.open(mount / "ballast", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        st = os.statvfs(mount)
        if st.f_bavail:
            os.posix_fallocate(fd, 0, st.f_bavail * st.f_frsize)
        for chunk in (1 << 16, 4096, 1):  # whatever is left, to the last byte
            try:
                while True:
                    os.write(fd, bytes(chunk))
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
    finally:
        os.close(fd)
    assert os.statvfs(mount).f_bavail == 0


class Filled(threading.Event):
    """Set once the disk was filled; `args`: those of the write that found it full."""

    args: tuple = ()


def fill_at(monkeypatch, cls, name: str, when, mount: Path) -> Filled:
    """Fill the disk the first time the store's own write `cls.name` is called on an object and with arguments
    `when` accepts, just before that write runs."""
    original = getattr(cls, name)
    filled = Filled()

    def hooked(self, *args, **kwargs):
        if not filled.is_set() and when(self, *args):
            fill(mount)
            filled.args = args
            filled.set()
        return original(self, *args, **kwargs)

    monkeypatch.setattr(cls, name, hooked)
    return filled


PAGE = os.sysconf("SC_PAGE_SIZE")  # tmpfs gives a file its space a page at a time


def needs_a_page(folder: RunFolder, rows: list[dict], columns: tuple[str, ...]) -> bool:
    """Do these rows need a new page of samples.csv (else they fit in its last one, and a full disk takes them)?"""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    for row in rows:
        writer.writerow([csv_cell(row.get(c)) for c in columns])
    size = folder.samples_path.stat().st_size
    return -(-(size + len(buf.getvalue().encode())) // PAGE) > -(-size // PAGE)


# moment -> (the write wrapped, which call fills the disk, save_images, steps kept (from that call's arguments))
MOMENTS = {
    "image save": (RunFolder, "save_image", lambda folder, name, image: name.startswith("step00003_"), True,
                   lambda name, image: 3),
    "sample write": (RunFolder, "append_many",
                     lambda folder, rows, columns: rows[0]["step"] >= 10 and needs_a_page(folder, rows, columns),
                     False, lambda rows, columns: rows[0]["step"]),
    "calibration store write": (CalibrationStore, "_insert", lambda *args: True, False, lambda *args: 24),
    # a step's samples in its run folder, their record (progress, outbox) not: sent again on resume
    "step record": (JobStore, "record_step", lambda store, job, item, step, *rest: step == 12, False,
                    lambda job, item, step, *rest: step + 1),
}


def integrity(store: Path) -> dict[str, str]:
    out = {}
    for name in ("daemon.sqlite", "calibrations.sqlite"):
        db = sqlite3.connect(f"file:{store / name}?mode=ro", uri=True)
        try:
            out[name] = db.execute("PRAGMA integrity_check").fetchone()[0]
        finally:
            db.close()
    return out


def assert_prefix_of_reference(rows: list[dict], reference, n: int) -> None:
    """The rows are the uninterrupted run's first `n`, measured value for measured value."""
    _, ref_samples = reference
    assert [r["step"] for r in rows] == list(range(n))
    for a, b in zip(ref_samples, rows):
        assert {k: a[k] for k in MEASURED} == {k: b[k] for k in MEASURED}


@pytest.mark.parametrize("moment", list(MOMENTS))
def test_a_disk_full_at_each_moment_faults_keeps_every_sample_and_resumes_to_the_same_result(
        moment, small_fs, tmp_path, monkeypatch, reference, caplog):
    caplog.set_level(logging.WARNING, logger="cellctl.core.worker")
    cls, name, when, save_images, kept_of = MOMENTS[moment]
    filled = fill_at(monkeypatch, cls, name, when, small_fs)
    store = small_fs / "store"
    with daemon_on(cell_file(tmp_path, small_fs), monkeypatch) as (daemon, app, c):
        assert (store / RESERVE_FILE).exists()
        r = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": SEED,
                                  "save_images": save_images})
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]
        reader = Reader(app, job_id)
        reader.start()
        try:
            faulted = wait_for(c, job_id, {"faulted", "done"})
            assert filled.is_set() and faulted["state"] == "faulted", faulted
            kept = kept_of(*filled.args)
            reason = faulted["reason"]
            # typed, naming the filesystem and what fills it
            assert reason.startswith("DiskFull: no space left on the store's filesystem"), reason
            assert f"tmpfs on {small_fs}" in reason and "lie outside the store" in reason, reason
            assert "daemon.sqlite" in reason and ("images" in reason) == save_images, reason
            # the filesystem's own error: the OS's for files, SQLite's for its databases
            said = "database or disk is full" if cls is not RunFolder else "No space left on device"
            assert said in reason, reason
            assert not faulted["acknowledged"]
            # an expected fault, said in the job's reason: a warning in the daemon's log, not a bug's traceback
            said = [(r.levelname, r.getMessage()) for r in caplog.records if getattr(r, "job", None) == job_id]
            assert ("WARNING", "job faulted") in said and ("ERROR", "job failed") not in said, said

            # nothing lost, nothing corrupt
            assert integrity(store) == {"daemon.sqlite": "ok", "calibrations.sqlite": "ok"}
            r = c.get(f"/jobs/{job_id}/samples")
            assert r.status_code == 200, r.text
            assert_prefix_of_reference(read_samples_text(r.text), reference, kept)
            assert daemon.calstore.list() == []  # no calibration half-stored
            assert not list(store.glob("samples/.pending-*"))  # nor its samples' copy

            # reads go on; new jobs (with or without images) are refused, naming the free space and the floor
            cell = c.get("/cell").json()
            assert cell["disk"]["low"] and cell["disk"]["free_mb"] < MIN_FREE_MB
            assert cell["disk"]["filesystem"] == f"tmpfs on {small_fs}"
            assert "cellctl_store_free_bytes" in c.get("/metrics").text
            for images in (False, True):
                r = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": SEED,
                                          "save_images": images})
                assert r.status_code == 507, r.text
                detail = r.json()["detail"]
                assert " MB free, below the " in detail, detail
                assert f"{MIN_FREE_MB:g} MB" in detail and "store.min_free_mb" in detail, detail
                assert f"tmpfs on {small_fs}" in detail, detail
            # acknowledged, still full: resuming is refused the same way
            assert c.post(f"/jobs/{job_id}/ack").status_code == 200
            r = c.post(f"/jobs/{job_id}/resume")
            assert r.status_code == 507 and "store.min_free_mb" in r.json()["detail"], r.text

            # space freed: the job resumes from its samples to the uninterrupted run's end
            (small_fs / "ballast").unlink()
            assert c.post(f"/jobs/{job_id}/resume").status_code == 200
            done = wait_for(c, job_id, {"done", "faulted"})
            assert done["state"] == "done", done
        finally:
            reader.stop.set()
            reader.join(30)
        assert reader.statuses and all(status == 200 for _, status in reader.statuses), \
            [s for s in reader.statuses if s[1] != 200][:5]

        ref_result, ref_samples = reference
        rows = read_samples_text(c.get(f"/jobs/{job_id}/samples").text)
        assert_prefix_of_reference(rows, reference, 24)
        assert [r["cell_time_s"] for r in rows] == [r["cell_time_s"] for r in ref_samples]
        result = c.get(f"/jobs/{job_id}/result").json()
        assert result["stats"] == json.loads(json.dumps(ref_result["stats"]))
        assert result["model"] == json.loads(json.dumps(ref_result["model"]))
        assert result["cell_time_s"] == ref_result["cell_time_s"]
        if save_images:
            assert len(list((store / "jobs" / f"{job_id:06d}" / "images").glob("step*_cam1.png"))) == 24
        # its calibration stored once, with its samples
        stored = daemon.calstore.list()
        assert [(s.target, s.version) for s in stored] == [("cam1", 1)] and result["calibration"]["id"] == stored[0].id
        assert daemon.calstore.samples_path(stored[0].id) is not None
        assert (store / RESERVE_FILE).exists()  # made again once there was room
        history = [h["to"] for h in c.get(f"/jobs/{job_id}").json()["history"]]
        assert history == ["queued", "running", "faulted", "paused", "queued", "running", "done"]

        # the outbox (its sink never reached) holds every step's samples and the result for the plant
        db = sqlite3.connect(f"file:{store / 'daemon.sqlite'}?mode=ro", uri=True)
        try:
            keys = [k for (k,) in db.execute("SELECT key FROM outbox")]
        finally:
            db.close()
        assert {k for k in keys if k.startswith(f"samples/{job_id}/")} == {f"samples/{job_id}//{s}" for s in range(24)}
        assert f"result/{job_id}/" in keys
    assert integrity(store) == {"daemon.sqlite": "ok", "calibrations.sqlite": "ok"}


def test_below_the_floor_new_jobs_and_saved_images_are_refused_naming_free_space_and_floor(small_fs, tmp_path,
                                                                                          monkeypatch, capsys):
    from cellctl.cli.display import print_status

    floor = FS_MB * 2  # more than the filesystem holds
    with daemon_on(cell_file(tmp_path, small_fs, min_free_mb=floor), monkeypatch) as (daemon, _app, c):
        disk = c.get("/cell").json()["disk"]
        assert disk["low"] and disk["min_free_mb"] == floor and disk["total_mb"] == pytest.approx(FS_MB, abs=1)
        for images in (False, True):
            r = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": SEED,
                                      "save_images": images})
            assert r.status_code == 507, r.text
            detail = r.json()["detail"]
            assert detail.startswith("a new job" + (" that saves its images" if images else "") + " is refused")
            assert f"{disk['free_mb']:.1f} MB free" in detail and f"below the {floor:g} MB" in detail, detail
            assert f"tmpfs on {small_fs}" in detail and "store.min_free_mb" in detail, detail
        assert c.get("/jobs").json()["jobs"] == []
        audit = c.get("/audit").json()["audit"]
        assert [a["outcome"][:11] for a in audit if a["action"] == "POST /jobs"] == ["refused 507"] * 2
        metrics = dict(line.rsplit(" ", 1) for line in c.get("/metrics").text.splitlines()
                       if line.startswith("cellctl_store_"))
        assert float(metrics["cellctl_store_min_free_bytes"]) == floor * 2**20
        labels = f'{{filesystem="tmpfs on {small_fs}"}}'
        assert float(metrics["cellctl_store_size_bytes" + labels]) == pytest.approx(FS_MB * 2**20, rel=0.01)
        assert float(metrics["cellctl_store_free_bytes" + labels]) == pytest.approx(disk["free_mb"] * 2**20,
                                                                                   abs=2**20)
        print_status(c.get("/cell").json(), "here")
        assert f"MB free of {disk['total_mb']:.1f} MB (tmpfs on {small_fs}), BELOW the {floor:g} MB" in \
            capsys.readouterr().out


def test_the_store_section_of_the_cell_file_is_strict(tmp_path):
    from cellctl.config import CellFileError, load_cell_file

    path = write_cell_file(tmp_path)
    assert load_cell_file(path, routines=False)[0].store.min_free_mb == 100.0  # the default
    for section, said in (({"min_free": 10}, "store.min_free: unknown key"),
                          ({"min_free_mb": -1}, "store.min_free_mb: Input should be greater than or equal to 0"),
                          ({"min_free_mb": "lots"}, "store.min_free_mb: Input should be a valid number")):
        data = yaml.safe_load(path.read_text())
        data["store"] = section
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(CellFileError) as exc:
            load_cell_file(path, routines=False)
        assert said in str(exc.value), str(exc.value)
