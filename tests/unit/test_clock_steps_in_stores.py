"""The job store under a stepped wall clock: its lists keep the order things happened in (ids), not their stamps,
and a duration read from the stamps never goes below zero."""

from __future__ import annotations

import time

import pytest

from cellctl.stores import jobs as jobs_module
from cellctl.stores.jobs import JobStore, _running_s


@pytest.fixture
def wall(monkeypatch):
    """The wall clock the store stamps with, stepped by the test (`wall.now`)."""
    class Wall:
        now = time.time()

        def __call__(self) -> float:
            return self.now

    clock = Wall()
    monkeypatch.setattr(jobs_module.time, "time", clock)
    return clock


def test_a_job_resumed_after_a_step_back_does_not_overtake_one_queued_before(tmp_path, wall):
    store = JobStore(tmp_path / "daemon.sqlite")
    held = store.submit("virtual-grid", {}, 1, "anna")
    store.transition(held.id, "running", "started", "daemon")
    store.transition(held.id, "paused", "paused", "anna")
    waiting = store.submit("virtual-grid", {}, 2, "ben")
    wall.now -= 3600.0  # NTP steps the clock an hour back
    store.transition(held.id, "queued", "resumed", "anna")  # stamped an hour before ben's job was queued
    assert store.get(held.id).updated < store.get(waiting.id).updated
    assert store.next_queued().id == waiting.id


def test_the_audit_and_a_jobs_history_keep_their_order_across_a_step_back(tmp_path, wall):
    store = JobStore(tmp_path / "daemon.sqlite")
    job = store.submit("virtual-grid", {}, 1, "anna")
    store.audit("token", "anna", "submit", f"job {job.id}", {}, "ok")
    store.transition(job.id, "running", "started", "daemon")
    wall.now -= 3600.0
    store.audit("token", "anna", "pause", f"job {job.id}", {}, "ok")
    store.transition(job.id, "paused", "paused", "anna")
    audit = store.audit_log()
    assert [a["action"] for a in audit] == ["submit", "pause"] and audit[1]["at"] < audit[0]["at"]
    assert [h["to"] for h in store.history(job.id)] == ["queued", "running", "paused"]


def test_running_time_from_stamps_never_goes_below_zero():
    events = [("2026-12-04T10:00:00.000+00:00", "running"), ("2026-12-04T09:00:05.000+00:00", "paused"),
              ("2026-12-04T09:00:10.000+00:00", "running"), ("2026-12-04T09:00:20.000+00:00", "done")]
    assert _running_s(events) == 10.0
