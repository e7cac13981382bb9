"""Job progress and state changes as a stream of numbered events (served as server-sent events).

The worker thread publishes; the publish is handed to the event loop, which keeps
the last events in a ring and wakes every waiting stream. A slow client costs the
worker nothing: it only ever appends to memory.
"""

from __future__ import annotations

import asyncio
import collections
import json
import threading
import time


class EventHub:
    def __init__(self, keep: int = 1000):
        self._events: collections.deque = collections.deque(maxlen=keep)
        self._seq = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._changed: asyncio.Event | None = None
        self._mutex = threading.Lock()

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        """Bind to the server's loop (called at start-up, inside it)."""
        self._loop = loop
        self._changed = asyncio.Event()

    def publish(self, kind: str, data: dict) -> None:
        """Thread-safe: record an event and wake the streams."""
        with self._mutex:
            self._seq += 1
            self._events.append((self._seq, kind, dict(data, at=time.time())))
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._wake)
            except RuntimeError:  # the loop is shutting down
                pass

    def _wake(self) -> None:
        changed, self._changed = self._changed, asyncio.Event()
        if changed is not None:
            changed.set()

    def since(self, seq: int) -> list[tuple[int, str, dict]]:
        with self._mutex:
            return [e for e in self._events if e[0] > seq]

    @property
    def last_seq(self) -> int:
        with self._mutex:
            return self._seq

    async def wait(self, timeout: float) -> None:
        changed = self._changed
        if changed is None:
            await asyncio.sleep(timeout)
            return
        try:
            await asyncio.wait_for(changed.wait(), timeout)
        except TimeoutError:
            pass


def sse(seq: int, kind: str, data: dict) -> str:
    return f"id: {seq}\nevent: {kind}\ndata: {json.dumps(data, allow_nan=False, default=str)}\n\n"
