"""What the real camera drivers share: the lifecycle, frame numbering, grayscale conversion.

Each backend (genicam, uvc, oak) subclasses `CameraBase` and provides `_open()`,
`_grab(timeout_s)` and `_release()`; this class keeps the state machine of
`drivers.interfaces` (CREATED -> READY -> CLOSED, FAULTED after a lost link) and
numbers frames so `Frame.frame_id` always rises, whatever the device counts.
No vendor SDK is imported here.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np

from drivers.interfaces import (
    CaptureTimeout,
    DeviceError,
    DeviceState,
    Frame,
)
from drivers.lifecycle import Driver


class EndOfSource(CaptureTimeout):
    """A file source (video, image sequence, replay) has no frame left: retrying will not help."""


@dataclass
class Grabbed:
    """One image as a backend got it, before it becomes a Frame."""

    image: np.ndarray
    device_timestamp_s: float | None = None
    host_timestamp_s: float | None = None  # None: taken when the grab returned
    exposure_s: float | None = None
    meta: dict = field(default_factory=dict)


def to_gray(image: np.ndarray, channel_order: str = "bgr") -> np.ndarray:
    """A 2-D grayscale image (uint8 / uint16 kept) from a gray, BGR(A) or RGB(A) array.

    OpenCV's integer weights sum to one exactly, so a colour image whose channels are
    equal (a gray source stored as colour) comes back with its original values."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"cannot make a grayscale image from an array of shape {image.shape}")
    alpha = image.shape[2] == 4
    code = {("bgr", False): cv2.COLOR_BGR2GRAY, ("bgr", True): cv2.COLOR_BGRA2GRAY,
            ("rgb", False): cv2.COLOR_RGB2GRAY, ("rgb", True): cv2.COLOR_RGBA2GRAY}[(channel_order, alpha)]
    return cv2.cvtColor(image, code)


class CameraBase(Driver):
    """Lifecycle and frame numbering for a real camera; backends fill in the three hooks."""

    LINK_LOST = "the link is down; reconnect the camera (connect()) before going on"

    def __init__(self, name: str, settings):
        super().__init__(name, settings)
        self._frame_id = 0
        self._resolution: tuple[int, int] | None = None
        self.refused: list[str] = []  # settings the device could not apply (strict: false)

    # -- hooks -------------------------------------------------------------
    def _open(self) -> tuple[int, int]:
        """Open the device and apply the settings; return (width, height) of its frames."""
        raise NotImplementedError

    def _grab(self, timeout_s: float) -> Grabbed:
        raise NotImplementedError

    def _release(self) -> None:
        """Free whatever _open took; must cope with a half-done _open."""

    # -- lifecycle ---------------------------------------------------------
    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the frames, as the device reports it once connected.

        Before that: the size the settings ask for, else (0, 0) -- not an exception, because
        `isinstance(camera, Camera)` reads this property on Python 3.11."""
        if self._resolution is not None:
            return self._resolution
        return self._asked_resolution() or (0, 0)

    def _asked_resolution(self) -> tuple[int, int] | None:
        width, height = getattr(self.settings, "width", None), getattr(self.settings, "height", None)
        return (width, height) if width and height else None

    def connect(self) -> None:
        if self._state is DeviceState.READY:
            return
        self._release()  # after a fault: start from a clean device
        self.refused = []
        try:
            self._resolution = tuple(int(v) for v in self._open())
        except BaseException:
            self._release()
            raise
        self._state = DeviceState.READY

    def close(self) -> None:
        self.stop()
        self._release()
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        """A camera has nothing moving to stop; always safe."""

    def capture(self, timeout_s: float = 2.0) -> Frame:
        self._ready()
        if not timeout_s > 0:
            raise ValueError(f"{self.name}: timeout_s must be positive, got {timeout_s}")
        grabbed = self._grab(timeout_s)
        host = grabbed.host_timestamp_s if grabbed.host_timestamp_s is not None else time.monotonic()
        self._frame_id += 1
        return Frame(grabbed.image, self.name, self._frame_id, grabbed.device_timestamp_s, host,
                     grabbed.exposure_s, grabbed.meta)

    def _fault(self, error: Exception) -> Exception:
        """Mark the link as down (the caller raises the returned error)."""
        self._state = DeviceState.FAULTED
        return error

    def _refused(self, message: str, strict: bool) -> None:
        """A setting the device cannot apply: an error when strict, else a kept warning."""
        if strict:
            raise CameraSettingError(f"{self.name}: {message} (set strict: false to go on without it)")
        self.refused.append(message)
        warnings.warn(f"{self.name}: {message}", CameraSettingWarning, stacklevel=3)


class CameraSettingError(DeviceError, ValueError):
    """A setting the camera refused or does not have (names the setting and the feature)."""


class CameraSettingWarning(UserWarning):
    """A setting the camera could not apply, with strict: false."""
