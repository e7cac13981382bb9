"""GenICam cameras (GigE Vision, USB3 Vision) through `harvesters` and a GenTL producer (.cti).

The producer file comes from the camera maker's SDK (or, without hardware, the
`genicam` wheel's `viky.cti`, a simulated camera). The device is chosen by serial
number, model or index among those the producer finds; `connect()` fails with the
list of devices when none or several match.

Features follow the SFNC names: `PixelFormat`, `Width`/`Height`,
`AcquisitionFrameRate`, `ExposureTime` (µs; older GigE cameras `ExposureTimeAbs`),
`Gain` (dB), `TriggerMode`/`TriggerSource`/`TriggerSoftware`. A setting whose
feature the camera lacks (viky has no exposure, gain or trigger) is an error
naming the setting and the feature, or, with `strict: false`, a warning kept in
`camera.refused` and the camera runs without it.

Capture: free-run drops the frames queued before the call and returns the next one
to complete (a frame exposed partly before the call can still come: use the
software trigger where exact timing matters); software trigger fires one frame per
call. No frame within the time-out -> `CaptureTimeout`; any other transport error
-> `ConnectionLost` (the camera is FAULTED until `connect()`). Mono formats give a
2-D array (8-bit as uint8, 10- to 16-bit as uint16 with the camera's values), colour
formats are converted to grayscale unless `color: native`. The device timestamp
is the buffer's (ns -> s) when the producer has one, else None.
"""

from __future__ import annotations

import contextlib
import os
import time
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ..interfaces import CaptureTimeout, ConnectionLost, CorruptFrame
from ._common import CameraBase, CameraSettingError, Grabbed, to_gray

# pixel format -> (channels, channel order for grayscale conversion); packed and Bayer formats are not handled
_FORMATS = {
    "Mono8": (1, None), "Mono10": (1, None), "Mono12": (1, None), "Mono14": (1, None), "Mono16": (1, None),
    "RGB8": (3, "rgb"), "BGR8": (3, "bgr"), "RGBa8": (4, "rgb"), "BGRa8": (4, "bgr"),
}


class GenICamSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    producer: str = Field(..., description="path of the GenTL producer (.cti) of the camera's SDK")
    serial: str | None = Field(None, description="device serial number (as the producer lists it)")
    model: str | None = Field(None, description="device model name")
    index: int | None = Field(None, ge=0, description="position among the matching devices (default: the only one)")
    pixel_format: str | None = Field(None, description=f"PixelFormat to set; handled: {', '.join(_FORMATS)}")
    color: Literal["gray", "native"] = Field("gray", description="gray: 2-D frames; native: as the format has them")
    width: int | None = Field(None, ge=1, le=65535, description="Width feature (px)")
    height: int | None = Field(None, ge=1, le=65535, description="Height feature (px)")
    frame_rate_hz: float | None = Field(None, gt=0, le=10000, description="AcquisitionFrameRate (free-run)")
    exposure_s: float | None = Field(None, gt=0, le=60, description="ExposureTime (sets ExposureAuto Off)")
    gain_db: float | None = Field(None, ge=0, le=60, description="Gain (sets GainAuto Off)")
    trigger: Literal["free-run", "software"] = Field("free-run", description="software: one frame per capture()")
    num_buffers: int = Field(4, ge=1, le=64, description="buffers announced to the producer")
    strict: bool = Field(True, description="a setting the camera lacks is an error (false: a warning)")


