"""The operator at a terminal: instructions printed, the operator confirms with Enter."""

from __future__ import annotations

import sys

from pydantic import BaseModel, ConfigDict

from .interfaces import DeviceState, NotConnected


class ConsoleOperatorSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ConsoleOperator:
    Settings = ConsoleOperatorSettings

    def __init__(self, name: str, stdin=None, stdout=None):
        self.name = name
        self._in, self._out = stdin or sys.stdin, stdout or sys.stderr
        self._state = DeviceState.CREATED

    @classmethod
    def create(cls, name: str, options: dict, context) -> "ConsoleOperator":
        cls.Settings(**options)
        return cls(name)

    @property
    def state(self) -> DeviceState:
        return self._state

    def connect(self) -> None:
        self._state = DeviceState.READY

    def close(self) -> None:
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        pass

    def request(self, instruction: str, fixture: str | None = None, present: bool | None = None) -> None:
        if self._state is not DeviceState.READY:
            raise NotConnected(f"{self.name}: not connected")
        print(f"\nOPERATOR: {instruction}\nPress Enter when done.", file=self._out, flush=True)
        if not self._in.readline():
            raise NotConnected(f"{self.name}: no operator input (stdin closed); cannot go on")
