"""Luxonis OAK cameras through depthai 3.x, or a recorded video replayed without a device.

With a device: a pipeline on it with a `Camera` node on the chosen board socket
(`CAM_A` colour, `CAM_B`/`CAM_C` mono on most models), one output at the chosen
size and rate (GRAY8 by default), read from a host queue; `capture()` drops the
frames queued before the call and waits for the next. `exposure_s`/`iso` set a
manual exposure through the node's initial control.

Without a device (`replay: path`): `dai.Pipeline(createImplicitDevice=False)` with a
`ReplayVideo` node, which runs on the host (depthai 3.12 starts host nodes in their
own threads at `pipeline.start()`); its output queue is read like a device's. It
plays what depthai's FFMPEG-based OpenCV decodes (FFV1, MJPEG, MPEG-4 in .avi/.mp4;
not PNG-in-AVI) as 8-bit frames, each with a sequence number and a device
timestamp that starts at 0 with the replay. The queue blocks the replay, so every
frame of the file comes out, in order, one per `capture()`. The replay always loops
(depthai stops the pipeline at the end of a file and drops what its queue still
holds), and the driver counts the file's frames: after the last one `EndOfSource`
(`at_end: error`), or the file again (`at_end: loop`).

`host_timestamp_s` is depthai's host timestamp (steady clock = `time.monotonic()`
on Linux); `device_timestamp_s` the frame's device timestamp; `meta` holds the
sequence number. depthai prints a USB warning when imported on a machine without
USB access: harmless for replay.
"""

from __future__ import annotations

import datetime
import os
import re
from typing import Literal

import cv2
from pydantic import BaseModel, ConfigDict, Field, field_validator

from drivers import endpoint
from drivers.cameras._common import CameraBase, CameraSettingError, EndOfSource, Grabbed
from drivers.interfaces import CaptureTimeout, ConnectionLost, CorruptFrame

SOCKETS = ("CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F", "CAM_G", "CAM_H")


class OakSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    replay: str | None = Field(None, description="video file to replay on the host instead of a device")
    device: str | None = Field(None, description="device id (MxId), IP address or USB name; default: the only one")
    socket: str = Field("CAM_A", description=f"board socket of the sensor; one of {', '.join(SOCKETS)}")
    resolution: tuple[int, int] | None = Field(None, description="(width, height) of the output; replay: "
                                               "default the video's size")
    fps: float | None = Field(None, gt=0, le=1000, description="frame rate; replay: default the video's")
    color: Literal["gray", "bgr"] = Field("gray", description="GRAY8 or BGR888i frames")
    exposure_s: float | None = Field(None, gt=0, le=1, description="manual exposure (device only)")
    trigger: Literal["free-run", "software"] = Field(
        "free-run", description="free-run: capture() takes the first frame after the call; software: refused "
                                "(depthai 3's Camera node streams and has no still output to fire)")
    iso: int = Field(400, ge=100, le=1600, description="sensitivity with a manual exposure")
    at_end: Literal["error", "loop"] = Field("error", description="end of a replayed file: EndOfSource, or loop")
    queue_size: int = Field(4, ge=1, le=64, description="frames the host queue holds")
    strict: bool = Field(True, description="a setting that does not apply is an error (false: a warning)")

    @field_validator("socket")
    @classmethod
    def _known_socket(cls, value: str) -> str:
        if value not in SOCKETS:
            raise ValueError(f"socket: {value!r} is not a board socket; allowed: {', '.join(SOCKETS)}")
        return value

    @field_validator("resolution")
    @classmethod
    def _positive(cls, value):
        if value is not None and (value[0] < 1 or value[1] < 1 or value[0] > 10000 or value[1] > 10000):
            raise ValueError(f"resolution: (width, height) between 1 and 10000 px, got {value}")
        return value

    def endpoints(self) -> list[str]:
        """A named device (MxId, IP address or USB name); a replay or "the only one" names nothing to lock."""
        return [endpoint.camera(self.device)] if self.device and not self.replay else []


