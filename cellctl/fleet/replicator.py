"""The replicator: one thread per sink drains the stores' outboxes to it, in order, with back-off while it is down.

A sink takes a batch of records whole or raises `SinkDown`; only then does its cursor move, so a record reaches
each sink at least once, and the sink's own keys make the second time a no-op (the plant database) or a
duplicate its subscribers can tell by the record's id (the event stream). Nothing here blocks the cell: the
stores only ever append to their outbox.
"""

from __future__ import annotations

import logging
import random
import threading
import time
from typing import Protocol

from cellctl.stores.outbox import Outbox, Record

log = logging.getLogger("cellctl.fleet")

BATCH = 500
BACKOFF_S = (0.5, 15.0)  # first wait after a failure, longest wait


class SinkDown(Exception):
    """The sink cannot take records now (unreachable, refused, timed out): try again later. The message names
    what failed and never holds a credential."""


class Sink(Protocol):
    name: str  # "postgres", "mqtt": the outbox cursor's name
    info: dict  # what the sink says of the cell besides its records: description, software_revision, api_url

    def connect(self) -> None:
        """(Re)open the link; SinkDown if it cannot."""

    def deliver(self, records: list[Record]) -> None:
        """Take the records (kinds it does not carry are skipped), all or nothing; SinkDown if not."""

    def heartbeat(self) -> None:
        """Say the cell is alive (between records); SinkDown if the link is down."""

    def close(self, graceful: bool) -> None:
        """Drop the link; graceful: the cell is stopping, say so (offline) first, best effort."""


class Replicator:
    def __init__(self, outboxes: list[Outbox], sinks: list[Sink], heartbeat_s: float = 10.0, poll_s: float = 1.0):
        self.outboxes, self.sinks = outboxes, sinks
        self.heartbeat_s, self.poll_s = heartbeat_s, poll_s
        self.names = tuple(s.name for s in sinks)
        self._wake = {s.name: threading.Event() for s in sinks}
        self._stopping = threading.Event()
        self._threads = [threading.Thread(target=self._loop, args=(s,), name=f"cellctl-fleet-{s.name}", daemon=True)
                         for s in sinks]
        self.up: dict[str, bool] = {s.name: False for s in sinks}
        self.delivered: dict[str, int] = {s.name: 0 for s in sinks}

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def wake(self) -> None:
        """A store committed a record: every sink looks now instead of at its next poll."""
        for event in self._wake.values():
            event.set()

    def backlog(self) -> dict[str, int]:
        return {s: sum(o.backlog(s) for o in self.outboxes) for s in self.names}

    def stop(self, drain_s: float = 3.0) -> None:
        """Deliver what is pending for up to `drain_s`, then say offline and close each sink."""
        deadline = time.monotonic() + drain_s
        while time.monotonic() < deadline and any(self.backlog().values()) and any(self.up.values()):
            self.wake()
            time.sleep(0.05)
        self._stopping.set()
        self.wake()
        for t in self._threads:
            t.join(10)
        for outbox in self.outboxes:
            outbox.close()

    # -- one sink's thread ----------------------------------------------------------------

    def _loop(self, sink: Sink) -> None:
        backoff = BACKOFF_S[0]
        next_beat = 0.0
        wake = self._wake[sink.name]
        said = ""  # the last failure logged: a sink that stays down with the same error is logged once
        while not self._stopping.is_set():
            try:
                if not self.up[sink.name]:
                    sink.connect()
                    self.up[sink.name] = True
                    log.info("fleet sink connected", extra={"sink": sink.name})
                    backoff, said = BACKOFF_S[0], ""
                wake.clear()
                moved = self._drain(sink)
                if time.monotonic() >= next_beat:
                    sink.heartbeat()
                    next_beat = time.monotonic() + self.heartbeat_s
                if not moved:
                    wake.wait(min(self.poll_s, max(next_beat - time.monotonic(), 0.01)))
            except SinkDown as exc:
                if str(exc) != said:
                    log.warning("fleet sink down; records are kept and sent when it is back",
                                extra={"sink": sink.name, "error": str(exc), "retry_s": backoff})
                    said = str(exc)
                self.up[sink.name] = False
                self._close(sink, graceful=False)
                # jittered: cells that lost the plant together do not all come back at the same instant
                self._stopping.wait(backoff * random.uniform(0.5, 1.0))
                backoff = min(backoff * 2, BACKOFF_S[1])
            except Exception:  # noqa: BLE001 - a bug in a sink must not end replication for good
                log.exception("fleet sink failed", extra={"sink": sink.name})
                self.up[sink.name] = False
                self._close(sink, graceful=False)
                self._stopping.wait(BACKOFF_S[1])
        self._close(sink, graceful=True)
        self.up[sink.name] = False

    def _drain(self, sink: Sink) -> int:
        moved = 0
        for outbox in self.outboxes:
            records = outbox.pending(sink.name, BATCH)
            if not records:
                continue
            sink.deliver(records)
            outbox.mark(sink.name, records[-1].seq, self.names)
            self.delivered[sink.name] += len(records)
            moved += len(records)
        return moved

    @staticmethod
    def _close(sink: Sink, graceful: bool) -> None:
        try:
            sink.close(graceful)
        except Exception:  # noqa: BLE001 - closing is best effort
            log.debug("closing a fleet sink", exc_info=True)
