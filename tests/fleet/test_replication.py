"""Replication in-process, on a real PostgreSQL: the stores' outboxes written in the change's own transaction,
each record in the plant database exactly once (however often it is delivered), kept through an outage, the
credentials' rules, and a store restored from the plant database."""

from __future__ import annotations

import json
import os
import sqlite3
import time
from pathlib import Path

import psycopg
import pytest

from cellctl.fleet import plant, secrets
from cellctl.fleet.postgres import PostgresSink
from cellctl.fleet.replicator import Replicator, SinkDown
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.jobs import JobStore
from cellctl.stores.outbox import Outbox

from tests.support.wait import eventually

CHECK = {"verdict": "drift", "drifted": ["cam1"], "checked": {"cam1": 1}, "actions": {"cam1": "touch-up"},
         "stats": {"drift": {"cam1": {"dx_um": 3.0, "dy_um": -4.0, "dx_std_um": 0.5, "dy_std_um": 0.5}},
                   "test": {"cam1": {"p_value": 1e-6}}}}


def fill(folder, cell_jobs: int = 2):
    """A cell's stores with jobs, steps, a result, two versions of cam1, an activation, a check and an audit."""
    jobs = JobStore(folder / "daemon.sqlite", replicate=True)
    cals = CalibrationStore(folder, replicate=True)
    for n in range(cell_jobs):
        job = jobs.submit("virtual-grid", {"rows": 4}, n, "token")
        jobs.transition(job.id, "running", "started", "daemon")
        for step in range(3):
            jobs.record_step(job.id, None, step, [{"step": step, "u_px": 1.5 * step, "set": "cal"}] * 2,
                             {"step": step + 1, "total": 3}, announce=step == 2)
        jobs.transition(job.id, "done", "finished", "daemon", result={"routine": "virtual-grid", "n": n})
        jobs.audit("token", "op@pc", "submit", f"job {job.id}", {"routine": "virtual-grid"}, "ok")
    first = cals.save("cam1", {"routine": "virtual-grid", "model": {"a": 1},
                               "stats": {"verification": {"mean_um": 2.5}}}, "cell: {name: a}")
    cals.save("cam1", {"routine": "virtual-grid", "model": {"a": 2}, "stats": {"verification": {"mean_um": 2.0}},
                       "provenance": {"parent": first.id}}, "cell: {name: a}")
    cals.activate(first.id)
    cals.save_check(CHECK)
    jobs.record_cell("idle", None)
    return jobs, cals


def replicator(folder, dsn, cell="cell-a"):
    return Replicator([Outbox(folder / "daemon.sqlite", "jobs"), Outbox(folder / "calibrations.sqlite",
                                                                         "calibrations")],
                      [PostgresSink(dsn, cell, {"description": "test cell"})], heartbeat_s=0.5, poll_s=0.1)


def drained(rep: Replicator, timeout: float = 30.0) -> None:
    def empty() -> bool:
        if rep.up["postgres"] and not any(rep.backlog().values()):
            return True
        rep.wake()
        return False

    eventually(empty, timeout=timeout, every=0.05, what=lambda: f"drained (backlog {rep.backlog()}, up {rep.up})")


def counts(dsn: str, cell: str) -> dict[str, int]:
    with psycopg.connect(dsn) as conn:
        return {t: conn.execute(f"SELECT COUNT(*) FROM {t} WHERE cell = %s", (cell,)).fetchone()[0]
                for t in ("jobs", "job_states", "samples", "results", "calibrations", "health_checks", "audit")}


EXPECTED = {"jobs": 2, "job_states": 6, "samples": 12, "results": 2, "calibrations": 2, "health_checks": 1,
            "audit": 2}


