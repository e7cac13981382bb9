"""The operator at a terminal: instructions printed, the operator confirms with Enter.

The time the operator takes is cell time: on a simulated cell the world's clock counts it (a real
cell's wall clock does anyway). What was confirmed in a step is kept with the step's samples
(cellctl/core/orchestrator.py: `RecordsAnswers`), so a step replayed on resume does not ask again.
"""

from __future__ import annotations

import sys
import time

from pydantic import BaseModel, ConfigDict

from drivers.interfaces import DeviceError, DeviceState, NotConnected


class ConsoleOperatorSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ConsoleOperator:
    Settings = ConsoleOperatorSettings

    def __init__(self, name: str, stdin=None, stdout=None, context=None):
        self.name = name
        self._in, self._out = stdin or sys.stdin, stdout or sys.stderr
        self._context = context  # the cell's DriverContext: a simulated world's clock counts the waits
        self._state = DeviceState.CREATED
        self._answers: list[dict] = []  # confirmed since the step began
        self._replaying: list[dict] | None = None  # a replayed step's recorded confirmations

    @classmethod
    def create(cls, name: str, options: dict, context) -> "ConsoleOperator":
        cls.Settings(**options)
        return cls(name, context=context)

    @property
    def state(self) -> DeviceState:
        return self._state

    def connect(self) -> None:
        self._state = DeviceState.READY

    def close(self) -> None:
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        pass

    def begin_step(self) -> None:
        self._answers = []
        self._replaying = None

    def request(self, instruction: str, fixture: str | None = None, present: bool | None = None) -> None:
        if self._state is not DeviceState.READY:
            raise NotConnected(f"{self.name}: not connected")
        if self._replaying is not None:
            self._replay_one(instruction)
            return
        start = time.monotonic()
        print(f"\nOPERATOR: {instruction}\nPress Enter when done.", file=self._out, flush=True)
        if not self._in.readline():
            raise NotConnected(f"{self.name}: no operator input (stdin closed); cannot go on")
        waited = time.monotonic() - start
        self._count(waited)
        self._answers.append({"verb": "request", "instruction": instruction, "outcome": "answered",
                              "waited_s": waited})

    # -- answers kept with the samples ----------------------------------------------------------------

    def answers(self) -> list[dict]:
        return [dict(a) for a in self._answers]

    def replay(self, answers: list[dict] | None) -> None:
        """Confirm the replayed step's requests from these, asking nobody (None: ask as usual)."""
        self._replaying = None if answers is None else [dict(a) for a in answers]

    def recall(self, answers: list[dict]) -> None:
        """Nothing a confirmation at the terminal establishes outlives its step."""

    def _replay_one(self, instruction: str) -> None:
        rec = self._replaying.pop(0) if self._replaying else None
        if rec is None or rec.get("verb") != "request" or rec.get("instruction") != instruction:
            raise DeviceError(f"{self.name}: replaying a step of a resumed run, it asks {instruction!r} but the "
                              f"answers recorded with its samples have {rec!r}; the run cannot be resumed exactly")
        self._count(float(rec.get("waited_s") or 0.0))
        self._answers.append(rec)

    def _count(self, seconds: float) -> None:
        world = self._context.existing_world if self._context is not None else None
        if world is not None:
            world.clock.add_waited(seconds)
