"""What every real driver (and the sim fakes' base) shares of the lifecycle in `drivers.interfaces`:
it is built from the cell file's options without touching hardware (`create`), it has a state
(CREATED -> READY -> CLOSED, FAULTED after a lost link), and every call checks it is READY first."""

from __future__ import annotations

from drivers.interfaces import DeviceState, require_ready


class Driver:
    Settings: type  # the pydantic model of the device's cell file options
    # what ConnectionLost says after a lost link: what went down and what to do
    LINK_LOST = "the link is down; call connect() again before going on"

    def __init__(self, name: str, settings):
        self.name = name
        self.settings = settings
        self._state = DeviceState.CREATED

    @classmethod
    def create(cls, name: str, options: dict, context=None):
        """Built from the cell file's options without touching hardware (`context` is for sim backends)."""
        return cls(name, cls.Settings(**options))

    @property
    def state(self) -> DeviceState:
        return self._state

    def _ready(self) -> None:
        require_ready(self.name, self._state, self.LINK_LOST)
