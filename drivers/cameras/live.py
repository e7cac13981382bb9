"""Exposure and gain changed on a connected camera, while it runs (the live view's controls).

Every camera backend offers the same small capability, so the daemon's live view works on any of them:

- `live_specs()`: the settings it can change live, each a `LiveSetting`: the cell file's option it is
  (`exposure_s`, `gain_db`, `gain`, `iso`, ...), its unit and the range allowed;
- `live_values()`: their current values on the device (None where the device does not say);
- `set_live(values)`: apply {option: value} now; a value out of range is `CameraSettingError` naming the
  range, before anything is sent; a value the device refuses is `CameraSettingError` too.

Changed live, a setting lasts until the camera is connected again (which applies the cell file's
settings); write it to the cell file to keep it. The option names are the cell file's own, so a
setting changed live is written back under the key the driver reads it from.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from drivers.cameras._common import CameraSettingError


@dataclass(frozen=True)
class LiveSetting:
    key: str  # the cell file's option of the camera's backend
    label: str  # "exposure" or "gain": what the console's control is
    unit: str
    minimum: float
    maximum: float
    integer: bool = False

    def public(self) -> dict:
        return asdict(self)

    def allowed(self) -> str:
        return f"{self.minimum:g} to {self.maximum:g} {self.unit}".rstrip()

    def check(self, camera: str, value) -> float:
        """The value as the device takes it, or CameraSettingError naming the range."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise CameraSettingError(f"{camera}: {self.key}: {value!r}; allowed: a number from {self.allowed()}")
        if not self.minimum <= value <= self.maximum:
            raise CameraSettingError(f"{camera}: {self.key}: {value:g}; allowed: {self.allowed()}")
        if self.integer and value != int(value):
            raise CameraSettingError(f"{camera}: {self.key}: {value:g}; allowed: a whole number from "
                                     f"{self.allowed()}")
        return int(value) if self.integer else float(value)


def checked(camera: str, specs: list[LiveSetting], values: dict) -> dict:
    """`values` checked against `specs` whole (every problem named at once), as the device will take them."""
    by_key = {s.key: s for s in specs}
    out, problems = {}, []
    for key, value in values.items():
        spec = by_key.get(key)
        if spec is None:
            problems.append(f"{camera}: {key}: not a setting this camera changes live; it has "
                            f"{', '.join(f'{s.key} ({s.allowed()})' for s in specs) or 'none'}")
            continue
        try:
            out[key] = spec.check(camera, value)
        except CameraSettingError as exc:
            problems.append(str(exc))
    if problems:
        raise CameraSettingError("; ".join(problems))
    return out


def supports_live(camera) -> bool:
    return all(callable(getattr(camera, name, None)) for name in ("live_specs", "live_values", "set_live"))
