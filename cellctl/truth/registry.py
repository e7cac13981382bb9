"""Which function judges a routine's result against the simulated world's hidden truth, by routine name.

The truth modules (truth.py, truth_csm.py, truth_vr.py) register theirs with `@truth_of(name)`; runs.py
imports them and looks the functions up in TRUTH. A function takes (world, devices, params, samples,
outcome) and returns the `truth` section of the result (JSON-safe)."""

from __future__ import annotations

from typing import Callable

TRUTH: dict[str, Callable[..., dict]] = {}


def truth_of(*routines: str):
    """Register the decorated function as the truth of these routines."""

    def register(function):
        for name in routines:
            if name in TRUTH:
                raise ValueError(f"routine {name!r} has a truth function already: {TRUTH[name].__qualname__}")
            TRUTH[name] = function
        return function

    return register
