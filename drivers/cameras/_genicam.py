"""What the two GenICam paths share: the cell file's options, choosing the device, applying the features.

`backend: genicam` drives a GenICam camera (GigE Vision, USB3 Vision) through one of two libraries,
chosen by `library`:

- `harvesters` (default): harvesters and the GenTL producer (.cti) of the camera maker's SDK
  (`producer`); `drivers/cameras/genicam.py`.
- `aravis`: the Aravis library, which speaks GigE Vision (and USB3 Vision) itself, so no vendor SDK
  is needed; used from Python through GObject introspection (PyGObject + Debian's
  gir1.2-aravis-0.8); `drivers/cameras/aravis.py`.

Both apply the settings through the same code (`GenICamBase._configure`) on the camera's SFNC
features, reached through a small `Features` adapter per library, so a setting behaves the same
on either path: a feature the camera lacks, or a value it refuses, is an error naming the setting
and the feature, or with `strict: false` a warning kept in `camera.refused`.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from drivers import endpoint
from drivers.cameras._common import CameraBase, CameraSettingError, to_gray
from drivers.interfaces import ConnectionLost, CorruptFrame

# pixel format -> (channels, channel order for grayscale conversion, bytes per value);
# packed and Bayer formats are not handled. 10- to 16-bit formats are little-endian 16-bit words (PFNC).
FORMATS = {
    "Mono8": (1, None, 1), "Mono10": (1, None, 2), "Mono12": (1, None, 2), "Mono14": (1, None, 2),
    "Mono16": (1, None, 2), "RGB8": (3, "rgb", 1), "BGR8": (3, "bgr", 1), "RGBa8": (4, "rgb", 1),
    "BGRa8": (4, "bgr", 1),
}


class GenICamSettings(BaseModel):
    """The options of `backend: genicam`, for both libraries unless said otherwise.

    library: harvesters (needs `producer`) or aravis (no producer; `address` or discovery).
    Device choice: `serial`, `model`, `index` among the devices found; with aravis, `address` opens
    the camera at that IP address directly (no broadcast discovery) and `serial`/`model` are then
    checked against it. Features (SFNC names): pixel_format -> PixelFormat, width/height ->
    Width/Height, frame_rate_hz -> AcquisitionFrameRate(Abs), exposure_s -> ExposureTime(Abs) in µs,
    gain_db -> Gain (dB), gain_raw -> GainRaw (device units, older GigE cameras), trigger ->
    TriggerMode/TriggerSource/TriggerSoftware. A feature the file leaves out keeps the camera's
    current value, which may be what an earlier program set (cameras keep their registers until
    they restart).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    library: Literal["harvesters", "aravis"] = Field(
        "harvesters", description="harvesters: through the GenTL producer (.cti) of the camera maker's SDK; "
        "aravis: GigE Vision (and USB3 Vision) through the Aravis library, no vendor SDK needed "
        "(PyGObject and Debian's gir1.2-aravis-0.8: tools/ensure-system)")
    producer: str | None = Field(None, validate_default=True, description="library: harvesters only (required "
                                 "there): path of the GenTL producer (.cti) of the camera's SDK")
    address: str | None = Field(None, min_length=1, description="library: aravis only: IP address (or host name) "
                                "of a GigE Vision camera, opened directly without broadcast discovery; "
                                "default: discover the cameras and choose by serial, model or index")
    serial: str | None = Field(None, description="device serial number (as the library lists it)")
    model: str | None = Field(None, description="device model name")
    index: int | None = Field(None, ge=0, description="position among the matching devices (default: the only "
                              "one; aravis lists them in order of device id); not with address")
    pixel_format: str | None = Field(None, description=f"PixelFormat to set; handled: {', '.join(FORMATS)}")
    color: Literal["gray", "native"] = Field("gray", description="gray: 2-D frames; native: as the format has them")
    width: int | None = Field(None, ge=1, le=65535, description="Width feature (px)")
    height: int | None = Field(None, ge=1, le=65535, description="Height feature (px)")
    frame_rate_hz: float | None = Field(None, gt=0, le=10000, description="AcquisitionFrameRate (free-run)")
    exposure_s: float | None = Field(None, gt=0, le=60, description="ExposureTime, or ExposureTimeAbs on older "
                                     "GigE cameras, in µs on the camera (sets ExposureAuto Off)")
    gain_db: float | None = Field(None, ge=0, le=60, description="Gain in dB (sets GainAuto Off); a camera with "
                                  "only GainRaw refuses it: use gain_raw")
    gain_raw: int | None = Field(None, ge=0, description="GainRaw in the camera's own units, for older GigE "
                                 "cameras without Gain in dB (sets GainAuto Off)")
    trigger: Literal["free-run", "software"] = Field("free-run", description="software: one frame per capture()")
    num_buffers: int = Field(4, ge=1, le=64, description="frame buffers queued for the camera")
    strict: bool = Field(True, description="a setting the camera lacks is an error (false: a warning)")

    @field_validator("producer")
    @classmethod
    def _producer_for_harvesters(cls, value, info: ValidationInfo):
        library = info.data.get("library")
        if library == "harvesters" and value is None:
            raise ValueError("required with library: harvesters (the GenTL producer .cti of the camera's SDK); "
                             "or set library: aravis to drive a GigE Vision camera without one")
        if library == "aravis" and value is not None:
            raise ValueError("only with library: harvesters; Aravis speaks GigE Vision itself and needs no "
                             "GenTL producer")
        return value

    @field_validator("address")
    @classmethod
    def _address_for_aravis(cls, value, info: ValidationInfo):
        if value is not None and info.data.get("library") == "harvesters":
            raise ValueError("only with library: aravis; a GenTL producer finds its devices itself (choose one "
                             "by serial, model or index)")
        return value

    @field_validator("index")
    @classmethod
    def _index_without_address(cls, value, info: ValidationInfo):
        if value is not None and info.data.get("address") is not None:
            raise ValueError("not with address, which names one camera already")
        return value

    def endpoints(self) -> list[str]:
        """The camera by its serial and/or address; by model or index it cannot be told apart across processes."""
        names = ([self.serial] if self.serial else []) + ([endpoint.address(self.address)] if self.address else [])
        return [endpoint.camera(name) for name in names]


