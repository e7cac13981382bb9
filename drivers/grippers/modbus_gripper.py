"""What the Modbus vacuum grippers share: the link's lifecycle, the device state, and the
bookkeeping of a held object (VacuumLost is raised once, by the first call that sees it gone).

A subclass says how to wake the gripper up (`_start`, after the link opened) and how to read
its state (`_read`, which raises VacuumLost when `_holding` and the object is gone).
"""

from __future__ import annotations

from ..interfaces import ConnectionLost, DeviceState, NotConnected, VacuumLost
from .modbus_link import ModbusLink


class ModbusGripper:
    Settings: type  # a pydantic model with link_config()

    def __init__(self, name: str, settings):
        self.name = name
        self.settings = settings
        self.link = ModbusLink(name, settings.link_config())
        self._state = DeviceState.CREATED
        self._holding = False  # the last grip detected an object not released since

    @classmethod
    def create(cls, name: str, options: dict, context=None):
        return cls(name, cls.Settings(**options))

    @property
    def state(self) -> DeviceState:
        return self._state

    def connect(self) -> None:
        """Open the link and bring the gripper up (`_start`); a failure leaves the link closed."""
        self.link.close()
        self._holding = False
        try:
            self.link.open()
            self._start()
        except BaseException:
            self.link.close()
            raise
        self._state = DeviceState.READY

    def close(self) -> None:
        """Close the link. The gripper keeps its last command (a held part stays held)."""
        self.link.close()
        self._holding = False
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        """Nothing moves: a vacuum gripper is left as it is (dropping a held part is not 'safe')."""

    # -- for the subclasses ---------------------------------------------------------------
    def _start(self) -> None:
        raise NotImplementedError

    def _read(self):
        raise NotImplementedError

    def _ready(self) -> None:
        if self._state is DeviceState.FAULTED:
            raise ConnectionLost(f"{self.name}: the link is down; call connect() again before going on")
        if self._state is not DeviceState.READY:
            raise NotConnected(f"{self.name}: not connected (state {self._state.value}); call connect() first")

    def _lost_before_release(self) -> str | None:
        """Before a release: the VacuumLost message if the held object was gone already (the release
        still goes ahead, the caller raises it afterwards), else None."""
        if not self._holding:
            return None
        try:
            self._read()
        except VacuumLost as exc:
            return str(exc)
        finally:
            self._holding = False
        return None

    def _guarded(self, exchange):
        """Run one link exchange; a lost link faults the device (reconnect only when told)."""
        try:
            return exchange()
        except ConnectionLost:
            if self._state is DeviceState.READY:
                self._state = DeviceState.FAULTED
            raise
