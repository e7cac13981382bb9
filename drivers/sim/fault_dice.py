"""The dice of `sim.faults.random` (RandomFaults): one stream of draws per seed for the whole process.

Every simulated world a daemon builds (one per job, one per resumption) rolls the same stream, so the draws go
on where the last world left them: a fault that ended a job is not met again when the job resumes, and a soak's
faults fall on a seeded schedule that no single world replays. Count knobs (`arm_drop_after_moves`, ...) are
per world and re-fire on every resumption; these do not.
"""

from __future__ import annotations

import threading

import numpy as np

_streams: dict[int, np.random.Generator] = {}
_lock = threading.Lock()


def roll(seed: int) -> float:
    """The next draw in [0, 1) of `seed`'s stream."""
    with _lock:
        rng = _streams.get(seed)
        if rng is None:
            rng = _streams[seed] = np.random.default_rng([seed, 0xFA17])
        return float(rng.random())


# the faults each kind of call can meet, by their RandomFaults names, in the order a roll is laid against them
CALLS = {"move": ("link_drop", "protective_stop"), "capture": ("capture_timeout", "corrupt_frame"),
         "grip": ("vacuum_loss",)}


def drawn(random, call: str) -> str | None:
    """One roll of `random`'s stream (RandomFaults, or None: never) for a `call` (CALLS): the fault it falls on,
    or None. No roll when nothing can fire, so a cell without these faults leaves the stream alone."""
    if random is None:
        return None
    chances = [(fault, getattr(random, fault)) for fault in CALLS[call]]
    if not any(p for _, p in chances):
        return None
    r = roll(random.seed)
    for fault, p in chances:
        if r < p:
            return fault
        r -= p
    return None
