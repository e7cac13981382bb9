"""Robotiq EPick vacuum gripper over Modbus RTU: on a serial port (RS-485, 115200 8N1, device id 9)
or as RTU frames over TCP (a UR wrist forwarding the tool's RS-485 bytes).

Registers and their decoding: `drivers.grippers.epick_registers`. The link (time-outs,
error classes, no silent reconnect, the 5 ms pacing the gripper needs) is
`drivers.grippers.modbus_link`.

- `connect()` opens the link and runs the activation sequence of the manual: reset
  (rACT=0, which also clears faults), activate (rACT=1, generator off), then poll the
  status until gSTA says operational.
- `grip()` sends rGTO=1 with the pressure request, grip timeout and minimum pressure
  for detection, then polls until the gripper decides: object detected (gOBJ 1 or 2),
  or none (gOBJ 3, or fault 0x6 grip timeout). A major fault is an error naming it.
- `release()` sends rPR=100 (passive: valve to atmosphere) or rPR>100 (active:
  blow-off) and waits until the vacuum is gone.
- After a grip that held an object, `status()` and every later call check the object
  is still there and raise `VacuumLost` once if it is not.
- Settings speak relative vacuum (kPa below the atmosphere), as `GripperStatus` does;
  the driver converts to the absolute pressures of the registers (100 - vacuum).
- On the RS-485 line (and through the wrist forwarder) only the addressed device
  answers: a frame from another device id is never taken for the gripper's reply; the
  driver keeps waiting for its own until `timeout_s` (`modbus_link`), and a time-out
  names the frames it ignored, which is what a wrong `device_id` looks like.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers import endpoint
from drivers.grippers.epick_registers import (
    ATMOSPHERE_KPA,
    BLOCK_REGISTERS,
    COMMAND_ADDRESS,
    DEFAULT_DEVICE_ID,
    FAULT_GRIP_TIMEOUT,
    MIN_GRIP_PRESSURE_KPA,
    MODES,
    OBJ_NONE,
    STATUS_ADDRESS,
    EPickCommand,
    EPickStatus,
    decode_status,
    encode_command,
)
from drivers.grippers.modbus_gripper import ModbusGripper, detection_below_grip
from drivers.grippers.modbus_link import LinkConfig
from drivers.interfaces import (
    DeviceError,
    GripperStatus,
    VacuumLost,
)

RESET = EPickCommand(activate=False, mode=0, regulate=False, pressure_kpa=0, timeout_ticks=0, min_pressure_kpa=0)


class EPickSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    transport: Literal["serial", "tcp"] = Field(
        "serial", description="'serial': RTU on a serial port; 'tcp': RTU frames over a TCP socket (UR wrist forwarder)")
    serial_port: str = Field("/dev/ttyUSB0", min_length=1, description="serial device (transport 'serial')")
    baudrate: int = Field(115200, ge=1200, le=1_000_000, description="serial speed, bit/s (8N1)")
    host: str = Field("127.0.0.1", min_length=1, description="forwarder host (transport 'tcp')")
    port: int = Field(54321, ge=1, le=65535, description="forwarder TCP port (transport 'tcp')")
    device_id: int = Field(DEFAULT_DEVICE_ID, ge=1, le=247, description="Modbus device id of the gripper")
    timeout_s: float = Field(0.2, gt=0, le=10, description="time-out for one reply")
    retries: int = Field(1, ge=0, le=5, description="extra attempts after a reply time-out")
    min_interval_s: float = Field(0.005, ge=0.005, le=1.0,
                                  description="at least this long between two requests (the gripper needs 5 ms)")
    mode: Literal["automatic", "advanced"] = Field(
        "advanced", description="rMOD: 'advanced' honours the vacuum, timeout and detection settings below")
    grip_vacuum_kpa: int = Field(60, ge=1, le=ATMOSPHERE_KPA - MIN_GRIP_PRESSURE_KPA,
                                 description="vacuum to regulate to while gripping, kPa below atmosphere (rPR = 100 - this)")
    detect_vacuum_kpa: int = Field(20, ge=1, le=ATMOSPHERE_KPA - MIN_GRIP_PRESSURE_KPA,
                                   description="an object counts as held from this vacuum on, kPa (rFR = 100 - this)")
    grip_timeout_s: float = Field(1.0, ge=0.1, le=25.5,
                                  description="no object if the detection vacuum is not reached within this (rSP, 100 ms units)")
    release: Literal["passive", "active"] = Field(
        "passive", description="'passive': valve to atmosphere (rPR 100); 'active': blow-off (rPR 100 + active_release_kpa)")
    active_release_kpa: int = Field(10, ge=1, le=155, description="blow-off overpressure request for an active release")
    release_vacuum_kpa: float = Field(2.0, gt=0, le=50, description="a release is complete once the vacuum is below this")
    release_timeout_s: float = Field(1.0, gt=0, le=30, description="longest wait for a release to complete")
    activation_timeout_s: float = Field(2.0, gt=0, le=30, description="longest wait for gSTA operational after activation")
    poll_interval_s: float = Field(0.01, ge=0.005, le=1.0, description="status polling period while waiting")

    @model_validator(mode="after")
    def _detection_below_grip(self):
        return detection_below_grip(self, "detect_vacuum_kpa", "grip_vacuum_kpa")

    def link_config(self) -> LinkConfig:
        kind = "serial" if self.transport == "serial" else "rtu-over-tcp"
        return LinkConfig(kind=kind, device_id=self.device_id, timeout_s=self.timeout_s, retries=self.retries,
                          min_interval_s=self.min_interval_s, serial_port=self.serial_port, baudrate=self.baudrate,
                          host=self.host, port=self.port)

    def endpoints(self) -> list[str]:
        """The serial device, or the forwarder's socket: whichever the transport uses."""
        if self.transport == "serial":
            return [endpoint.device(self.serial_port)]
        return [endpoint.tcp(self.host, self.port)]


