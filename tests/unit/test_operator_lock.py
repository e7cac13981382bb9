"""The operator lock on injected clocks: its expiry follows the monotonic clock whatever the wall clock does, and
breaking it frees it, tells its holder (by whom, why) and is refused with nobody to break."""

from __future__ import annotations

import pytest

from cellctl.errors import Conflict
from cellctl.service.auth import LockBroken, LockHeld, OperatorLock


class Clock:
    def __init__(self, now: float):
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clocks():
    return Clock(1000.0), Clock(1_764_000_000.0)  # monotonic, wall


@pytest.fixture
def lock(clocks):
    monotonic, wall = clocks
    return OperatorLock(monotonic=monotonic, wall=wall)


@pytest.mark.parametrize("step_s", [3600.0, -3600.0])
def test_a_wall_clock_step_neither_ends_the_lock_early_nor_keeps_it_late(lock, clocks, step_s):
    monotonic, wall = clocks
    info = lock.acquire("anna", ttl_s=30.0)
    wall.now += step_s  # NTP, or a person, sets the clock an hour on (or back)
    monotonic.now += 29.0
    assert lock.status()["held"] and lock.status()["expires_in_s"] == 1.0
    with pytest.raises(LockHeld):
        lock.check(None)
    lock.check(info.lock_id)
    monotonic.now += 1.0  # 30 s after it was taken, by the clock that cannot step
    assert lock.status() == {"held": False}
    lock.check(None)


def test_times_shown_to_people_are_on_the_wall_clock(lock, clocks):
    monotonic, wall = clocks
    lock.acquire("anna", ttl_s=30.0)
    monotonic.now += 10.0
    wall.now += 10.0
    status = lock.status()
    assert status["acquired"] == wall.now - 10.0 and status["expires"] == wall.now + 20.0
    assert status["expires_in_s"] == 20.0


def test_a_renewal_extends_from_now(lock, clocks):
    monotonic, _ = clocks
    info = lock.acquire("console-1", ttl_s=30.0)
    for _ in range(5):  # a heartbeat every 10 s keeps a 30 s lease for as long as it beats
        monotonic.now += 10.0
        assert lock.acquire("console-1", 30.0, info.lock_id).lock_id == info.lock_id
    monotonic.now += 29.0
    assert lock.status()["holder"] == "console-1"
    monotonic.now += 1.0
    assert not lock.status()["held"]


def test_a_lock_in_use_is_not_broken_a_stale_one_is(clocks):
    monotonic, wall = clocks
    lock = OperatorLock(monotonic=monotonic, wall=wall, break_after_idle_s=60.0)
    info = lock.acquire("anna", ttl_s=600.0)
    monotonic.now += 59.0
    with pytest.raises(Conflict, match=r"in use: its holder renewed it or commanded with it 59 s ago.*in 1 s"):
        lock.break_lock("bob@pc", "gone for lunch?")
    lock.check(info.lock_id)  # a command with it: its holder is at work, idle counts from now
    monotonic.now += 59.0
    with pytest.raises(Conflict, match="in use"):
        lock.break_lock("bob@pc", "gone for lunch?")
    with pytest.raises(LockHeld):
        lock.check(None)  # another client's refused command does not count as the holder's use
    lock.acquire("anna", 600.0, info.lock_id)  # a renewal counts as use
    monotonic.now += 59.0
    with pytest.raises(Conflict, match="in use"):
        lock.break_lock("bob@pc", "gone for lunch?")
    wall.now -= 3600.0  # a wall-clock step makes it no staler
    with pytest.raises(Conflict, match="in use"):
        lock.break_lock("bob@pc", "gone for lunch?")
    monotonic.now += 1.0
    assert lock.break_lock("bob@pc", "gone for lunch").holder == "anna"


def test_breaking_frees_the_lock_and_tells_its_holder(lock, clocks):
    monotonic, _ = clocks
    info = lock.acquire("console-1", ttl_s=300.0)
    with pytest.raises(LockHeld, match="only its holder can release it.*lock break --reason"):
        lock.release(None)
    monotonic.now += lock.break_after_idle_s  # stale: neither renewed nor used since
    broken = lock.break_lock("bob@pc", "tab left open on line 3")
    assert (broken.holder, broken.by, broken.reason) == ("console-1", "bob@pc", "tab left open on line 3")
    assert lock.status() == {"held": False}
    lock.check(None)  # anyone may command again
    # the holder's next command, and its heartbeat's renewal, are refused saying who broke it and why
    for attempt in (lambda: lock.check(info.lock_id), lambda: lock.acquire("console-1", 30.0, info.lock_id)):
        with pytest.raises(LockBroken, match="broken by bob@pc at .*: tab left open on line 3") as refused:
            attempt()
        assert isinstance(refused.value, LockHeld) and refused.value.broken is broken
    assert lock.status() == {"held": False}  # the refused renewal took nothing back
    # taken again without the broken id, it is an ordinary lock
    again = lock.acquire("console-1", ttl_s=30.0)
    assert again.lock_id != info.lock_id
    lock.check(again.lock_id)


def test_nothing_to_break(lock, clocks):
    monotonic, _ = clocks
    with pytest.raises(Conflict, match="nobody holds"):
        lock.break_lock("bob@pc", "why not")
    lock.acquire("anna", ttl_s=5.0)
    monotonic.now += 5.0
    with pytest.raises(Conflict, match="nobody holds"):  # lapsed: free, nothing to break
        lock.break_lock("bob@pc", "why not")


def test_only_the_last_breaks_are_remembered(lock, clocks):
    monotonic, _ = clocks
    ids = []
    for n in range(OperatorLock.BROKEN_KEPT + 1):
        ids.append(lock.acquire(f"h{n}", 600.0).lock_id)
        monotonic.now += lock.break_after_idle_s
        lock.break_lock("bob", "stale")
    lock.check(ids[0])  # the oldest is forgotten: its id is just not the lock's
    with pytest.raises(LockBroken):
        lock.check(ids[1])


def test_a_command_without_a_lock_id_is_told_how_to_present_one(lock):
    """The usual slip: `cellctl lock acquire`, then a command without the printed `export CELLCTL_LOCK=...`."""
    held = lock.acquire("root@vm", 600.0)
    for refused in (lambda: lock.check(None), lambda: lock.acquire("root@vm", 600.0)):
        with pytest.raises(LockHeld, match="presented no lock id.*export CELLCTL_LOCK="):
            refused()
    with pytest.raises(LockHeld) as wrong:  # another client's id: no such hint, it is not theirs
        lock.check("someone-elses")
    assert "presented no lock id" not in str(wrong.value)
    lock.check(held.lock_id)
