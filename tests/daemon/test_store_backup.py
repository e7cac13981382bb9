"""A corrupt or lost store, through the real daemon: a copy of a store with a corrupt page is refused at start-up
(exit 2, logged), naming the file, the last good backup and the command that restores it; a backup taken while a
job runs, restored once the daemon has stopped, brings the job back faulted, and acknowledged and resumed it ends
as an uninterrupted run of the same seed."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
import yaml

from cellctl.cli import main
from cellctl.stores.backup import backups_in, read_manifest
from cellctl.stores.jobs import DB_FILE
from cellctl.stores.run_folder import RunFolder

from tests.daemon.test_jobs import assert_same_as_reference, samples_of, submit
from tests.support.daemon import ROOT, DaemonProcess, wait_for, wait_step, write_cell_file
from tests.support.wait import eventually
from tests.unit.test_store_backup_unit import corrupt_middle_page

pytestmark = pytest.mark.long


@pytest.fixture(autouse=True)
def stores_of_the_cell_files(monkeypatch):
    """Each command finds its store through its cell file (--config), as on a cell PC: not $CELLCTL_STORE."""
    monkeypatch.delenv("CELLCTL_STORE")


def test_a_corrupt_store_is_refused_with_the_file_and_the_restore_command(start_daemon, tmp_path, capsys):
    daemon = start_daemon(realtime_factor=0.0)
    with daemon.client() as c:
        for _ in range(3):  # a store of a few pages
            wait_for(c, submit(c)["id"], {"done"})
    assert daemon.terminate() == 0
    assert main(["store", "backup", "--config", str(daemon.cell_file)]) == 0
    good = backups_in(daemon.store.with_name("store-backups"))[-1]

    # a copy of the store, its backups named in its cell file; a page in the middle of its job database torn
    copy = tmp_path / "copy"
    copy.mkdir()
    shutil.copytree(daemon.store, copy / "store")
    (copy / "store" / "daemon.url").unlink()  # the original daemon's
    data = yaml.safe_load(daemon.cell_file.read_text())
    data["store_dir"] = str(copy / "store")
    data["store"] = {"backup": {"every_h": 24, "keep": 3, "to": str(good.parent)}}
    cell_file = copy / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(data))
    corrupt_middle_page(copy / "store" / DB_FILE)

    refused = subprocess.run([sys.executable, "-m", "cellctl.startup", "--config", str(cell_file), "--port", "0"],
                             cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2  # systemd sees a failed start
    said = refused.stderr
    assert str(copy / "store" / DB_FILE) in said and "integrity check" in said
    assert f"cellctl store restore {good} --config {cell_file}" in said
    assert '"msg": "store refused"' in said  # logged (JSON lines) before the one-line error
    assert not (copy / "store" / "daemon.url").exists()  # it never served

    # the command it names restores the store, and the daemon then serves what the backup holds
    assert main(["store", "restore", str(good), "--config", str(cell_file)]) == 0
    assert "the store it replaced is kept in" in capsys.readouterr().out
    restarted = DaemonProcess(cell_file).start()
    with restarted, restarted.client() as c:
        assert [j["state"] for j in c.get("/jobs").json()["jobs"]] == ["done"] * 3


def test_a_backup_taken_mid_job_restores_and_resumes_to_the_same_result(start_daemon, reference, capsys):
    daemon = start_daemon()
    with daemon.client() as c:
        job = submit(c)
        wait_step(c, job["id"], 9)
        assert main(["store", "backup", "--config", str(daemon.cell_file)]) == 0  # beside the running daemon
        taken = backups_in(daemon.store.with_name("store-backups"))[-1]
        assert str(taken) in capsys.readouterr().out
        # a restore is refused while the daemon owns the store, and changes nothing
        assert main(["store", "restore", str(taken), "--config", str(daemon.cell_file)]) == 2
        assert "is owned by pid" in capsys.readouterr().err
        wait_for(c, job["id"], {"done"})  # the store goes on past the backup
    assert daemon.terminate() == 0
    in_backup = RunFolder(taken / "jobs" / f"{job['id']:06d}").samples()
    assert 9 <= len(in_backup) < 24

    assert main(["store", "restore", str(taken), "--config", str(daemon.cell_file)]) == 0
    daemon.start()
    with daemon.client() as c:
        found = c.get(f"/jobs/{job['id']}").json()
        assert found["state"] == "faulted" and found["reason"] == "daemon stopped while running"
        assert not found["acknowledged"]  # nothing moves before an operator says so
        assert [r["step"] for r in samples_of(c, job["id"])] == [r["step"] for r in in_backup]
        assert c.post(f"/jobs/{job['id']}/ack").json()["state"] == "paused"
        assert c.post(f"/jobs/{job['id']}/resume").status_code == 200
        wait_for(c, job["id"], {"done"})
        assert_same_as_reference(c, job["id"], reference)
    assert daemon.terminate() == 0


def test_the_daemon_backs_its_store_up_on_the_schedule_of_its_cell_file(start_daemon, tmp_path, capsys):
    cell_file = write_cell_file(tmp_path, realtime_factor=0.0)
    data = yaml.safe_load(cell_file.read_text())
    data["store"] = {"backup": {"every_h": 24, "keep": 2, "to": str(tmp_path / "backups")}}
    cell_file.write_text(yaml.safe_dump(data))
    daemon = start_daemon(cell_file)  # no backup yet: the first is taken at start
    taken = eventually(lambda: backups_in(tmp_path / "backups"), timeout=60, what="the first scheduled backup")
    assert read_manifest(taken[0])["cell"] == data["cell"]["name"]
    eventually(lambda: any(e.get("msg") == "store backed up" for e in daemon.logs()), what="the backup logged")

    # one now, asked of the daemon (whose user reads the store): where its cell file says, audited
    assert main(["store", "backup", "--url", daemon.url, "--token", daemon.token]) == 0
    asked = backups_in(tmp_path / "backups")[-1]
    assert f"backed its store up into {asked}" in capsys.readouterr().out
    assert main(["store", "backup", "--url", daemon.url, "--token", daemon.token, "--to", str(tmp_path)]) == 2
    assert "daemon's to choose" in capsys.readouterr().err
    with daemon.client() as c:
        assert any(e["target"] == str(asked) and e["outcome"] == "ok" for e in c.get("/audit").json()["audit"])
    assert len(backups_in(tmp_path / "backups")) <= 2  # keep: 2
    assert daemon.terminate() == 0