class OakCamera(CameraBase):
    """An OAK camera (depthai 3.x) or its replay of a video file."""

    Settings = OakSettings

    def __init__(self, name: str, settings: OakSettings):
        super().__init__(name, settings)
        self._pipeline = None
        self._queue = None
        self._replay_frames: int | None = None
        self._delivered = 0
        self._control = None  # a device's camera control queue (exposure and ISO while it streams)
        self._live: dict = {}

    def _asked_resolution(self) -> tuple[int, int] | None:
        return self.settings.resolution

    # -- hooks -------------------------------------------------------------
    def _open(self) -> tuple[int, int]:
        import depthai as dai  # vendor import only when this backend is used

        s = self.settings
        if s.trigger == "software":  # told, before anything opens
            self._refused("trigger: an OAK camera streams (depthai 3 has no still-capture output here); "
                          "use trigger: free-run, where capture() drops stale frames and waits for the next", s.strict)
        frame_type = dai.ImgFrame.Type.GRAY8 if s.color == "gray" else dai.ImgFrame.Type.BGR888i
        if s.replay is not None:
            size = self._open_replay(dai, frame_type)
        else:
            size = self._open_device(dai, frame_type)
        self._pipeline.start()
        return size

    def _open_replay(self, dai, frame_type) -> tuple[int, int]:
        s = self.settings
        if not os.path.isfile(s.replay):
            raise CameraSettingError(f"{self.name}: replay {s.replay!r}: no such video file")
        probe = cv2.VideoCapture(s.replay)  # the size and rate before depthai opens it in its own thread
        width, height = int(probe.get(cv2.CAP_PROP_FRAME_WIDTH)), int(probe.get(cv2.CAP_PROP_FRAME_HEIGHT))
        video_fps = probe.get(cv2.CAP_PROP_FPS)
        frames = int(probe.get(cv2.CAP_PROP_FRAME_COUNT))
        probe.release()
        # At the end of a file depthai stops the pipeline and closes the queue with the frames still in it,
        # so a reader that fell behind would lose the last ones: the replay loops and the end is counted here.
        self._replay_frames = frames if frames > 0 else None
        self._delivered = 0
        if width <= 0 or height <= 0:
            raise CameraSettingError(f"{self.name}: replay {s.replay!r} is not a video that can be decoded")
        for setting in ("device", "exposure_s"):
            if getattr(s, setting) is not None:
                self._refused(f"{setting}: does not apply to a replayed video", s.strict)
        self._pipeline = dai.Pipeline(createImplicitDevice=False)
        replay = self._pipeline.create(dai.node.ReplayVideo)
        replay.setReplayVideoFile(s.replay)
        replay.setOutFrameType(frame_type)
        replay.setLoop(s.at_end == "loop" or self._replay_frames is not None)
        fps = s.fps or (video_fps if video_fps and video_fps > 0 else None)
        if fps:
            replay.setFps(float(fps))
        if s.resolution is not None:
            replay.setSize(*s.resolution)
            width, height = s.resolution
        # blocking: the replay waits for the reader, so no frame of the file is skipped
        self._queue = replay.out.createOutputQueue(maxSize=s.queue_size, blocking=True)
        return width, height

    def _open_device(self, dai, frame_type) -> tuple[int, int]:
        s = self.settings
        found = dai.Device.getAllAvailableDevices()  # quick look, before depthai's ~10 s search
        ids = [d.getDeviceId() for d in found]
        listed = ", ".join(f"{d.getDeviceId()} ({d.name})" for d in found) or "none"
        is_address = s.device is not None and re.fullmatch(r"\d+\.\d+\.\d+\.\d+", s.device)
        if s.device is not None and not is_address and s.device not in ids and s.device not in [d.name for d in found]:
            raise CameraSettingError(f"{self.name}: device {s.device!r} not found; OAK devices here: {listed}")
        if s.device is None and not found:
            raise CameraSettingError(f"{self.name}: no OAK device found (device not set); connect one, or set "
                                     "replay: to play a video file")
        try:
            device = dai.Device(dai.DeviceInfo(s.device)) if s.device is not None else dai.Device()
        except RuntimeError as exc:
            raise CameraSettingError(f"{self.name}: device {s.device or 'any'!r} could not be opened: {exc}") from exc
        self._pipeline = dai.Pipeline(device)
        camera = self._pipeline.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, s.socket))
        if s.exposure_s is not None:
            camera.initialControl.setManualExposure(round(s.exposure_s * 1e6), s.iso)
        self._live = {"exposure_s": s.exposure_s, "iso": s.iso}
        try:  # exposure and ISO changed while it streams (the live view): a control queue into the node
            self._control = camera.inputControl.createInputQueue()
        except (AttributeError, RuntimeError):  # a depthai without it: the settings stay as connected
            self._control = None
        width, height = s.resolution or (1280, 800)
        output = camera.requestOutput((width, height), frame_type, fps=s.fps)
        self._queue = output.createOutputQueue(maxSize=s.queue_size, blocking=False)
        return width, height

    # -- exposure and ISO while it streams (drivers/cameras/live.py) -------------
    def live_specs(self):
        """A device's exposure_s and iso (set together, as a manual exposure); a replayed video has neither."""
        from drivers.cameras.live import LiveSetting

        self._ready()
        if self.settings.replay is not None or self._control is None:
            return []
        return [LiveSetting("exposure_s", "exposure", "s", 1e-6, 1.0),
                LiveSetting("iso", "gain", "ISO", 100, 1600, integer=True)]

    def live_values(self) -> dict:
        return {spec.key: self._live.get(spec.key) for spec in self.live_specs()}

    def set_live(self, values: dict) -> dict:
        import depthai as dai

        from drivers.cameras.live import checked

        specs = self.live_specs()
        if not specs:
            raise CameraSettingError(f"{self.name}: a replayed video has no exposure or ISO to change"
                                     if self.settings.replay is not None else
                                     f"{self.name}: this depthai gives no camera control queue")
        values = checked(self.name, specs, values)
        exposure = values.get("exposure_s", self._live.get("exposure_s") or 0.01)
        iso = values.get("iso", self._live.get("iso") or self.settings.iso)
        control = dai.CameraControl()
        control.setManualExposure(round(exposure * 1e6), int(iso))
        self._control.send(control)
        self._live = {"exposure_s": exposure, "iso": int(iso)}
        return self.live_values()

    def _grab(self, timeout_s: float) -> Grabbed:
        import depthai as dai

        live = self.settings.replay is None
        if not live and self.settings.at_end == "error" and self._replay_frames is not None \
                and self._delivered >= self._replay_frames:
            raise EndOfSource(f"{self.name}: replay {self.settings.replay!r} has no frame left after its "
                              f"{self._replay_frames} (set at_end: loop to play it again)")
        try:
            if live:  # frames queued before the call are stale (taken during a move)
                self._queue.tryGetAll()
            message = self._queue.get(datetime.timedelta(seconds=timeout_s))
        except dai.MessageQueue.QueueException:  # the pipeline stopped and closed its queue
            if not live:
                raise EndOfSource(f"{self.name}: replay {self.settings.replay!r} has no frame left "
                                  "(set at_end: loop to play it again)") from None
            raise self._fault(ConnectionLost(f"{self.name}: the OAK pipeline stopped (device lost?); "
                                             "check the cable, then connect() again")) from None
        except RuntimeError as exc:  # a timed-out get raises in some depthai versions
            if "timeout" in str(exc).lower():
                message = None
            else:
                raise self._fault(ConnectionLost(f"{self.name}: reading frames failed: {exc}")) from exc
        if message is None:
            raise CaptureTimeout(f"{self.name}: no frame within {timeout_s:g} s; check the device and its frame rate")
        if not isinstance(message, dai.ImgFrame):
            raise CorruptFrame(f"{self.name}: expected an image frame, got {type(message).__name__}")
        if not live:
            self._delivered += 1
        image = message.getCvFrame() if self.settings.color == "bgr" else message.getFrame()
        if image.ndim != 2 and self.settings.color == "gray":
            raise CorruptFrame(f"{self.name}: expected a GRAY8 frame, got shape {image.shape}")
        exposure = message.getExposureTime().total_seconds()
        return Grabbed(
            image.copy(),
            device_timestamp_s=message.getTimestampDevice().total_seconds(),
            host_timestamp_s=message.getTimestamp().total_seconds(),
            exposure_s=exposure if exposure > 0 else None,
            meta={"sequence_number": int(message.getSequenceNum())},
        )

    def _release(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            finally:
                self._pipeline = None
                self._queue = None
                self._control = None