def test_every_record_reaches_the_plant_once_however_often_it_is_sent(postgres, tmp_path):
    jobs, cals = fill(tmp_path)
    rep = replicator(tmp_path, postgres.dsn)
    rep.start()
    drained(rep)
    rep.stop()
    assert counts(postgres.dsn, "cell-a") == EXPECTED
    # the outbox is emptied once delivered
    for name in ("daemon.sqlite", "calibrations.sqlite"):
        with sqlite3.connect(tmp_path / name) as db:
            assert db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0] == 0

    # everything again (as after a crash before the cursor moved): nothing doubles, nothing changes
    again = fill(tmp_path / "again")
    sink = PostgresSink(postgres.dsn, "cell-a", {"description": "test cell"})
    sink.connect()
    for name, source in (("daemon.sqlite", "jobs"), ("calibrations.sqlite", "calibrations")):
        box = Outbox(tmp_path / "again" / name, source)
        records = box.pending("postgres", 10_000)
        sink.deliver(records)
        sink.deliver(records)
        box.close()
    sink.close(graceful=True)
    assert counts(postgres.dsn, "cell-a") == EXPECTED
    with psycopg.connect(postgres.dsn) as conn:
        cells = plant.status(conn, "cell-a")["cells"]
        assert [c["name"] for c in cells] == ["cell-a"]
        # the activation of the first version holds; the check of it says drift
        assert cells[0]["calibrations"] == {"cam1": {"version": 1, "verification_mean_um": 2.5, "health": "drift"}}
        assert cells[0]["state"] == "offline" and cells[0]["description"] == "test cell"
        listed = plant.jobs(conn, "cell-a")["jobs"]
        assert sorted((j["id"], j["state"], j["samples"]) for j in listed) == [(1, "done", 6), (2, "done", 6)]
    for store in (jobs, cals, *again):
        store.close()


def test_a_deactivated_version_leaves_its_target_without_one_in_the_plant(postgres, tmp_path):
    """`calibrations deactivate`: the plant database then has no active version of the target either, and
    activating one again is replicated after it."""
    cals = CalibrationStore(tmp_path, replicate=True)
    arm = cals.save("arm", {"routine": "arm-kinematics", "model": {"a": 1}, "stats": {}}, "cell: {name: a}")
    cals.deactivate(arm.id)
    sink = PostgresSink(postgres.dsn, "cell-d", {"description": "test cell"})
    sink.connect()
    box = Outbox(tmp_path / "calibrations.sqlite", "calibrations")

    def active() -> list[bool]:
        sink.deliver(box.pending("postgres", 10_000))
        with psycopg.connect(postgres.dsn) as conn:
            return [r[0] for r in conn.execute("SELECT active FROM calibrations WHERE cell = 'cell-d' ORDER BY id")]

    assert active() == [False]
    cals.activate(arm.id)
    assert active() == [True]
    sink.close(graceful=True)
    box.close()
    cals.close()


def test_records_wait_out_an_outage_and_arrive_once(postgres, tmp_path):
    jobs = JobStore(tmp_path / "daemon.sqlite", replicate=True)
    rep = replicator(tmp_path, postgres.dsn, cell="cell-b")
    jobs.outbox.on_commit = rep.wake
    rep.start()
    try:
        drained(rep)
        postgres.stop()
        job = jobs.submit("calibration-check", {}, None, "token")
        for to in ("running", "done"):
            jobs.transition(job.id, to, to, "daemon")
        time.sleep(1.0)
        assert not rep.up["postgres"] and rep.backlog()["postgres"] > 0
        postgres.resume()
        drained(rep)
        assert counts(postgres.dsn, "cell-b")["job_states"] == 3
        with psycopg.connect(postgres.dsn) as conn:
            assert conn.execute("SELECT state FROM jobs WHERE cell = 'cell-b'").fetchone()[0] == "done"
    finally:
        if postgres.proc is None:
            postgres.resume()
        rep.stop()
        jobs.close()


def test_a_cell_outside_a_fleet_keeps_no_outbox(tmp_path):
    jobs = JobStore(tmp_path / "daemon.sqlite")
    job = jobs.submit("calibration-check", {}, None, "token")
    jobs.transition(job.id, "running", "started", "daemon")
    jobs.record_step(job.id, None, 0, [{"step": 0}], {"step": 1}, announce=True)
    with sqlite3.connect(tmp_path / "daemon.sqlite") as db:
        assert db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0] == 0
    jobs.close()


def test_credentials_come_from_owner_only_files_and_never_show(postgres, tmp_path):
    dsn_file = tmp_path / "plant.dsn"
    dsn_file.write_text(postgres.dsn + "\n")
    os.chmod(dsn_file, 0o644)
    with pytest.raises(secrets.CredentialError, match=r"may be read by others \(mode 0644\); allowed: owner-only"):
        secrets.from_file(dsn_file, "fleet.postgres")
    os.chmod(dsn_file, 0o600)
    assert secrets.from_file(dsn_file, "fleet.postgres") == postgres.dsn
    with pytest.raises(secrets.CredentialError, match="does not exist"):
        secrets.from_file(tmp_path / "nothing", "fleet.postgres")
    # a wrong password: refused, said so, and the password is nowhere in the message
    wrong = postgres.dsn.replace(postgres.password, "not-the-Secret-42")
    sink = PostgresSink(wrong, "cell-x")
    with pytest.raises(SinkDown) as refused:
        sink.connect()
    assert "password authentication failed" in str(refused.value)
    assert "not-the-Secret-42" not in str(refused.value)


