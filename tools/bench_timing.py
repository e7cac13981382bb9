"""Timing for the benchmarks (tools/bench_*.py): the best of several rounds, since the machine may be shared
and the best round is the least disturbed one. Timings are printed, never asserted."""

from __future__ import annotations

import time


def best_of(fn, rounds: int, number: int = 1) -> float:
    """Seconds per call: the best over `rounds` rounds of the mean time of `number` calls."""
    best = float("inf")
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - start) / number)
    return best