class GenICamCamera(CameraBase):
    """A GenICam camera through harvesters."""

    Settings = GenICamSettings

    def __init__(self, name: str, settings: GenICamSettings):
        super().__init__(name, settings)
        self._harvester = None
        self._acquirer = None
        self._format: str | None = None
        self._software_trigger = False
        self._exposure_s: float | None = None

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
        info = self._choose_device(self._harvester.device_info_list)
        self._acquirer = self._harvester.create(info)
        self._acquirer.num_buffers = s.num_buffers
        self._configure(self._acquirer.remote_device.node_map)
        self._acquirer.start()
        nodes = self._acquirer.remote_device.node_map
        return int(nodes.Width.value), int(nodes.Height.value)

    def _choose_device(self, devices):
        s = self.settings

        def describe(d):
            return f"{_info(d, 'model')} serial {_info(d, 'serial_number')} ({_info(d, 'id_')})"

        listed = "; ".join(f"[{i}] {describe(d)}" for i, d in enumerate(devices)) or "none"
        matches = [d for d in devices
                   if (s.serial is None or _info(d, "serial_number") == s.serial)
                   and (s.model is None or _info(d, "model") == s.model)]
        asked = ", ".join(f"{k} {v!r}" for k, v in (("serial", s.serial), ("model", s.model)) if v is not None)
        if not matches:
            raise CameraSettingError(f"{self.name}: no device with {asked or 'any settings'} from producer "
                                     f"{s.producer!r}; found: {listed}")
        if s.index is not None:
            if s.index >= len(matches):
                raise CameraSettingError(f"{self.name}: index {s.index} but only {len(matches)} matching "
                                         f"device(s); found: {listed}")
            return matches[s.index]
        if len(matches) > 1:
            raise CameraSettingError(f"{self.name}: {len(matches)} devices match ({asked or 'no serial/model/index'}"
                                     f"); set serial, model or index; found: {listed}")
        return matches[0]

    def _configure(self, nodes) -> None:
        s = self.settings
        strict = s.strict
        if s.pixel_format is not None:
            if s.pixel_format not in _FORMATS:
                raise CameraSettingError(f"{self.name}: pixel_format {s.pixel_format!r} is not handled; "
                                         f"allowed: {', '.join(_FORMATS)}")
            offered = list(nodes.PixelFormat.symbolics) if nodes.has_node("PixelFormat") else []
            if s.pixel_format in offered:
                nodes.PixelFormat.value = s.pixel_format
            else:
                self._refused(f"pixel_format: the camera offers {', '.join(offered) or 'no PixelFormat'}, "
                              f"not {s.pixel_format!r}", strict)
        self._format = str(nodes.PixelFormat.value) if nodes.has_node("PixelFormat") else "Mono8"
        if self._format not in _FORMATS:
            raise CameraSettingError(f"{self.name}: the camera delivers PixelFormat {self._format!r}, which this "
                                     f"driver does not convert; set pixel_format to one of {', '.join(_FORMATS)}")
        for setting, feature, value in (("width", "Width", s.width), ("height", "Height", s.height)):
            if value is not None:
                self._write(nodes, setting, [feature], value)
        if s.frame_rate_hz is not None:
            self._write(nodes, "frame_rate_hz", ["AcquisitionFrameRateEnable"], True, quiet=True)
            self._write(nodes, "frame_rate_hz", ["AcquisitionFrameRate", "AcquisitionFrameRateAbs"], s.frame_rate_hz)
        if s.exposure_s is not None:
            self._write(nodes, "exposure_s", ["ExposureAuto"], "Off", quiet=True)
            self._write(nodes, "exposure_s", ["ExposureTime", "ExposureTimeAbs"], s.exposure_s * 1e6)
        self._exposure_s = None  # what the camera says it exposes, not what was asked
        for feature in ("ExposureTime", "ExposureTimeAbs"):
            if nodes.has_node(feature):
                with contextlib.suppress(*_vendor_errors()):  # unreadable on some cameras: leave it unknown
                    self._exposure_s = float(getattr(nodes, feature).value) * 1e-6
                break
        if s.gain_db is not None:
            self._write(nodes, "gain_db", ["GainAuto"], "Off", quiet=True)
            self._write(nodes, "gain_db", ["Gain", "GainRaw"], s.gain_db)
        if s.trigger == "software":
            self._write(nodes, "trigger", ["TriggerSelector"], "FrameStart", quiet=True)
            ok = self._write(nodes, "trigger", ["TriggerMode"], "On")
            ok = ok and self._write(nodes, "trigger", ["TriggerSource"], "Software")
            if ok and not nodes.has_node("TriggerSoftware"):
                self._refused("trigger: the camera has no TriggerSoftware command", strict)
                ok = False
            self._software_trigger = ok
        else:
            self._write(nodes, "trigger", ["TriggerMode"], "Off", quiet=True)
            self._software_trigger = False

    def _write(self, nodes, setting: str, features: list[str], value, quiet: bool = False) -> bool:
        """Set the first of `features` the camera has; report (unless quiet) when none can take the value."""
        for feature in features:
            if not nodes.has_node(feature):
                continue
            try:
                getattr(nodes, feature).value = value
                return True
            except _vendor_errors() as exc:  # out of range, read-only, wrong type: the camera says why
                if not quiet:
                    self._refused(f"{setting}: {feature} refused {value!r} ({type(exc).__name__}: {exc})",
                                  self.settings.strict)
                return False
        if not quiet:
            self._refused(f"{setting}: the camera has no {' or '.join(features)} feature", self.settings.strict)
        return False

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

    def _decode(self, buffer) -> tuple[np.ndarray, dict]:
        components = buffer.payload.components
        if not components:
            raise CorruptFrame(f"{self.name}: a buffer arrived with no image component")
        part = components[0]
        fmt = str(part.data_format)
        if fmt not in _FORMATS:
            raise CorruptFrame(f"{self.name}: a frame arrived in PixelFormat {fmt!r}; expected {self._format!r}")
        channels, order = _FORMATS[fmt]
        width, height = int(part.width), int(part.height)
        data = part.data
        if data.size != width * height * channels:
            raise CorruptFrame(f"{self.name}: frame holds {data.size} values, expected {width}x{height}x{channels}")
        image = np.array(data.reshape(height, width, channels) if channels > 1 else data.reshape(height, width))
        if channels > 1 and self.settings.color == "gray":
            image = to_gray(image, order)
        meta = {"pixel_format": fmt}
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