@dataclass(frozen=True)
class DeviceInfo:
    """One device a library found, as the cell file can choose it."""

    model: str | None
    serial: str | None
    id: str | None  # the library's own name for it (GenTL id, Aravis device id)
    address: str | None = None

    def describe(self) -> str:
        where = f" at {self.address}" if self.address else ""
        return f"{self.model} serial {self.serial} ({self.id}){where}"


class Features:
    """The camera's GenICam features, as one library reaches them.

    Absent features are found with `has`; a value the camera refuses raises one of `errors`
    (reported as a refused setting); a link that went down raises ConnectionLost."""

    errors: tuple[type[BaseException], ...] = ()

    def has(self, name: str) -> bool:
        raise NotImplementedError

    def get(self, name: str) -> Any:
        raise NotImplementedError

    def set(self, name: str, value: Any) -> None:
        raise NotImplementedError

    def entries(self, name: str) -> list[str]:
        """The symbolic values an enumeration feature offers."""
        raise NotImplementedError

    def execute(self, name: str) -> None:
        raise NotImplementedError


class GenICamBase(CameraBase):
    """What both GenICam paths share: device choice, settings applied on features, frame decoding."""

    Settings = GenICamSettings

    def __init__(self, name: str, settings: GenICamSettings):
        super().__init__(name, settings)
        self._format: str | None = None
        self._software_trigger = False
        self._exposure_s: float | None = None
        self.applied: dict[str, float] = {}  # what the camera reports after the settings (exposure_s, gain_db, ...)

    # -- what each library provides ---------------------------------------
    def _features(self) -> Features:
        """The connected camera's features."""
        raise NotImplementedError

    # -- reading a feature ---------------------------------------------------
    def read_feature(self, name: str) -> Any:
        """The current value of GenICam feature `name`, read from the camera (for diagnostics and checks)."""
        self._ready()
        features = self._features()
        if not features.has(name):
            raise CameraSettingError(f"{self.name}: the camera has no {name} feature")
        try:
            return features.get(name)
        except ConnectionLost as exc:
            raise self._fault(exc) from exc
        except features.errors as exc:
            raise CameraSettingError(f"{self.name}: {name} cannot be read ({type(exc).__name__}: {exc})") from exc

    # -- device choice ------------------------------------------------------
    def _choose_device(self, devices: list[DeviceInfo], source: str) -> int:
        """The index in `devices` of the one device the settings name (`source` says where they were found,
        e.g. "from producer '…'")."""
        s = self.settings
        listed = "; ".join(f"[{i}] {d.describe()}" for i, d in enumerate(devices)) or "none"
        matches = [i for i, d in enumerate(devices)
                   if (s.serial is None or d.serial == s.serial) and (s.model is None or d.model == s.model)]
        asked = ", ".join(f"{k} {v!r}" for k, v in (("serial", s.serial), ("model", s.model)) if v is not None)
        if not matches:
            raise CameraSettingError(f"{self.name}: no device with {asked or 'any settings'} {source}; "
                                     f"found: {listed}")
        if s.index is not None:
            if s.index >= len(matches):
                raise CameraSettingError(f"{self.name}: index {s.index} but only {len(matches)} matching "
                                         f"device(s); found: {listed}")
            return matches[s.index]
        if len(matches) > 1:
            raise CameraSettingError(f"{self.name}: {len(matches)} devices match ({asked or 'no serial/model/index'}"
                                     f"); set serial, model or index; found: {listed}")
        return matches[0]

    # -- settings -----------------------------------------------------------
    def _configure(self, features: Features) -> None:
        """Apply the settings on the camera's features (before acquisition starts), then read back what it uses."""
        s = self.settings
        strict = s.strict
        if s.pixel_format is not None:
            if s.pixel_format not in FORMATS:
                raise CameraSettingError(f"{self.name}: pixel_format {s.pixel_format!r} is not handled; "
                                         f"allowed: {', '.join(FORMATS)}")
            offered = features.entries("PixelFormat") if features.has("PixelFormat") else []
            if s.pixel_format in offered:
                features.set("PixelFormat", s.pixel_format)
            else:
                self._refused(f"pixel_format: the camera offers {', '.join(offered) or 'no PixelFormat'}, "
                              f"not {s.pixel_format!r}", strict)
        self._format = str(features.get("PixelFormat")) if features.has("PixelFormat") else "Mono8"
        if self._format not in FORMATS:
            raise CameraSettingError(f"{self.name}: the camera delivers PixelFormat {self._format!r}, which this "
                                     f"driver does not convert; set pixel_format to one of {', '.join(FORMATS)}")
        for setting, feature, value in (("width", "Width", s.width), ("height", "Height", s.height)):
            if value is not None:
                self._write(features, setting, [feature], value)
        if s.frame_rate_hz is not None:
            self._write(features, "frame_rate_hz", ["AcquisitionFrameRateEnable"], True, quiet=True)
            self._write(features, "frame_rate_hz", ["AcquisitionFrameRate", "AcquisitionFrameRateAbs"],
                        s.frame_rate_hz)
        if s.exposure_s is not None:
            self._write(features, "exposure_s", ["ExposureAuto"], "Off", quiet=True)
            self._write(features, "exposure_s", ["ExposureTime", "ExposureTimeAbs"], s.exposure_s * 1e6)
        if s.gain_db is not None:
            self._write(features, "gain_db", ["GainAuto"], "Off", quiet=True)
            hint = ("; it has GainRaw, in its own units: set gain_raw instead"
                    if features.has("GainRaw") and not features.has("Gain") else "")
            self._write(features, "gain_db", ["Gain"], s.gain_db, hint=hint)
        if s.gain_raw is not None:
            self._write(features, "gain_raw", ["GainAuto"], "Off", quiet=True)
            hint = "; it has Gain in dB: set gain_db instead" if features.has("Gain") else ""
            self._write(features, "gain_raw", ["GainRaw"], s.gain_raw, hint=hint)
        if s.trigger == "software":
            self._write(features, "trigger", ["TriggerSelector"], "FrameStart", quiet=True)
            ok = self._write(features, "trigger", ["TriggerMode"], "On")
            ok = ok and self._write(features, "trigger", ["TriggerSource"], "Software")
            if ok and not features.has("TriggerSoftware"):
                self._refused("trigger: the camera has no TriggerSoftware command", strict)
                ok = False
            self._software_trigger = ok
        else:
            self._write(features, "trigger", ["TriggerMode"], "Off", quiet=True)
            self._software_trigger = False
        self.applied = self._read_back(features)
        self._exposure_s = self.applied.get("exposure_s")  # what the camera says it exposes, not what was asked

    def _write(self, features: Features, setting: str, names: list[str], value, quiet: bool = False,
               hint: str = "") -> bool:
        """Set the first of `names` the camera has; report (unless quiet) when none can take the value."""
        for feature in names:
            if not features.has(feature):
                continue
            try:
                features.set(feature, value)
                return True
            except features.errors as exc:  # out of range, read-only, wrong type: the camera says why
                if not quiet:
                    self._refused(f"{setting}: {feature} refused {value!r} ({type(exc).__name__}: {exc})",
                                  self.settings.strict)
                return False
        if not quiet:
            self._refused(f"{setting}: the camera has no {' or '.join(names)} feature{hint}", self.settings.strict)
        return False

    def _read_back(self, features: Features) -> dict[str, float]:
        """What the camera reports for the settings that matter to a measurement, where it has them."""
        out: dict[str, float] = {}
        for key, names, scale in (("exposure_s", ("ExposureTime", "ExposureTimeAbs"), 1e-6),
                                  ("gain_db", ("Gain",), 1.0), ("gain_raw", ("GainRaw",), 1.0),
                                  ("frame_rate_hz", ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"), 1.0)):
            for feature in names:
                if features.has(feature):
                    with contextlib.suppress(*features.errors):  # unreadable on some cameras: leave it unknown
                        out[key] = float(features.get(feature)) * scale
                    break
        return out

    # -- exposure and gain while it runs (drivers/cameras/live.py) ---------------
    def live_specs(self):
        """exposure_s, and gain_db (Gain, dB) or, on a camera with only GainRaw, gain_raw; the ranges the cell
        file allows (the camera may clamp further: what it took is read back)."""
        from drivers.cameras.live import LiveSetting

        self._ready()
        features = self._features()
        specs = [LiveSetting("exposure_s", "exposure", "s", 1e-6, 60.0)]
        if features.has("Gain") or not features.has("GainRaw"):
            specs.append(LiveSetting("gain_db", "gain", "dB", 0.0, 60.0))
        else:
            specs.append(LiveSetting("gain_raw", "gain", "device units", 0, 4095, integer=True))
        return specs

    def live_values(self) -> dict:
        self._ready()
        values = self._read_back(self._features())
        return {s.key: values.get(s.key) for s in self.live_specs()}

    def set_live(self, values: dict) -> dict:
        from drivers.cameras.live import checked

        values = checked(self.name, self.live_specs(), values)
        features = self._features()
        targets = {"exposure_s": (["ExposureTime", "ExposureTimeAbs"], 1e6, "ExposureAuto"),
                   "gain_db": (["Gain"], 1.0, "GainAuto"), "gain_raw": (["GainRaw"], 1, "GainAuto")}
        for key, value in values.items():
            names, scale, auto = targets[key]
            with contextlib.suppress(*features.errors):  # a camera without the auto feature: nothing to switch off
                if features.has(auto):
                    features.set(auto, "Off")
            feature = next((n for n in names if features.has(n)), None)
            if feature is None:
                raise CameraSettingError(f"{self.name}: {key}: the camera has no {' or '.join(names)} feature")
            try:
                features.set(feature, value * scale)
            except ConnectionLost as exc:
                raise self._fault(exc) from exc
            except features.errors as exc:
                raise CameraSettingError(f"{self.name}: {key}: {feature} refused {value * scale!r} "
                                         f"({type(exc).__name__}: {exc})") from exc
        self.applied = self._read_back(features)
        self._exposure_s = self.applied.get("exposure_s")
        return self.live_values()

    # -- frames -------------------------------------------------------------
    def _image(self, data, fmt: str, width: int, height: int) -> np.ndarray:
        """A frame's pixels as an array (gray unless color: native) from its raw data (bytes or an array)."""
        if fmt not in FORMATS:
            raise CorruptFrame(f"{self.name}: a frame arrived in PixelFormat {fmt!r}; expected {self._format!r}")
        channels, order, size = FORMATS[fmt]
        if isinstance(data, np.ndarray):
            values = data.reshape(-1)
        else:
            values = np.frombuffer(data, dtype=np.uint8 if size == 1 else np.dtype("<u2"))
        if values.size != width * height * channels:
            raise CorruptFrame(f"{self.name}: frame holds {values.size} values, expected {width}x{height}x{channels}")
        image = np.array(values.reshape(height, width, channels) if channels > 1 else values.reshape(height, width))
        if channels > 1 and self.settings.color == "gray":
            image = to_gray(image, order)
        return image

    def _meta(self, fmt: str) -> dict:
        meta = {"pixel_format": fmt}
        for key in ("gain_db", "gain_raw"):
            if key in self.applied:
                meta[key] = self.applied[key]
        return meta
