"""UVC / V4L2 cameras, video files, streams and image sequences through OpenCV's `VideoCapture`.

`source` says what to open:

- a device index (`0`) or path (`/dev/video0`): a live camera (V4L2 on Linux);
- an image sequence, a pattern with a printf field (`frames/frame_%04d.png`), read with
  `cv2.CAP_IMAGES`, which keeps 8- and 16-bit grayscale PNGs as they are;
- a URL (`rtsp://…`, `tcp://…`): a network stream through FFMPEG;
- any other path: a video file through FFMPEG.

Exposure, gain, frame size and rate are set where the backend has them; what `set()`
returns is checked and the value read back, and a refused setting is an error naming
it (or a warning with `strict: false`). File sources end: `at_end: error` raises
`EndOfSource`, `loop` starts again.

Time-outs: V4L2 takes a read time-out per call; FFMPEG streams take one when opened
(`timeout_s`); a read that took longer than asked is reported as `CaptureTimeout`,
a read that failed at once on a live source as `ConnectionLost` (the camera is
FAULTED until `connect()`).

Timestamps: `host_timestamp_s` is `time.monotonic()` when the read returned;
`device_timestamp_s` is `CAP_PROP_POS_MSEC` where it means something (the V4L2
buffer time of a live camera, the media time of a video file), else None.
"""

from __future__ import annotations

import os
import re
import time
from typing import Literal

import cv2
from pydantic import BaseModel, ConfigDict, Field, field_validator

from drivers import endpoint
from drivers.cameras._common import CameraBase, CameraSettingError, EndOfSource, Grabbed, to_gray
from drivers.interfaces import CaptureTimeout, ConnectionLost

_APIS = {"auto": cv2.CAP_ANY, "v4l2": cv2.CAP_V4L2, "ffmpeg": cv2.CAP_FFMPEG, "images": cv2.CAP_IMAGES}


class UvcSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    source: int | str = Field(..., description="device index or /dev/videoN, image-sequence pattern "
                              "(frame_%04d.png), video file path or stream URL")
    api: Literal["auto", "v4l2", "ffmpeg", "images"] = Field(
        "auto", description="OpenCV backend; auto: images for a pattern, ffmpeg for files/URLs, v4l2 for devices")
    width: int | None = Field(None, ge=1, le=20000, description="frame width to ask a live camera for (px)")
    height: int | None = Field(None, ge=1, le=20000, description="frame height to ask a live camera for (px)")
    fps: float | None = Field(None, gt=0, le=10000, description="frame rate to ask a live camera for")
    exposure_s: float | None = Field(None, gt=0, le=10, description="manual exposure (V4L2 only: sets manual mode)")
    gain: float | None = Field(None, ge=0, description="CAP_PROP_GAIN, in the backend's own units")
    fourcc: str | None = Field(None, min_length=4, max_length=4, description="pixel format of a live camera, e.g. MJPG")
    color: Literal["gray", "bgr"] = Field("gray", description="gray: 2-D frames (8/16-bit kept); bgr: as decoded")
    at_end: Literal["error", "loop"] = Field("error", description="end of a file source: raise EndOfSource, or loop")
    timeout_s: float = Field(2.0, gt=0, le=600, description="read time-out given to a stream when it is opened")
    strict: bool = Field(True, description="a setting the backend refuses is an error (false: a warning)")

    @field_validator("source")
    @classmethod
    def _not_empty(cls, value):
        if isinstance(value, str) and not value.strip():
            raise ValueError("source: empty; give a device index, /dev/videoN, a file, a pattern or a URL")
        if isinstance(value, int) and value < 0:
            raise ValueError(f"source: device index must be >= 0, got {value}")
        return value

    def endpoints(self) -> list[str]:
        """A /dev/video device; an index is not locked (it names no file), a file or stream is shared."""
        return [endpoint.device(self.source)] if str(self.source).startswith("/dev/") else []


