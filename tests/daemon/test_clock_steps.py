"""A step of the wall clock (NTP after a week offline: an hour on, an hour back) under the real daemon
(tests/support/wall_clock.py): the daemon's wall clock steps while its monotonic clock runs on.

Durations run on the monotonic clock, so a step neither ends the operator lock early nor keeps it late, and
neither skips a scheduled calibration check nor runs one twice; the audit keeps the order of the commands (by
its ids) while their wall-clock stamps go back; the times shown to people follow the wall clock."""

from __future__ import annotations

import shutil
import time
from datetime import datetime

import pytest
import yaml

from tests.support.daemon import SEED, SMALL, DaemonProcess, wait_for, write_cell_file
from tests.support.wait import eventually
from tests.support.wall_clock import SteppedWallClock, compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler for the stepped wall clock (tools/ensure-system)")

HOUR = 3600
LOCK_TTL_S = 6.0
EVERY_H = 0.002  # 7.2 s between checks: longer than a check takes, so one brought forward would show
SLACK_S = 2.0  # a job is stamped a moment after the schedule read its clock (longer on a loaded machine)


def stamp_s(at: str) -> float:
    """A stamp of the store (2026-12-04T09:10:11.123Z) in seconds since the epoch."""
    return datetime.fromisoformat(at.replace("Z", "+00:00")).timestamp()


def lock_wall(c) -> float:
    """The daemon's wall clock, as its lock status shows it (while a lock is held)."""
    status = c.get("/lock").json()
    assert status["held"], status
    return status["expires"] - status["expires_in_s"]


def schedule_wall(c) -> float:
    """The daemon's wall clock (to the second), as its schedule's next check shows it."""
    s = c.get("/cell").json()["health_schedule"]
    return stamp_s(s["next_check"]) - s["due_in_s"]


def stepped(clock: SteppedWallClock, seconds: int, daemon_wall) -> None:
    """Step the daemon's wall clock and see that the daemon reads the new time."""
    clock.step(seconds)
    offset = daemon_wall() - time.time()
    assert abs(offset - clock.offset_s) < 30, (offset, clock.offset_s)


def test_a_wall_step_during_a_job_neither_ends_the_lock_early_nor_keeps_it_late(tmp_path):
    clock = SteppedWallClock(tmp_path)
    daemon = DaemonProcess(write_cell_file(tmp_path, realtime_factor=2.0))  # the job runs through both steps
    daemon.extra_env.update(clock.env())
    with daemon.start(), daemon.client(**{"X-Cellctl-Client": "anna"}) as anna, \
            daemon.client(**{"X-Cellctl-Client": "ben"}) as ben:
        job = anna.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": SEED}).json()
        wait_for(anna, job["id"], {"running"})
        lock = anna.post("/lock", json={"holder": "anna", "ttl_s": LOCK_TTL_S}).json()["lock_id"]
        held = {"X-Cellctl-Lock": lock}

        stepped(clock, +HOUR, lambda: lock_wall(anna))  # on the wall clock the lock's time is long past
        assert anna.get("/lock").json()["expires_in_s"] <= LOCK_TTL_S
        assert ben.post(f"/jobs/{job['id']}/pause").status_code == 423  # still anna's: not ended early
        renewed_at = time.monotonic()
        assert anna.post("/lock", json={"holder": "anna", "ttl_s": LOCK_TTL_S}, headers=held).status_code == 200

        stepped(clock, -HOUR, lambda: lock_wall(anna))  # on the wall clock the lock now has an hour more to go
        assert anna.get(f"/jobs/{job['id']}").json()["state"] == "running"
        eventually(lambda: not anna.get("/lock").json()["held"], timeout=60, what="the lock to lapse")
        assert time.monotonic() - renewed_at >= LOCK_TTL_S  # ...and not before its time either
        late = ben.post("/lock", json={"holder": "ben", "ttl_s": LOCK_TTL_S}).json()["lock_id"]
        assert ben.delete("/lock", headers={"X-Cellctl-Lock": late}).status_code == 200

        done = wait_for(anna, job["id"], {"done", "faulted", "aborted"})
        assert done["state"] == "done", done
        # the audit in the order of the commands, though the last ones are stamped an hour before the renewal
        audit = [a for a in anna.get("/audit").json()["audit"]
                 if a["outcome"] == "ok" and a["client"].partition("@")[0] in ("anna", "ben")]
        said = [(a["client"].partition("@")[0], a["action"], a["target"]) for a in audit]
        assert said == [("anna", "POST /jobs", f"job {job['id']}"), ("anna", "POST /lock", "lock"),
                        ("anna", "POST /lock", "lock"), ("ben", "POST /lock", "lock"),
                        ("ben", "DELETE /lock", "lock")], said
        renewal, taken_late = audit[2], audit[3]
        assert stamp_s(taken_late["at"]) < stamp_s(renewal["at"]) - HOUR / 2
        history = anna.get(f"/jobs/{job['id']}").json()["history"]
        assert [h["to"] for h in history] == ["queued", "running", "done"]


