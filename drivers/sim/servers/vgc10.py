"""OnRobot VGC10 protocol simulator: Modbus TCP (unit 65) in front of the simulated world.

Registers as in `drivers.grippers.vgc10_registers`: holding 0 / 1 (channel A / B
control: mode release 0, grip 1, idle 2 in the high byte, target vacuum % in the
low byte), 2 (current limit, mA), 258 / 259 (actual vacuum, 1/1000, read only),
and 18 / 19, the same actual vacuum again: a public driver reads it there, and
answering both lets either reading of the register map work (read only too).

What the device documents, and so what the simulator answers (OnRobot, "Connectivity
Guide for Modbus RTU and TCP", section VG10/VGC10):
- function codes: "all writable registers can be accessed using function codes 6, 16
  or 23 and all readable registers using function codes 3 or 23". Anything else (FC 4
  read input registers, the coil functions, ...) is answered with exception 1 (illegal
  function) before its address is looked at: `00 01 00 00 00 06 41 04 01 02 00 02` ->
  `00 01 00 00 00 03 41 84 01`. The VGC10 has no input registers: its actual vacuum is
  a holding register;
- target vacuum: "should be provided in % vacuum. It should never exceed 80". The
  guide names no exception for a larger value, and public VG drivers written against
  the hardware command 255 (0xFF, e.g. takuya-ki/onrobot-vg's `vacuum_on`) and grip, so
  the gripper takes such a write; it regulates at most 80 %. The simulator does the
  same: the write is accepted and echoed, the register reads back what was written,
  and the channel regulates to min(target, 80) % (`00 01 00 00 00 06 41 06 00 00 01 64`,
  grip at 100 %, is echoed; the vacuum settles at 800 per mille, not 1000). The driver
  never sends more than 80 (drivers/grippers/vgc10.py);
- a mode above 2 is refused with exception 3 (illegal data value), and so is a current
  limit above 1000 mA ("should never be set above 1000 mA": here nothing public shows
  what the device does, and refusing is the reading that protects the pump).

Both channels work the world's one nozzle, reached through the simulated gripper
fake (`drivers.sim.devices.SimGripper`): when a channel starts gripping, the world
decides whether a sphere lies under the nozzle; the sphere stays on while any
channel grips or idles, and is put down when the last one releases. The vacuum of
a gripping channel rises first-order (time constant `tau_s`) towards its target when
sealed and stays at a percent or two on an open nozzle; release vents it quickly;
idle (pump off, valves closed) lets a sealed vacuum leak away slowly.

Fault knobs: those of `modbus_common.ModbusFaults` (drop the connection after N
messages, slow replies, malformed frames) and `drop_object()` (the held sphere falls).
"""

from __future__ import annotations

import math
import threading
import time

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.grippers.vgc10_registers import (
    CONTROL_ADDRESS,
    CURRENT_LIMIT_ADDRESS,
    DEFAULT_UNIT,
    FUNCTIONS,
    MAX_TARGET_PERCENT,
    MODE_GRIP,
    MODE_IDLE,
    MODE_NAMES,
    MODE_RELEASE,
    VACUUM_ADDRESS,
    decode_control,
    encode_vacuum,
)
from drivers.interfaces import VacuumLost
from drivers.sim.servers import run_until, sim_device, world_of
from drivers.sim.servers.modbus_common import ModbusFaults, SimModbusServer

TCP_PORT = 502
VACUUM_MIRROR_ADDRESS = 18  # channel A; B at 19: where one public driver reads the actual vacuum
OPEN_CUP_VACUUM_PERCENT = 1.5  # what the pump pulls through open cups


class Vgc10Model:
    """Two channels on one nozzle of the world: control registers in, vacuum registers out."""

    def __init__(self, gripper, tau_s: float = 0.15):
        self.gripper = gripper
        self.tau_s = tau_s
        self.lock = threading.Lock()
        self.modes = [MODE_RELEASE, MODE_RELEASE]
        self.targets = [0, 0]
        self.vacuum = [0.0, 0.0]  # %
        self.sealed = False
        self.updated = time.monotonic()

    def apply(self, controls: list[int], now: float) -> None:
        with self.lock:
            self._advance(now)
            was_gripping = MODE_GRIP in self.modes
            for channel, value in enumerate(controls):
                mode, target = decode_control(value)
                self.modes[channel] = mode
                self.targets[channel] = min(target, MAX_TARGET_PERCENT)  # the gripper regulates at most 80 %
            if MODE_GRIP in self.modes and not was_gripping and not self.sealed:
                try:
                    self.sealed = self.gripper.grip()
                except VacuumLost:  # the world's own vacuum-loss fault
                    self.sealed = False
            if self.sealed and all(mode == MODE_RELEASE for mode in self.modes):
                self.gripper.release()
                self.sealed = False

    def drop_object(self) -> bool:
        with self.lock:
            self._advance(time.monotonic())
            held, self.sealed = self.sealed, False
            if held:
                self.gripper.release()
            return held

    def vacuum_registers(self, now: float) -> list[int]:
        with self.lock:
            self._advance(now)
            return [encode_vacuum(v) for v in self.vacuum]

    def _advance(self, now: float) -> None:
        dt = max(0.0, now - self.updated)
        self.updated = now
        for channel, mode in enumerate(self.modes):
            if mode == MODE_GRIP:
                target, tau = (self.targets[channel], self.tau_s) if self.sealed else (OPEN_CUP_VACUUM_PERCENT, self.tau_s / 3)
            elif mode == MODE_IDLE and self.sealed:
                target, tau = 0.0, 5.0  # valves closed: the seal leaks slowly
            else:
                target, tau = 0.0, self.tau_s / 3
            self.vacuum[channel] = target + (self.vacuum[channel] - target) * math.exp(-dt / tau)