class UvcCamera(CameraBase):
    """A camera (or a file standing in for one) read through OpenCV's VideoCapture."""

    Settings = UvcSettings

    def __init__(self, name: str, settings: UvcSettings):
        super().__init__(name, settings)
        self.kind = _source_kind(settings.source)  # device | sequence | stream | file
        self._cap: cv2.VideoCapture | None = None
        self._read_timeout_settable = False

    @property
    def is_file(self) -> bool:
        return self.kind in ("sequence", "file")

    # -- hooks -------------------------------------------------------------
    def _open(self) -> tuple[int, int]:
        s = self.settings
        source = s.source
        if isinstance(source, str) and source.isdigit():
            source = int(source)
        if self.kind == "sequence":
            _check_sequence(self.name, source)
        elif self.kind == "file" and not os.path.isfile(source):
            raise CameraSettingError(f"{self.name}: source {source!r}: no such video file")
        api = _APIS[s.api] if s.api != "auto" else {
            "sequence": cv2.CAP_IMAGES, "file": cv2.CAP_FFMPEG, "stream": cv2.CAP_FFMPEG, "device": cv2.CAP_ANY,
        }[self.kind]
        params = []
        if self.kind == "stream":  # FFMPEG takes its time-outs when it opens, not later
            ms = int(s.timeout_s * 1000)
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms]
        cap = cv2.VideoCapture(source, api, params)
        if not cap.isOpened():
            cap.release()
            hint = {"device": "no such camera, or it is busy", "sequence": "the pattern matched no readable image",
                    "file": "not a video OpenCV can decode", "stream": "nothing answered at that address"}[self.kind]
            raise CameraSettingError(f"{self.name}: source {s.source!r} could not be opened ({hint})")
        self._cap = cap
        if self.kind == "device":
            self._apply_live_settings()
        elif any(v is not None for v in (s.width, s.height, s.fps, s.exposure_s, s.gain, s.fourcc)):
            self._apply_live_settings()  # a file has none of them: each one is reported as refused
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if width <= 0 or height <= 0:  # some backends know the size only from a frame
            ok, image = cap.read()
            if not ok:
                raise CameraSettingError(f"{self.name}: source {s.source!r} opened but gave no frame")
            height, width = image.shape[:2]
            if self.is_file:
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._read_timeout_settable = self.kind == "device" and cap.set(
            cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(s.timeout_s * 1000))
        return width, height

    def _apply_live_settings(self) -> None:
        s, cap = self.settings, self._cap
        backend = cap.getBackendName()
        if s.fourcc is not None:
            self._set("fourcc", cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*s.fourcc))
        if s.width is not None:
            self._set("width", cv2.CAP_PROP_FRAME_WIDTH, s.width, readback=True)
        if s.height is not None:
            self._set("height", cv2.CAP_PROP_FRAME_HEIGHT, s.height, readback=True)
        if s.fps is not None:
            self._set("fps", cv2.CAP_PROP_FPS, s.fps)
        if s.exposure_s is not None:
            if backend == "V4L2":  # V4L2 manual exposure: auto mode 1, time in 100 µs steps
                self._set("exposure_s (auto exposure off)", cv2.CAP_PROP_AUTO_EXPOSURE, 1)
                self._set("exposure_s", cv2.CAP_PROP_EXPOSURE, s.exposure_s * 1e4)
            else:
                self._refused(f"exposure_s: the {backend} backend of source {s.source!r} has no exposure "
                              "control this driver knows the unit of", s.strict)
        if s.gain is not None:
            self._set("gain", cv2.CAP_PROP_GAIN, s.gain)
        if self.kind == "device":
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # fewer stale frames after a move; not every backend has it

    def _set(self, setting: str, prop: int, value: float, readback: bool = False) -> None:
        backend = self._cap.getBackendName()
        accepted = self._cap.set(prop, value)
        if accepted and readback:
            got = self._cap.get(prop)
            accepted = abs(got - value) < 1e-6
            detail = f"asked {value}, the camera gives {got:g}"
        else:
            detail = f"asked {value}"
        if not accepted:
            self._refused(f"{setting}: refused by the {backend} backend of source {self.settings.source!r} "
                          f"({detail})", self.settings.strict)

    # -- exposure and gain while it runs (drivers/cameras/live.py) ---------------
    def live_specs(self):
        """A live camera's gain (CAP_PROP_GAIN, the backend's units) and, through V4L2, its exposure_s; a file or
        stream has neither."""
        from drivers.cameras.live import LiveSetting

        self._ready()
        if self.kind != "device":
            return []
        specs = [LiveSetting("gain", "gain", "backend units", 0.0, 65535.0)]
        if self._cap.getBackendName() == "V4L2":
            specs.insert(0, LiveSetting("exposure_s", "exposure", "s", 1e-4, 10.0))
        return specs

    def live_values(self) -> dict:
        specs = self.live_specs()
        values = {}
        for spec in specs:
            if spec.key == "exposure_s":
                values["exposure_s"] = self._cap.get(cv2.CAP_PROP_EXPOSURE) * 1e-4  # V4L2: 100 µs steps
            else:
                values["gain"] = self._cap.get(cv2.CAP_PROP_GAIN)
        return values

    def set_live(self, values: dict) -> dict:
        from drivers.cameras.live import checked

        specs = self.live_specs()
        if not specs:
            raise CameraSettingError(f"{self.name}: source {self.settings.source!r} is a {self.kind}, which has no "
                                     "exposure or gain to change")
        values = checked(self.name, specs, values)
        for key, value in values.items():
            if key == "exposure_s":
                self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)
                accepted = self._cap.set(cv2.CAP_PROP_EXPOSURE, value * 1e4)
            else:
                accepted = self._cap.set(cv2.CAP_PROP_GAIN, value)
            if not accepted:
                raise CameraSettingError(f"{self.name}: {key}: refused by the {self._cap.getBackendName()} backend "
                                         f"of source {self.settings.source!r} (asked {value:g})")
        return self.live_values()

    def _grab(self, timeout_s: float) -> Grabbed:
        cap = self._cap
        if self._read_timeout_settable:
            cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(timeout_s * 1000))
        start = time.monotonic()
        ok, image = cap.read()
        elapsed = time.monotonic() - start
        if not ok and self.is_file:
            if self.settings.at_end == "loop" and cap.set(cv2.CAP_PROP_POS_FRAMES, 0):
                ok, image = cap.read()
            if not ok:
                raise EndOfSource(f"{self.name}: source {self.settings.source!r} has no frame left "
                                  "(set at_end: loop to play it again)")
        limit = timeout_s if self._read_timeout_settable or self.kind != "stream" else self.settings.timeout_s
        if not self.is_file and elapsed > limit * 0.95:
            raise CaptureTimeout(f"{self.name}: no frame within {limit:g} s from {self.settings.source!r}; "
                                 "check the camera, its cable and its frame rate")
        if not ok:
            raise self._fault(ConnectionLost(f"{self.name}: reading {self.settings.source!r} failed; the camera "
                                             "or stream is gone; reconnect it, then connect() again"))
        if self.settings.color == "gray":
            image = to_gray(image)
        pos_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
        device_ts = pos_ms * 1e-3 if pos_ms > 0 or (self.kind == "file" and pos_ms == 0) else None
        meta = {"source": str(self.settings.source)}
        if self.is_file:
            meta["source_index"] = int(cap.get(cv2.CAP_PROP_POS_FRAMES)) - 1
        return Grabbed(image, device_ts, meta=meta)

    def _release(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def _source_kind(source: int | str) -> str:
    if isinstance(source, int) or source.isdigit() or source.startswith("/dev/"):
        return "device"
    if "%" in source:
        return "sequence"
    if "://" in source:
        return "stream"
    return "file"


def _check_sequence(name: str, pattern: str) -> None:
    """CAP_IMAGES says only 'cannot open': name the pattern and what it should look like."""
    if len(re.findall(r"%0?\d*d", pattern)) != 1 or pattern.count("%") != 1:
        raise CameraSettingError(f"{name}: source {pattern!r}: an image-sequence pattern needs one integer field "
                                 "such as frame_%04d.png")
    first = [pattern % i for i in range(5)]
    if not any(os.path.isfile(p) for p in first):
        raise CameraSettingError(f"{name}: source {pattern!r}: no image matches it (looked for {first[0]} … {first[-1]})")
