"""Robotiq EPick register blocks as pure functions: command encoding, status decoding.

The EPick is a Modbus device with two blocks of three 16-bit registers; each
register carries two of the manual's byte-wide fields, high byte first:

    command (robot output), written with FC16 at 0x03E8:
      0x03E8  high: ACTION REQUEST  bit0 rACT, bits1-2 rMOD, bit3 rGTO, bit4 rATR | low: reserved
      0x03E9  high: reserved                                                      | low: rPR pressure request
      0x03EA  high: rSP grip timeout (100 ms units)                               | low: rFR minimum pressure
    status (robot input), read with FC04 (or FC03) at 0x07D0:
      0x07D0  high: GRIPPER STATUS  bit0 gACT, bits1-2 gMOD, bit3 gGTO, bits4-5 gSTA, bits6-7 gOBJ
              low: bits0-1 gVAS (actuator)
      0x07D1  high: FAULT STATUS  low nibble gFLT, high nibble kFLT (controller) | low: gPR echo
      0x07D2  high: gPO actual pressure                                         | low: reserved

Pressures are absolute kPa with the atmosphere at 100: a pressure request of 22-99
grips (lower = more vacuum), 100 releases passively (valve open), 101-255 blows
(active release). Relative vacuum = 100 - pressure.

Both directions are here so the simulator (`drivers/sim/servers/epick.py`) and the
driver share one reading of the manual, and tests pin them register by register.
"""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_DEVICE_ID = 9
COMMAND_ADDRESS = 0x03E8
STATUS_ADDRESS = 0x07D0
BLOCK_REGISTERS = 3
ATMOSPHERE_KPA = 100  # the EPick's pressure scale puts the atmosphere at 100 kPa
MIN_GRIP_PRESSURE_KPA = 22  # the strongest vacuum the generator can be asked for (78 kPa below atmosphere)

MODE_AUTOMATIC, MODE_ADVANCED = 0, 1
MODES = {"automatic": MODE_AUTOMATIC, "advanced": MODE_ADVANCED}

# gSTA: activation status
STA_NOT_ACTIVATED, STA_OPERATIONAL = 0, 3
# gOBJ: object status
OBJ_REGULATING, OBJ_AT_MIN, OBJ_AT_MAX, OBJ_NONE = 0, 1, 2, 3
OBJECT_TEXT = {
    OBJ_REGULATING: "unknown: regulating towards the requested vacuum",
    OBJ_AT_MIN: "object detected, minimum vacuum reached",
    OBJ_AT_MAX: "object detected, requested vacuum reached",
    OBJ_NONE: "no object: none detected before the grip timeout, or lost",
}
# gVAS: actuator status
VAS_STANDBY, VAS_GRIPPING, VAS_PASSIVE_RELEASE, VAS_ACTIVE_RELEASE = 0, 1, 2, 3
ACTUATOR_TEXT = {
    VAS_STANDBY: "standby",
    VAS_GRIPPING: "gripping",
    VAS_PASSIVE_RELEASE: "passive release",
    VAS_ACTIVE_RELEASE: "active release",
}
# gFLT: gripper faults (manual section 4.x). 0x0-0x7 are minor (cleared by the next
# command), 0x8 and above are major (need a reset: rACT 0 then 1).
FAULT_TEXT = {
    0x0: "no fault",
    0x3: "porous material detected: the requested vacuum cannot be held",
    0x5: "action delayed: activation must complete before the command",
    0x6: "grip timeout: the minimum vacuum was not reached within the grip timeout",
    0x7: "activation bit not set: the gripper must be activated (rACT=1) first",
    0x8: "maximum operating temperature exceeded: let the gripper cool down",
    0x9: "no communication for at least 1 s",
    0xA: "under minimum operating voltage: check the 24 V supply",
    0xB: "automatic release in progress",
    0xC: "internal fault: contact the supplier",
    0xF: "automatic release completed",
}
FAULT_GRIP_TIMEOUT = 0x6
FAULT_NOT_ACTIVATED = 0x7
MAJOR_FAULT_FROM = 0x8


def _byte(name: str, value: int) -> int:
    if not isinstance(value, int) or not 0 <= value <= 255:
        raise ValueError(f"{name} must be an integer 0..255, got {value!r}")
    return value


@dataclass(frozen=True)
class EPickCommand:
    """The three command registers, field by field (manual names in the comments)."""

    activate: bool = False  # rACT: 1 activate, 0 reset (also clears faults)
    mode: int = MODE_ADVANCED  # rMOD: 0 automatic, 1 advanced (pressure, timeout and minimum honoured)
    regulate: bool = False  # rGTO: 1 follow the pressure request, 0 stop the vacuum generator
    auto_release: bool = False  # rATR: 1 automatic (emergency) release
    pressure_kpa: int = ATMOSPHERE_KPA  # rPR: absolute kPa; <100 grip, 100 passive release, >100 active release
    timeout_ticks: int = 0  # rSP: grip timeout in 100 ms units (release time for an active release)
    min_pressure_kpa: int = ATMOSPHERE_KPA  # rFR: an object counts as detected at or below this pressure


