"""OnRobot VGC10 (and VG10) vacuum gripper over Modbus TCP through the Compute Box (port 502, unit 65).

Registers: `drivers.grippers.vgc10_registers`. Each of the two channels (A, B) is
commanded by one holding register (mode release / grip / idle, and a target vacuum
in %) and reports its actual vacuum in 1/1000 of relative vacuum. The driver works
one channel or both together (`channel` setting):

- `grip()` puts the channel(s) in grip mode with the target vacuum and polls the
  actual vacuum; an object is detected once every working channel reaches
  `detect_vacuum_percent` within `grip_timeout_s` (if not, the pump keeps trying
  and `grip()` returns False);
- `release()` puts them in release mode and waits until the vacuum is gone;
  `idle()` stops the pump with the valves closed;
- after a grip that held an object, `status()` and every later call raise
  `VacuumLost` once if the vacuum falls below the detection level.

The target vacuum never goes above 80 % on the wire: OnRobot's register description
says it "should never exceed 80". A gripper sent more takes the write without an
exception and regulates at most 80 % anyway (drivers/sim/servers/vgc10.py says why we
read it so), so a larger setting would silently not do what it says: the settings
refuse it, naming the limit (`vacuum_percent: 95 is above 80 %, ...`), before anything
is sent.

Function codes: FC03 (read holding registers) and FC16 (write multiple registers),
both documented for the VG10 / VGC10; the actual vacuum is a holding register (FC04,
read input registers, is answered with exception 1 by the gripper).

Errors and link handling are those of `drivers.grippers.modbus_link`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from drivers import endpoint
from drivers.grippers.modbus_gripper import ModbusGripper, detection_below_grip
from drivers.grippers.modbus_link import LinkConfig
from drivers.grippers.vgc10_registers import (
    ATMOSPHERE_KPA,
    CHANNELS,
    CONTROL_ADDRESS,
    DEFAULT_UNIT,
    MAX_TARGET_PERCENT,
    MODE_GRIP,
    MODE_IDLE,
    MODE_NAMES,
    MODE_RELEASE,
    VACUUM_ADDRESS,
    decode_control,
    encode_control,
    vacuum_kpa,
    vacuum_percent,
)
from drivers.interfaces import (
    DeviceError,
    GripperStatus,
    VacuumLost,
)


class Vgc10Settings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = Field("192.168.1.1", min_length=1, description="Compute Box address")
    port: int = Field(502, ge=1, le=65535, description="Modbus TCP port")
    device_id: int = Field(DEFAULT_UNIT, ge=1, le=247, description="Modbus unit id of the gripper (65 on the Compute Box)")
    channel: Literal["A", "B", "both"] = Field("both", description="vacuum channel(s) the driver works")
    vacuum_percent: int = Field(60, ge=1, description=f"target vacuum while gripping, % relative vacuum (at most "
                                                      f"{MAX_TARGET_PERCENT}: the gripper regulates no higher)")
    detect_vacuum_percent: float = Field(20.0, gt=0, description="an object counts as held from this vacuum on, %")
    grip_timeout_s: float = Field(1.0, gt=0, le=30, description="no object if the detection vacuum is not reached within this")
    release_vacuum_percent: float = Field(2.0, gt=0, le=50, description="a release is complete once the vacuum is below this, %")
    release_timeout_s: float = Field(1.0, gt=0, le=30, description="longest wait for a release to complete")
    timeout_s: float = Field(0.5, gt=0, le=10, description="time-out for one reply")
    retries: int = Field(1, ge=0, le=5, description="extra attempts after a reply time-out")
    poll_interval_s: float = Field(0.01, ge=0.001, le=1.0, description="vacuum polling period while waiting")

    @field_validator("vacuum_percent", "detect_vacuum_percent")
    @classmethod
    def _at_most_80(cls, value, info):
        if value > MAX_TARGET_PERCENT:
            raise ValueError(
                f"{info.field_name}: {value} is above {MAX_TARGET_PERCENT} %, the most vacuum the VGC10 regulates to "
                f"(OnRobot: the target 'should never exceed {MAX_TARGET_PERCENT}'; a gripper sent more silently "
                f"regulates at {MAX_TARGET_PERCENT} %); allowed: 1..{MAX_TARGET_PERCENT}. Nothing was sent")
        return value

    @model_validator(mode="after")
    def _detection_below_target(self):
        return detection_below_grip(self, "detect_vacuum_percent", "vacuum_percent")

    def link_config(self) -> LinkConfig:
        return LinkConfig(kind="tcp", device_id=self.device_id, timeout_s=self.timeout_s, retries=self.retries,
                          host=self.host, port=self.port)

    def endpoints(self) -> list[str]:
        return [endpoint.tcp(self.host, self.port)]


class Vgc10Gripper(ModbusGripper):
    """The Gripper interface on an OnRobot VGC10 / VG10."""

    Settings = Vgc10Settings

    def __init__(self, name: str, settings: Vgc10Settings):
        super().__init__(name, settings)
        self.channels = [0, 1] if settings.channel == "both" else [CHANNELS[settings.channel]]

    def _start(self) -> None:
        self._read()  # the gripper answers: its control and vacuum registers read back

    # -- Gripper --------------------------------------------------------------
    def grip(self) -> bool:
        self._ready()
        if self._holding:
            self._read()  # raises VacuumLost if the object fell off since
            return True
        self._command(MODE_GRIP, self.settings.vacuum_percent)
        for _, vacuum in self._polled(self.settings.grip_timeout_s):
            if min(vacuum) >= self.settings.detect_vacuum_percent:
                self._holding = True
                return True
        return False  # the pump keeps trying; status().gripping stays True

    def release(self) -> None:
        """Release and wait until the vacuum is gone. If the held object had been lost
        before, the release is still done and VacuumLost is raised afterwards."""
        self._ready()
        lost_text = self._lost_before_release()
        self._command(MODE_RELEASE, 0)
        for _, vacuum in self._polled(self.settings.release_timeout_s):
            if max(vacuum) <= self.settings.release_vacuum_percent:
                break
        else:
            raise DeviceError(f"{self.name}: release not complete after {self.settings.release_timeout_s} s: "
                              f"vacuum still {max(vacuum):.1f} %")
        if lost_text:
            raise VacuumLost(lost_text)

    def idle(self) -> None:
        """Stop the pump with the valves closed (a sealed part stays on while the vacuum lasts)."""
        self._ready()
        if self._holding:
            self._read()  # raises VacuumLost if the object fell off since
        self._command(MODE_IDLE, 0)

    def status(self) -> GripperStatus:
        self._ready()
        modes, vacuum = self._read()
        weakest = min(vacuum)
        return GripperStatus(weakest / 100.0 * ATMOSPHERE_KPA, weakest >= self.settings.detect_vacuum_percent,
                             any(mode == MODE_GRIP for mode in modes))

    def read_channels(self) -> dict[str, dict]:
        """Mode, target and actual vacuum of both channels, for diagnostics."""
        self._ready()
        controls = self._guarded(lambda: self.link.read(CONTROL_ADDRESS, 2))
        permille = self._guarded(lambda: self.link.read(VACUUM_ADDRESS, 2))
        out = {}
        for name, index in CHANNELS.items():
            mode, target = decode_control(controls[index])
            out[name] = {"mode": MODE_NAMES.get(mode, f"unknown ({mode})"), "target_percent": target,
                         "vacuum_percent": vacuum_percent(permille[index]), "vacuum_kpa": vacuum_kpa(permille[index])}
        return out

    # -- internals ------------------------------------------------------------
    def _command(self, mode: int, percent: int) -> None:
        value = encode_control(mode, percent)
        first = self.channels[0]
        self._guarded(lambda: self.link.write(CONTROL_ADDRESS + first, [value] * len(self.channels)))

    def _read(self) -> tuple[list[int], list[float]]:
        """Modes and vacuum (%) of the working channels; raise VacuumLost once if a held object is gone."""
        controls = self._guarded(lambda: self.link.read(CONTROL_ADDRESS, 2))
        permille = self._guarded(lambda: self.link.read(VACUUM_ADDRESS, 2))
        modes = [decode_control(controls[i])[0] for i in self.channels]
        vacuum = [vacuum_percent(permille[i]) for i in self.channels]
        if self._holding and min(vacuum) < self.settings.detect_vacuum_percent:
            self._holding = False
            raise VacuumLost(f"{self.name}: the object held since the last grip was lost: vacuum {min(vacuum):.1f} %, "
                             f"below the detection level {self.settings.detect_vacuum_percent} %; "
                             "check the part and the cups")
        return modes, vacuum
