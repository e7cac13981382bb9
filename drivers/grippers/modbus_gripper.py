"""What the Modbus vacuum grippers share: the link's lifecycle, the device state, and the
bookkeeping of a held object (VacuumLost is raised once, by the first call that sees it gone).

A subclass says how to wake the gripper up (`_start`, after the link opened) and how to read
its state (`_read`, which raises VacuumLost when `_holding` and the object is gone).
"""

from __future__ import annotations

import time

from drivers.grippers.modbus_link import ModbusLink
from drivers.interfaces import ConnectionLost, DeviceState, VacuumLost
from drivers.lifecycle import Driver


def detection_below_grip(settings, detect: str, grip: str):
    """The settings check of both grippers: the field `detect` (the level from which an object counts
    as held) must not exceed the field `grip` (the vacuum it grips with)."""
    if getattr(settings, detect) > getattr(settings, grip):
        raise ValueError(f"{detect} ({getattr(settings, detect)}) must not exceed {grip} "
                         f"({getattr(settings, grip)}): the gripper would never detect what it holds")
    return settings


class ModbusGripper(Driver):
    Settings: type  # a pydantic model with link_config()

    def __init__(self, name: str, settings):
        super().__init__(name, settings)
        self.link = ModbusLink(name, settings.link_config())
        self._holding = False  # the last grip detected an object not released since

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

    def _polled(self, timeout_s: float):
        """The gripper's state (`_read()`), read every poll interval: the caller leaves the loop once it
        has its answer; a loop that runs out has waited timeout_s in vain (its loop variable holds the
        last state read, as there is always one)."""
        deadline = time.monotonic() + timeout_s
        while True:
            yield self._read()
            if time.monotonic() >= deadline:
                return
            time.sleep(self.settings.poll_interval_s)

    def _guarded(self, exchange):
        """Run one link exchange; a lost link faults the device (reconnect only when told)."""
        try:
            return exchange()
        except ConnectionLost:
            if self._state is DeviceState.READY:
                self._state = DeviceState.FAULTED
            raise