class EPickGripper(ModbusGripper):
    """The Gripper interface on a Robotiq EPick. Built without touching hardware; `connect()` activates it."""

    Settings = EPickSettings

    def __init__(self, name: str, settings: EPickSettings):
        super().__init__(name, settings)
        self.last_status: EPickStatus | None = None

    def _start(self) -> None:
        """Activate: reset (clears faults), activate, wait for gSTA operational."""
        self._write(RESET)
        self._write(self._command(regulate=False, pressure_kpa=ATMOSPHERE_KPA))
        for status in self._polled(self.settings.activation_timeout_s):
            if status.operational and status.activated:
                return
            if status.major_fault:
                raise self._refused("activation failed", status)
        raise DeviceError(f"{self.name}: activation did not complete within "
                          f"{self.settings.activation_timeout_s} s ({status.describe()})")

    # -- Gripper --------------------------------------------------------------
    def grip(self) -> bool:
        self._ready()
        if self._holding:
            self._read()  # raises VacuumLost if the object fell off since
            return True
        command = self._command(regulate=True, pressure_kpa=ATMOSPHERE_KPA - self.settings.grip_vacuum_kpa)
        self._write(command)
        for status in self._polled(self.settings.grip_timeout_s + 1.0):
            if status.major_fault:
                raise self._refused("grip failed", status)
            if status.pressure_request_kpa == command.pressure_kpa and status.activated:  # our command was taken
                if status.object_detected:
                    self._holding = True
                    return True
                if status.object == OBJ_NONE or status.fault == FAULT_GRIP_TIMEOUT:
                    return False
                if status.fault and status.fault != FAULT_GRIP_TIMEOUT:
                    raise self._refused("grip refused", status)
        raise DeviceError(f"{self.name}: the gripper did not report an object decision within "
                          f"{self.settings.grip_timeout_s + 1.0:.1f} s of the grip command ({status.describe()})")

    def release(self) -> None:
        """Release and wait until the vacuum is gone. If the held object had been lost
        before, the release is still done and VacuumLost is raised afterwards."""
        self._ready()
        lost_text = self._lost_before_release()
        extra = self.settings.active_release_kpa if self.settings.release == "active" else 0
        command = self._command(regulate=True, pressure_kpa=ATMOSPHERE_KPA + extra)
        self._write(command)
        for status in self._polled(self.settings.release_timeout_s):
            if status.pressure_request_kpa == command.pressure_kpa and status.vacuum_kpa <= self.settings.release_vacuum_kpa:
                break
            if status.major_fault:
                raise self._refused("release failed", status)
        else:
            raise DeviceError(f"{self.name}: release not complete after {self.settings.release_timeout_s} s: "
                              f"vacuum still {status.vacuum_kpa:.0f} kPa ({status.describe()})")
        if lost_text:
            raise VacuumLost(lost_text)

    def status(self) -> GripperStatus:
        self._ready()
        status = self._read()
        return GripperStatus(status.vacuum_kpa, status.object_detected, status.gripping)

    def read_status(self) -> EPickStatus:
        """The decoded status block (faults, actuator, pressures), for diagnostics."""
        self._ready()
        return self._read()

    # -- internals ------------------------------------------------------------
    def _command(self, regulate: bool, pressure_kpa: int) -> EPickCommand:
        s = self.settings
        return EPickCommand(activate=True, mode=MODES[s.mode], regulate=regulate, pressure_kpa=pressure_kpa,
                            timeout_ticks=round(s.grip_timeout_s * 10),
                            min_pressure_kpa=ATMOSPHERE_KPA - s.detect_vacuum_kpa)

    def _refused(self, what: str, status: EPickStatus) -> DeviceError:
        return DeviceError(f"{self.name}: {what}: {status.fault_text()} ({status.describe()})")

    def _write(self, command: EPickCommand) -> None:
        self._guarded(lambda: self.link.write(COMMAND_ADDRESS, encode_command(command)))

    def _read(self) -> EPickStatus:
        """Read and decode the status block; raise VacuumLost once if a held object is gone."""
        status = decode_status(self._guarded(lambda: self.link.read(STATUS_ADDRESS, BLOCK_REGISTERS, function=4)))
        self.last_status = status
        if self._holding and not status.object_detected:
            self._holding = False
            raise VacuumLost(f"{self.name}: the object held since the last grip was lost: vacuum "
                             f"{status.vacuum_kpa:.0f} kPa, below the detection level "
                             f"{self.settings.detect_vacuum_kpa} kPa; check the part and the nozzle")
        return status
