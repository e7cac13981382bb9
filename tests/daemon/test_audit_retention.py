"""The audit log stays bounded: refused requests are kept REFUSED_KEEP_DAYS days and at most the newest
REFUSED_KEEP_LAST of them; an accepted command is never dropped. Deleting the old refusals is local: a cell in a
fleet wrote each entry to its outbox in the same transaction, and the plant keeps its copy."""

from __future__ import annotations

import sqlite3
import time

from cellctl.startup.daemon import DB_FILE
from cellctl.stores import jobs as jobs_module
from cellctl.stores.jobs import JobStore

from tests.support.daemon import DaemonProcess, write_cell_file


def backdate(path, days: float, outcome_like: str = "%") -> None:
    """Make the matching audit entries `days` old (as if written then)."""
    t = time.time() - days * 86400
    at = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + ".000Z"
    with sqlite3.connect(path) as db:
        db.execute("UPDATE audit SET at = ? WHERE outcome LIKE ?", (at, outcome_like))


def outcomes(store: JobStore) -> list[str]:
    return [a["outcome"] for a in store.audit_log(1_000_000)]


def test_refused_requests_are_kept_n_days_and_the_last_m_accepted_commands_always(tmp_path):
    path = tmp_path / "jobs.sqlite"
    store = JobStore(path, replicate=True, refused_keep_last=50)
    for i in range(1000):  # a client knocking with a wrong token, among real commands
        accepted = i % 10 == 0
        store.audit("token" if accepted else "-", "client@host", "POST /jobs", f"job {i}", "",
                    "ok" if accepted else "refused 403")
    store.audit("token", "client@host", "POST /jobs/1/abort", "job 1", "", "failed")  # accepted; its work failed
    kept = outcomes(store)
    assert kept.count("ok") == 100 and kept.count("failed") == 1
    assert 50 <= kept.count("refused 403") < 50 + jobs_module.PRUNE_EVERY  # pruned every PRUNE_EVERY refusals
    assert [a["target"] for a in store.audit_log(3)][-1] == "job 1"  # the newest stay
    # the plant's copy: every entry went into the outbox when it was written, pruned ones included
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT COUNT(*) FROM outbox WHERE kind = 'audit'").fetchone()[0] == 1001
    store.close()

    # older than the retention: the refusals go when the store opens, accepted commands stay whatever their age
    backdate(path, jobs_module.REFUSED_KEEP_DAYS + 1)
    store = JobStore(path)
    assert outcomes(store) == ["ok"] * 100 + ["failed"]
    # a newer refusal stays; numbering goes on after the deleted ones (the plant keys entries by their id)
    store.audit("-", "client@host", "POST /jobs", "", "", "refused 401")
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT MAX(id) FROM audit").fetchone()[0] == 1002
    assert outcomes(store)[-1] == "refused 401"
    store.close()


def test_the_daemon_drops_old_refusals_at_start_and_keeps_every_accepted_command(tmp_path):
    cell = write_cell_file(tmp_path, realtime_factor=0.0)
    with DaemonProcess(cell).start() as d:
        with d.client() as c:
            lock = c.post("/lock", json={"holder": "alice", "ttl_s": 60}).json()  # accepted
            assert c.request("DELETE", "/lock", headers={"X-Cellctl-Lock": lock["lock_id"]}).status_code == 200
        with d.client(token="wrong") as wrong:
            for _ in range(5):
                assert wrong.post("/jobs/1/abort").status_code == 403
        d.terminate()
    db = d.store / DB_FILE
    backdate(db, jobs_module.REFUSED_KEEP_DAYS + 2)  # all of it a month old
    with DaemonProcess(cell).start() as d:
        with d.client(token="wrong") as wrong:
            assert wrong.post("/jobs/1/abort").status_code == 403  # a new refusal
        with d.client() as c:
            audit = c.get("/audit").json()["audit"]
    assert [(a["action"], a["outcome"]) for a in audit] == [("POST /lock", "ok"), ("DELETE /lock", "ok"),
                                                           ("POST /jobs/1/abort", "refused 403")]
