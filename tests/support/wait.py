"""Waiting on an event, never on a sleep: `eventually(probe)` asks again until the probe says yes.

The one wait loop of the tests: a probe returns something truthy when the awaited thing has happened (returned
to the caller), or something falsy to be asked again; an AssertionError it raises fails at once (a state from
which the awaited one cannot come). Past `timeout` the test fails naming `what` and the probe's last answer."""

from __future__ import annotations

import time
from typing import Callable, TypeVar

T = TypeVar("T")


def eventually(probe: Callable[[], T], *, timeout: float = 60.0, every: float = 0.02,
               what: str | Callable[[], str] = "the awaited condition") -> T:
    """`what`: the awaited thing, said in the failure; a callable is asked then (to say the state it ended in)."""
    deadline = time.monotonic() + timeout
    while True:
        value = probe()
        if value:
            return value
        if time.monotonic() >= deadline:
            said = what() if callable(what) else what
            raise AssertionError(f"{said}: not within {timeout:g} s (last: {value!r})")
        time.sleep(every)