def test_restore_puts_the_versions_back_into_an_empty_store(postgres, tmp_path):
    jobs, cals = fill(tmp_path / "old")
    rep = replicator(tmp_path / "old", postgres.dsn, cell="cell-r")
    rep.start()
    drained(rep)
    rep.stop()
    with psycopg.connect(postgres.dsn) as conn:
        versions, checks = plant.restore_records(conn, "cell-r")
    fresh = CalibrationStore(tmp_path / "new")
    assert fresh.restore(versions, checks) == 2
    for old, new in zip(cals.list(), fresh.list()):
        assert (old.id, old.target, old.version, old.active, old.result) == \
               (new.id, new.target, new.version, new.active, new.result)
    assert fresh.active_models() == cals.active_models()
    assert fresh.health()["cam1"]["verdict"] == cals.health()["cam1"]["verdict"] == "drift"
    assert json.loads(json.dumps(fresh.get(2).result["provenance"])) == {"parent": 1}
    with pytest.raises(Exception, match="already holds calibrations: restore into an empty store"):
        fresh.restore(versions, checks)
    for store in (jobs, cals, fresh):
        store.close()


def test_the_cell_files_fleet_section_names_what_is_wrong(tmp_path):
    from cellctl.config import CellFileError, load_cell_file

    base = (Path(__file__).resolve().parents[2] / "config" / "sim-microcell.yaml").read_text()

    def problems(fleet: str) -> str:
        path = tmp_path / "cell.yaml"
        path.write_text(base + "\nfleet:\n" + fleet)
        with pytest.raises(CellFileError) as bad:
            load_cell_file(path)
        return str(bad.value)

    assert "fleet.postgres: Value error, give dsn_file or dsn_env, exactly one" in problems(
        "  postgres: {dsn_file: a, dsn_env: B}\n")
    assert "fleet.mqtt.topic_prefix" in problems("  mqtt: {host: h, topic_prefix: 'plant/#'}\n")
    assert "fleet.mqtt.topic_prefix" in problems("  mqtt: {host: h, topic_prefix: '/plant'}\n")
    assert "fleet.mqtt: Value error, a password needs a username" in problems(
        "  mqtt: {host: h, topic_prefix: p, password_env: X}\n")
    assert "fleet.mqtt.port" in problems("  mqtt: {host: h, topic_prefix: p, port: 70000}\n")
    assert "fleet.cell_id" in problems("  cell_id: 'has space'\n")
    assert "fleet.postgres.password: unknown key" in problems("  postgres: {dsn_env: X, password: hunter2}\n")
    path = tmp_path / "cell.yaml"
    path.write_text(base + "\nfleet: {cell_id: press-7, mqtt: {host: h, topic_prefix: p}}\n")
    config, _ = load_cell_file(path)
    assert config.fleet_name == "press-7" and config.fleet.mqtt.port == 1883


def test_the_fleet_command_reads_the_plant_database(postgres, tmp_path, capsys):
    from cellctl.cli import main

    jobs, cals = fill(tmp_path / "cell")
    rep = replicator(tmp_path / "cell", postgres.dsn, cell="cell-cli")
    rep.start()
    drained(rep)
    rep.stop()
    dsn_file = tmp_path / "plant.dsn"
    dsn_file.write_text(postgres.dsn)
    os.chmod(dsn_file, 0o600)
    db = ["--dsn-file", str(dsn_file), "--cell", "cell-cli"]
    assert main(["fleet", "health", *db, "--json"]) == 0
    health = json.loads(capsys.readouterr().out)["health"]
    assert [(h["target"], h["version"], h["verdict"], h["last_check"]["drift"]["dx_um"]) for h in health] == [
        ("cam1", 1, "drift", 3.0)]
    assert main(["fleet", "calibrations", *db, "--target", "cam1", "--json"]) == 0
    versions = json.loads(capsys.readouterr().out)["calibrations"]
    assert [(c["version"], c["active"], c["provenance"]) for c in versions] == [(1, True, None),
                                                                                (2, False, {"parent": 1})]
    for verb in ("status", "jobs", "calibrations", "health"):  # the tables name what they show
        assert main(["fleet", verb, *db]) == 0
        assert "cell-cli" in capsys.readouterr().out
    assert main(["fleet", "status", "--dsn-file", str(dsn_file), "--cell", "nope"]) == 2
    assert "cell: 'nope' is not in the plant database (cells: " in capsys.readouterr().err
    for store in (jobs, cals):
        store.close()