def encode_command(command: EPickCommand) -> list[int]:
    """The three register values written at 0x03E8."""
    if command.mode not in (MODE_AUTOMATIC, MODE_ADVANCED):
        raise ValueError(f"mode must be 0 (automatic) or 1 (advanced), got {command.mode!r}")
    action = int(command.activate) | command.mode << 1 | int(command.regulate) << 3 | int(command.auto_release) << 4
    return [
        action << 8,
        _byte("pressure_kpa", command.pressure_kpa),
        _byte("timeout_ticks", command.timeout_ticks) << 8 | _byte("min_pressure_kpa", command.min_pressure_kpa),
    ]


def decode_command(registers: list[int]) -> EPickCommand:
    """What a gripper reads from the three command registers (used by the simulator)."""
    _check_block(registers, "command")
    action = registers[0] >> 8
    return EPickCommand(
        activate=bool(action & 0x01),
        mode=(action >> 1) & 0x03,
        regulate=bool(action & 0x08),
        auto_release=bool(action & 0x10),
        pressure_kpa=registers[1] & 0xFF,
        timeout_ticks=registers[2] >> 8,
        min_pressure_kpa=registers[2] & 0xFF,
    )


@dataclass(frozen=True)
class EPickStatus:
    """The three status registers, decoded."""

    activated: bool  # gACT
    mode: int  # gMOD
    regulating: bool  # gGTO
    activation: int  # gSTA: 0 not activated, 3 operational
    object: int  # gOBJ
    actuator: int  # gVAS
    fault: int  # gFLT
    controller_fault: int  # kFLT (high nibble of the fault byte)
    pressure_request_kpa: int  # gPR echo
    pressure_kpa: int  # gPO actual, absolute

    @property
    def operational(self) -> bool:
        return self.activation == STA_OPERATIONAL

    @property
    def vacuum_kpa(self) -> float:
        """Relative vacuum below the atmosphere (0 at atmosphere or above)."""
        return float(max(0, ATMOSPHERE_KPA - self.pressure_kpa))

    @property
    def object_detected(self) -> bool:
        return self.object in (OBJ_AT_MIN, OBJ_AT_MAX)

    @property
    def gripping(self) -> bool:
        return self.actuator == VAS_GRIPPING

    @property
    def major_fault(self) -> bool:
        return self.fault >= MAJOR_FAULT_FROM and self.fault not in (0xB, 0xF)

    def fault_text(self) -> str:
        text = FAULT_TEXT.get(self.fault, f"unknown fault code 0x{self.fault:X}")
        if self.controller_fault:
            text += f" (controller fault 0x{self.controller_fault:X})"
        return text

    def describe(self) -> str:
        return (f"gSTA={self.activation} ({'operational' if self.operational else 'not activated'}), "
                f"gOBJ={self.object} ({OBJECT_TEXT[self.object]}), gVAS={self.actuator} ({ACTUATOR_TEXT[self.actuator]}), "
                f"gFLT=0x{self.fault:X} ({self.fault_text()}), pressure {self.pressure_kpa} kPa "
                f"(request {self.pressure_request_kpa} kPa)")


def decode_status(registers: list[int]) -> EPickStatus:
    """Decode the three registers read at 0x07D0."""
    _check_block(registers, "status")
    status_byte = registers[0] >> 8
    fault_byte = registers[1] >> 8
    return EPickStatus(
        activated=bool(status_byte & 0x01),
        mode=(status_byte >> 1) & 0x03,
        regulating=bool(status_byte & 0x08),
        activation=(status_byte >> 4) & 0x03,
        object=(status_byte >> 6) & 0x03,
        actuator=registers[0] & 0x03,
        fault=fault_byte & 0x0F,
        controller_fault=fault_byte >> 4,
        pressure_request_kpa=registers[1] & 0xFF,
        pressure_kpa=registers[2] >> 8,
    )


def encode_status(status: EPickStatus) -> list[int]:
    """The three status register values a gripper presents (used by the simulator)."""
    status_byte = (int(status.activated) | (status.mode & 0x03) << 1 | int(status.regulating) << 3
                   | (status.activation & 0x03) << 4 | (status.object & 0x03) << 6)
    fault_byte = (status.fault & 0x0F) | (status.controller_fault & 0x0F) << 4
    return [
        status_byte << 8 | (status.actuator & 0x03),
        fault_byte << 8 | _byte("pressure_request_kpa", status.pressure_request_kpa),
        _byte("pressure_kpa", status.pressure_kpa) << 8,
    ]


def _check_block(registers, what: str) -> None:
    if len(registers) != BLOCK_REGISTERS or any(not 0 <= r <= 0xFFFF for r in registers):
        raise ValueError(f"EPick {what} block must be {BLOCK_REGISTERS} registers of 0..0xFFFF, got {list(registers)!r}")