class Vgc10Server(SimModbusServer):
    """The VGC10 simulator in-process: `Vgc10Server(gripper).start()`, then `close()`.

    `gripper` is a SimGripper on the world the test shares (connected here if not yet).
    Modbus TCP on `host`:`port` (0 picks a free port).
    """

    def __init__(self, gripper, host: str = "127.0.0.1", port: int = 0, device_id: int = DEFAULT_UNIT,
                 faults: ModbusFaults | None = None, tau_s: float = 0.15):
        if gripper.state.value != "ready":
            gripper.connect()
        self.model = Vgc10Model(gripper, tau_s=tau_s)
        device = SimDevice(
            id=device_id,
            simdata=[
                SimData(CONTROL_ADDRESS, values=[0, 0, 500], datatype=DataType.REGISTERS),
                SimData(VACUUM_MIRROR_ADDRESS, count=2, values=0, datatype=DataType.REGISTERS, readonly=True),
                SimData(VACUUM_ADDRESS, count=2, values=0, datatype=DataType.REGISTERS, readonly=True),
            ],
            action=self._action,
        )
        super().__init__(device, "tcp", host, port, faults=faults, functions=frozenset(FUNCTIONS))

    def drop_object(self) -> bool:
        """Fault knob: the held sphere drops off the cups (vacuum loss). True if one was held."""
        return self.model.drop_object()

    async def _action(self, function_code, start_address, address, count, registers, values):
        now = time.monotonic()
        end = address + count
        if values is not None:
            if address <= CURRENT_LIMIT_ADDRESS < end:
                limit = int(values[CURRENT_LIMIT_ADDRESS - address])
                if not 0 <= limit <= 1000:
                    return ExcCodes.ILLEGAL_VALUE
            controls = list(registers[CONTROL_ADDRESS - start_address:CONTROL_ADDRESS - start_address + 2])
            touched = False
            for i, value in enumerate(values):
                channel = address + i - CONTROL_ADDRESS
                if channel in (0, 1):
                    if decode_control(int(value))[0] not in MODE_NAMES:
                        return ExcCodes.ILLEGAL_VALUE
                    controls[channel] = int(value)
                    touched = True
            if touched:
                self.model.apply(controls, now)
            return None
        for base in (VACUUM_ADDRESS, VACUUM_MIRROR_ADDRESS):
            if address < base + 2 and end > base:
                offset = base - start_address
                registers[offset:offset + 2] = self.model.vacuum_registers(now)
        return None


def start(world, host: str = "127.0.0.1", port: int = TCP_PORT, options: dict | None = None) -> Vgc10Server:
    """Serve the cups of `world` (shared with the caller's arm and cameras) over Modbus TCP on `port`.
    `options` are `ModbusFaults` fields and `device_id`, `tau_s`. Returns the running server."""
    options = dict(options or {})
    settings_keys = ("device_id", "tau_s")
    settings = {key: options.pop(key) for key in settings_keys if key in options}
    faults = ModbusFaults.from_options(options, extra_allowed=settings_keys)
    return Vgc10Server(sim_device("gripper", world), host, port, faults=faults, **settings).start()


def start_for_cell(world, spec, arm_limits: dict | None = None) -> Vgc10Server:
    """The simulator of a cell file's `sim.servers` entry (protocol vgc10): Modbus TCP."""
    return start(world, spec.host, TCP_PORT if spec.port is None else spec.port, options=spec.options)


def serve(world_config=None, host: str = "127.0.0.1", port: int = TCP_PORT, options: dict | None = None,
          stop: threading.Event | None = None, world=None) -> None:
    """Serve until `stop` is set (see `start`); the world is `world` or one built from `world_config`."""
    run_until(start(world_of(world_config, world), host, port, options), stop)
