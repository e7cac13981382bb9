"""The calibration-check schedule on injected clocks: within a run it is due by the monotonic clock whatever the wall
clock does (no check skipped, none run twice); across a restart the stored last check (wall clock) sets the first
wait, bounded to [0, every_h] so that a wall step between runs cannot put the next check off or bring on several."""

from __future__ import annotations

import time

import pytest

from cellctl.config import HealthSchedule
from cellctl.service.schedule import CheckSchedule

EVERY_H = 2.0
EVERY_S = EVERY_H * 3600
WALL_0 = 1_764_000_000.0  # 2025-11-24T16:00:00Z


class Clock:
    def __init__(self, now: float):
        self.now = now

    def __call__(self) -> float:
        return self.now


class Cell:
    """The service, worker, calibration store and lock the schedule looks at: an idle cell, a free lock."""

    def __init__(self, last_check_wall: float | None = None):
        self.live_job = None
        self.submitted: list[int] = []
        self.last = last_check_wall

    # the calibration store
    def checks(self, limit: int = 1000) -> list[dict]:
        if self.last is None:
            return []
        return [{"created": time.strftime("%Y-%m-%dT%H:%M:%S+0000", time.gmtime(self.last))}]

    # the service
    def jobs(self, state=None) -> list[dict]:
        return []

    def submit(self, caller, routine, params) -> dict:
        self.submitted.append(len(self.submitted) + 1)
        return {"id": self.submitted[-1]}

    # the lock
    def status(self) -> dict:
        return {"held": False}


def schedule(cell: Cell, monotonic: Clock, wall: Clock, at_start: bool = False) -> CheckSchedule:
    config = HealthSchedule(every_h=EVERY_H, at_start=at_start)
    return CheckSchedule(config, cell, cell, cell, cell, monotonic=monotonic, wall=wall)


def run(s: CheckSchedule, monotonic: Clock, wall: Clock, seconds: float, step_s: float = 1.0) -> None:
    """Both clocks go on together for `seconds`, the schedule ticking every `step_s`."""
    for _ in range(int(seconds / step_s)):
        monotonic.now += step_s
        wall.now += step_s
        s.tick()


@pytest.mark.parametrize("wall_step_s", [3600.0, -3600.0])
def test_a_wall_step_between_checks_neither_skips_one_nor_runs_one_twice(wall_step_s):
    monotonic, wall, cell = Clock(500.0), Clock(WALL_0), Cell()
    s = schedule(cell, monotonic, wall, at_start=True)
    s.tick()
    assert cell.submitted == [1]
    run(s, monotonic, wall, EVERY_S / 2)
    wall.now += wall_step_s  # NTP steps the clock an hour on (or back), half-way to the next check
    run(s, monotonic, wall, EVERY_S / 2 - 1)
    assert cell.submitted == [1]  # not brought forward by a step on
    run(s, monotonic, wall, 1)
    assert cell.submitted == [1, 2]  # nor put off by a step back: every_h after the last, by the monotonic clock
    run(s, monotonic, wall, EVERY_S - 1)
    assert cell.submitted == [1, 2]


def test_the_next_check_shown_to_people_follows_the_wall_clock():
    monotonic, wall, cell = Clock(500.0), Clock(WALL_0), Cell()
    s = schedule(cell, monotonic, wall)
    assert s.status()["due_in_s"] == EVERY_S and s.status()["next_check"] == "2025-11-24T18:00:00Z"
    wall.now += 3600.0
    assert s.status()["due_in_s"] == EVERY_S and s.status()["next_check"] == "2025-11-24T19:00:00Z"


def test_after_a_restart_the_first_check_is_due_every_h_after_the_stored_last_one():
    monotonic, wall = Clock(10.0), Clock(WALL_0)
    cell = Cell(last_check_wall=WALL_0 - 0.25 * EVERY_S)
    s = schedule(cell, monotonic, wall)
    assert s.status()["due_in_s"] == 0.75 * EVERY_S
    run(s, monotonic, wall, 0.75 * EVERY_S - 1)
    assert cell.submitted == []
    run(s, monotonic, wall, 1)
    assert cell.submitted == [1]


def test_a_wall_step_back_between_runs_delays_the_first_check_at_most_every_h():
    """The stored last check looks an hour in the future: due every_h after the start, not an hour more."""
    monotonic, wall = Clock(10.0), Clock(WALL_0)
    cell = Cell(last_check_wall=WALL_0 + 3600.0)
    s = schedule(cell, monotonic, wall)
    assert s.status()["due_in_s"] == EVERY_S
    run(s, monotonic, wall, EVERY_S)
    assert cell.submitted == [1]


def test_a_wall_step_on_between_runs_brings_one_check_not_the_missed_ones():
    monotonic, wall = Clock(10.0), Clock(WALL_0)
    cell = Cell(last_check_wall=WALL_0 - 10 * EVERY_S)  # the clock went on ten intervals while the daemon was down
    s = schedule(cell, monotonic, wall)
    s.tick()
    assert cell.submitted == [1]
    run(s, monotonic, wall, EVERY_S - 1)
    assert cell.submitted == [1]
    run(s, monotonic, wall, 1)
    assert cell.submitted == [1, 2]


def test_a_due_check_waits_for_a_busy_cell_and_is_then_run_once():
    monotonic, wall, cell = Clock(500.0), Clock(WALL_0), Cell()
    s = schedule(cell, monotonic, wall)
    cell.live_job = 7
    run(s, monotonic, wall, EVERY_S + 60)
    assert cell.submitted == [] and s.status()["waiting_for"] == "a job is live or queued"
    wall.now -= 3600.0
    cell.live_job = None
    run(s, monotonic, wall, 5)
    assert cell.submitted == [1] and s.status()["waiting_for"] is None
    assert s.status()["due_in_s"] == EVERY_S - 4