def scheduled_checks(c) -> list[dict]:
    """The checks the schedule submitted, oldest first."""
    return sorted((j for j in c.get("/jobs").json()["jobs"] if j["submitted_by"] == "schedule"),
                  key=lambda j: j["id"])


def next_check(c, after: list[dict], timeout: float = 120.0) -> dict:
    """The scheduled check submitted after `after` (one, not two)."""
    found = eventually(lambda: scheduled_checks(c)[len(after):], timeout=timeout, every=0.05,
                       what=lambda: f"a scheduled check after {[j['id'] for j in after]}")
    assert len(found) == 1, found
    return found[0]


def test_a_wall_step_between_scheduled_checks_neither_skips_one_nor_runs_one_twice(tmp_path, calibrated_cell):
    clock = SteppedWallClock(tmp_path)
    cell_file = write_cell_file(tmp_path, realtime_factor=0.05)
    data = yaml.safe_load(cell_file.read_text())
    data["health"] = {"every_h": EVERY_H, "targets": ["cam1"]}
    data["sim"]["seed"] = calibrated_cell.seed
    cell_file.write_text(yaml.safe_dump(data))
    shutil.copytree(calibrated_cell.store_path, tmp_path / "store")
    every_s = EVERY_H * 3600
    daemon = DaemonProcess(cell_file)
    daemon.extra_env.update(clock.env())
    with daemon.start(), daemon.client() as c:
        first = next_check(c, [])
        stepped(clock, +HOUR, lambda: schedule_wall(c))
        assert 0 < c.get("/cell").json()["health_schedule"]["due_in_s"] <= every_s
        second = next_check(c, [first])
        # not at once, though the wall clock says it is an hour late: every_h after the first by the monotonic
        # clock, so the stamps (wall clock) differ by that and the step
        assert stamp_s(second["created"]) - stamp_s(first["created"]) - HOUR >= every_s - SLACK_S
        stepped(clock, -HOUR, lambda: schedule_wall(c))
        third = next_check(c, [first, second])  # not an hour later, as the wall clock would have it, but on time
        assert stamp_s(third["created"]) - stamp_s(second["created"]) + HOUR >= every_s - SLACK_S
        assert wait_for(c, third["id"], {"done", "faulted"})["state"] == "done"
        checks = scheduled_checks(c)[:3]  # (a fourth may be due by now)
        audit = [a for a in c.get("/audit").json()["audit"] if a["client"] == "schedule"][:3]

    assert [j["id"] for j in checks] == [first["id"], second["id"], third["id"]]
    assert [j["state"] for j in checks] == ["done"] * 3
    # each check audited once, in the order they were submitted, though the third is stamped before the second
    assert [a["target"] for a in audit] == [f"job {j['id']}" for j in checks], audit
    assert stamp_s(audit[2]["at"]) < stamp_s(audit[1]["at"])

    # a restart with the wall clock an hour back: the last check looks an hour ahead, the next is due every_h
    # after the start all the same (see cellctl/service/schedule.py)
    clock.step(-HOUR)
    again = DaemonProcess(cell_file)
    again.extra_env.update(clock.env())
    with again.start(), again.client() as c:
        assert 0 < c.get("/cell").json()["health_schedule"]["due_in_s"] <= every_s
        next_check(c, scheduled_checks(c), timeout=60)
