"""GenICam cameras (GigE Vision, USB3 Vision): `backend: genicam`, through harvesters or Aravis.

`library` chooses how the camera is reached (the options are `GenICamSettings`, in `_genicam.py`):

- `harvesters` (default): harvesters and a GenTL producer (.cti) from the camera maker's SDK
  (or, without hardware, the `genicam` wheel's `viky.cti`, a simulated camera). This module.
- `aravis`: GigE Vision through the Aravis library, no vendor SDK: `drivers/cameras/aravis.py`.
  `GenICamCamera.create` returns that driver for `library: aravis`.

Harvesters path: the device is chosen by serial number, model or index among those the producer
finds; `connect()` fails with the list of devices when none or several match. Features follow the
SFNC names (see `GenICamSettings`); a setting whose feature the camera lacks (viky has no
exposure, gain or trigger) is an error naming the setting and the feature, or, with `strict:
false`, a warning kept in `camera.refused` and the camera runs without it.

Capture: free-run drops the frames queued before the call and returns the next one to complete (a
frame exposed partly before the call can still come: use the software trigger where exact timing
matters); software trigger fires one frame per call. No frame within the time-out ->
`CaptureTimeout`; any other transport error -> `ConnectionLost` (the camera is FAULTED until
`connect()`). Mono formats give a 2-D array (8-bit as uint8, 10- to 16-bit as uint16 with the
camera's values), colour formats are converted to grayscale unless `color: native`. The device
timestamp is the buffer's (ns -> s) when the producer has one, else None.
"""

from __future__ import annotations

import contextlib
import os
import time
from typing import Any

from drivers.cameras._common import CameraSettingError, Grabbed
from drivers.cameras._genicam import DeviceInfo, Features, GenICamBase, GenICamSettings
from drivers.interfaces import CaptureTimeout, ConnectionLost, CorruptFrame

__all__ = ["GenICamCamera", "GenICamSettings"]


class GenICamCamera(GenICamBase):
    """A GenICam camera through harvesters (or, with `library: aravis`, see `create`)."""

    Settings = GenICamSettings

    @classmethod
    def create(cls, name: str, options: dict, context=None):
        """The harvesters driver, or the Aravis one (drivers/cameras/aravis.py) for `library: aravis`."""
        settings = cls.Settings(**options)
        if settings.library == "aravis":
            from drivers.cameras.aravis import AravisCamera  # gi is imported only when that camera connects

            return AravisCamera(name, settings)
        return cls(name, settings)

    def __init__(self, name: str, settings: GenICamSettings):
        super().__init__(name, settings)
        self._harvester = None
        self._acquirer = None

    # -- hooks -------------------------------------------------------------
    def _open(self) -> tuple[int, int]:
        from harvesters.core import (
            Harvester,  # vendor import only when this backend is used
        )

        s = self.settings
        if not os.path.isfile(s.producer):
            raise CameraSettingError(f"{self.name}: producer {s.producer!r}: no such GenTL producer file (.cti)")
        self._harvester = Harvester()
        self._harvester.add_file(s.producer, check_existence=True)
        self._harvester.update()
        infos = list(self._harvester.device_info_list)
        devices = [DeviceInfo(_info(d, "model"), _info(d, "serial_number"), _info(d, "id_")) for d in infos]
        chosen = self._choose_device(devices, f"from producer {s.producer!r}")
        self._acquirer = self._harvester.create(infos[chosen])
        self._acquirer.num_buffers = s.num_buffers
        self._configure(self._features())
        self._acquirer.start()
        nodes = self._acquirer.remote_device.node_map
        return int(nodes.Width.value), int(nodes.Height.value)

    def _features(self) -> Features:
        return _NodeMapFeatures(self._acquirer.remote_device.node_map)

    def _grab(self, timeout_s: float) -> Grabbed:
        from genicam.gentl import GenericException, TimeoutException

        acquirer = self._acquirer
        try:
            self._drop_queued()
            if self._software_trigger:
                acquirer.remote_device.node_map.TriggerSoftware.execute()
            buffer = acquirer.fetch(timeout=timeout_s)
        except TimeoutException:
            raise CaptureTimeout(f"{self.name}: no frame within {timeout_s:g} s; check the trigger, the cable "
                                 "and the frame rate") from None
        except GenericException as exc:
            raise self._fault(ConnectionLost(f"{self.name}: acquisition failed ({type(exc).__name__}: {exc}); "
                                             "check the camera link, then connect() again")) from exc
        host = time.monotonic()
        try:
            image, meta = self._decode(buffer)
            device_ts = _buffer_timestamp_s(buffer)
        finally:
            buffer.queue()
        return Grabbed(image, device_ts, host, self._exposure_s, meta)

    def _drop_queued(self) -> None:
        """Hand back frames that completed before this call (stale after a move); ~1 ms when none is queued."""
        while (stale := self._acquirer.try_fetch(timeout=1e-4)) is not None:
            stale.queue()

    def _decode(self, buffer):
        components = buffer.payload.components
        if not components:
            raise CorruptFrame(f"{self.name}: a buffer arrived with no image component")
        part = components[0]
        fmt = str(part.data_format)
        image = self._image(part.data, fmt, int(part.width), int(part.height))
        meta = self._meta(fmt)
        with contextlib.suppress(*_vendor_errors()):  # not every producer numbers its buffers
            meta["device_frame_id"] = int(buffer.module.frame_id)
        return image, meta

    def _release(self) -> None:
        if self._acquirer is not None:
            try:
                self._acquirer.stop()
            finally:
                self._acquirer.destroy()
                self._acquirer = None
        if self._harvester is not None:
            self._harvester.reset()
            self._harvester = None


class _NodeMapFeatures(Features):
    """Features through a harvesters node map (genicam's GenApi)."""

    def __init__(self, node_map):
        self._nodes = node_map
        self.errors = _vendor_errors()

    def has(self, name: str) -> bool:
        return bool(self._nodes.has_node(name))

    def get(self, name: str) -> Any:
        return getattr(self._nodes, name).value

    def set(self, name: str, value: Any) -> None:
        getattr(self._nodes, name).value = value

    def entries(self, name: str) -> list[str]:
        return [str(v) for v in getattr(self._nodes, name).symbolics]

    def execute(self, name: str) -> None:
        getattr(self._nodes, name).execute()


def _info(device_info, attribute: str) -> str | None:
    """A device-info field, None where the producer does not provide it (it raises then)."""
    try:
        value = getattr(device_info, attribute)
    except _vendor_errors():
        return None
    return None if value is None else str(value)


def _buffer_timestamp_s(buffer) -> float | None:
    """The buffer's device timestamp in seconds; None when the producer has none (viky)."""
    errors = _vendor_errors()
    with contextlib.suppress(*errors):
        return buffer.module.timestamp_ns * 1e-9
    try:  # producers without the ns field: ticks and the device's tick frequency
        ticks = buffer.module.timestamp
        frequency = buffer.module.parent.parent.timestamp_frequency
    except errors:
        return None
    return ticks / frequency if frequency else None


def _vendor_errors() -> tuple[type[BaseException], ...]:
    """What harvesters / genicam raise for an absent, unreadable or refused feature."""
    from genicam import genapi, gentl

    return (genapi.GenericException, gentl.GenericException, AttributeError, TypeError, ValueError)

