"""OnRobot VG10 / VGC10 registers (Modbus TCP through the Compute Box, unit 65) as pure functions.

Holding registers:
    0 / 1   channel A / B control: high byte mode (0 release, 1 grip, 2 idle),
            low byte target vacuum in % ("should never exceed 80": the gripper takes
            more without an exception and regulates to at most 80 %; we never send more)
    2       current limit, mA (default 500, at most 1000)
    258/259 actual vacuum of channel A / B in 1/1000 of relative vacuum (read only)

Function codes the gripper documents: 3 (read holding registers), 6 and 16 (write one /
several), 23 (read/write); anything else is answered with exception 1. FC 4 finds no
input registers.

Relative vacuum 100 % is a perfect vacuum, one standard atmosphere (101.325 kPa)
below the ambient pressure; 80 % is about -81 kPa.
"""

from __future__ import annotations

DEFAULT_UNIT = 65
CONTROL_ADDRESS = 0  # channel A; channel B at 1
CURRENT_LIMIT_ADDRESS = 2
VACUUM_ADDRESS = 258  # channel A; channel B at 259
MAX_TARGET_PERCENT = 80
ATMOSPHERE_KPA = 101.325

MODE_RELEASE, MODE_GRIP, MODE_IDLE = 0, 1, 2
MODE_NAMES = {MODE_RELEASE: "release", MODE_GRIP: "grip", MODE_IDLE: "idle"}
FUNCTIONS = (3, 6, 16, 23)  # documented function codes (OnRobot Connectivity Guide, VG10/VGC10)
CHANNELS = {"A": 0, "B": 1}


def encode_control(mode: int, target_percent: int = 0) -> int:
    """One channel's control register value."""
    if mode not in MODE_NAMES:
        raise ValueError(f"mode must be one of {sorted(MODE_NAMES)} ({', '.join(MODE_NAMES.values())}), got {mode!r}")
    if not isinstance(target_percent, int) or not 0 <= target_percent <= MAX_TARGET_PERCENT:
        raise ValueError(f"target vacuum must be an integer 0..{MAX_TARGET_PERCENT} % (the gripper regulates at most "
                         f"{MAX_TARGET_PERCENT} %), got {target_percent!r}; nothing was sent")
    return mode << 8 | target_percent


def decode_control(value: int) -> tuple[int, int]:
    """(mode, target %) of a control register; the mode may be one the gripper rejects."""
    return value >> 8, value & 0xFF


def vacuum_percent(permille: int) -> float:
    """An actual-vacuum register (1/1000 relative vacuum) in %."""
    return permille / 10.0


def vacuum_kpa(permille: int) -> float:
    """An actual-vacuum register as kPa below the atmosphere."""
    return permille / 1000.0 * ATMOSPHERE_KPA


def encode_vacuum(percent: float) -> int:
    """The actual-vacuum register value for a vacuum in % (used by the simulator)."""
    return max(0, min(1000, round(percent * 10)))
