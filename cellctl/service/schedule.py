"""Calibration checks on a schedule (the cell file's `health:`): the daemon submits the routine that judges the
active calibrations (`calibration.routines.judging_routine`) by itself.

Only when the cell is idle (no job live or queued) and nobody holds the operator lock: a scheduled check never
waits behind, interrupts or overtakes anyone's work, and nothing moves that no job asked for. It is submitted
through the service like any other job, so it is validated and audited (as "schedule"). Due `every_h` hours
after the last check kept in the store (any check: the operator's count too), or at start with `at_start`.

Clocks: within one daemon run the schedule counts on the monotonic clock, so an NTP step of the wall clock
neither brings a check forward (twice in one interval) nor puts it off (skipped). Across a restart the last
check's stored time (wall clock) is all there is: the first wait is read from it once, at start, and bounded to
[0, every_h]. A wall step between runs can therefore at most make the first check come at once (the clock went
forward: one check, missed ones are not caught up) or no later than every_h after the start (it went back).
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import datetime, timezone

from calibration.routines import judging_routine

from cellctl.config import HealthSchedule
from cellctl.errors import ServiceError
from cellctl.service import Caller

log = logging.getLogger("cellctl.service.schedule")
WHO = "schedule"
POLL_S = 1.0


class CheckSchedule:
    """`monotonic` decides when a check is due; `wall` only reads the stored last check and shows the next one."""

    def __init__(self, config: HealthSchedule, service, worker, calstore, lock, poll_s: float = POLL_S,
                 monotonic=time.monotonic, wall=time.time):
        self.config, self.service, self.worker, self.calstore, self.lock = config, service, worker, calstore, lock
        self.poll_s = poll_s
        self._monotonic, self._wall = monotonic, wall
        self.every_s = config.every_h * 3600
        self.next_due = self._monotonic() + self._first_wait()  # monotonic
        self.last_job: int | None = None
        self.waiting_for = ""  # why a due check has not been submitted yet
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="cellctl-schedule", daemon=True)

    def _first_wait(self) -> float:
        """Seconds from now to the first check: the one place the wall clock counts (see the module's doc)."""
        if self.config.at_start:
            return 0.0
        checks = self.calstore.checks(limit=1)
        if not checks:
            return self.every_s
        last = datetime.strptime(checks[-1]["created"], "%Y-%m-%dT%H:%M:%S%z").timestamp()
        return min(max(last + self.every_s - self._wall(), 0.0), self.every_s)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def status(self) -> dict:
        due_in = max(self.next_due - self._monotonic(), 0.0)
        return {"every_h": self.config.every_h, "next_check": _iso(self._wall() + due_in),
                "due_in_s": round(due_in, 1), "last_job": self.last_job, "waiting_for": self.waiting_for or None}

    def _loop(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self.tick()
            except Exception:  # noqa: BLE001 - the schedule must outlive one bad tick
                log.exception("schedule: a tick failed")

    def tick(self, now: float | None = None) -> int | None:
        """Submit the check if it is due and the cell is free; the job id, else None. `now`: monotonic."""
        now = self._monotonic() if now is None else now
        if now < self.next_due:
            return None
        busy = self._busy()
        if busy:
            self.waiting_for = busy
            return None
        params = {"update": self.config.update}
        if self.config.targets:
            params["targets"] = ",".join(self.config.targets)
        try:
            job = self.service.submit(Caller(WHO, via="schedule: calibration check", credential="the daemon itself"),
                                     judging_routine(), params)
        except ServiceError as exc:  # the lock was taken, or a job submitted, between our look and the submit
            self.waiting_for = str(exc)
            return None
        self.last_job, self.waiting_for = job["id"], ""
        self.next_due = now + self.every_s
        log.info("scheduled check submitted", extra={"job": job["id"], "next_check": self.status()["next_check"]})
        return job["id"]

    def _busy(self) -> str:
        if self.worker.live_job is not None or self.service.jobs(state="queued"):
            return "a job is live or queued"
        if self.lock.status().get("held"):
            return "the operator lock is held"
        return ""


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
