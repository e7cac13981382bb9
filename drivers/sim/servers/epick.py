"""Robotiq EPick protocol simulator: Modbus RTU (serial port or RTU over TCP) in front of the simulated world.

Registers as in `drivers.grippers.epick_registers` (command block FC16 at 0x03E8,
status block at 0x07D0 answered to FC04 and FC03 alike, device id 9). The vacuum
nozzle is the world's, reached through the simulated gripper fake
(`drivers.sim.devices.SimGripper`), so an object is sealed only when a sphere lies
under the nozzle (`world.grip()` decides) and the world's gripper fault settings
apply.

Behaviour (wall-clock time, since the driver polls in real time):
- activation: rACT 0 -> 1 makes gSTA "in progress" (1), then operational (3) after
  `activation_s`; rACT 0 resets (clears faults, stops the generator);
- a grip (rGTO=1, rPR < 100) asks the world for the sphere under the nozzle; the
  pressure falls first-order (time constant `tau_s`) towards rPR when sealed, and
  stays within a few kPa of the atmosphere on an open nozzle. gOBJ: 0 while
  regulating, 1 once at or below rFR, 2 once within 1 kPa of rPR, 3 when rSP x 100 ms
  pass without reaching rFR (with fault 0x6, grip timeout) or when a detected object
  is lost (the pressure rises above rFR);
- rPR = 100 is a passive release (valve to atmosphere, gVAS 2), rPR > 100 an active
  one (blow-off for rSP x 100 ms, gVAS 3); either puts the held sphere down;
- a command with rGTO=1 before activation sets fault 0x7 and is ignored; rMOD 2 or
  3 (reserved) is refused with Modbus exception 3 (illegal data value).

Addressing (on a pty and over TCP alike, `modbus_common`): only requests for its own
device id (9 unless `device_id` says otherwise) are executed and answered. A request
for any other id gets no reply at all, as on an RS-485 line where only the addressed
device answers (`08 04 07 D0 00 03 B0 1F`: silence). Device id 0 is the Modbus
broadcast: a command-block write (FC16, FC06) is executed and never answered
(`00 10 03 E8 00 03 06 01 00 00 00 00 00 ...` activates, silently); a broadcast read
is ignored. The manual does not say whether the EPick honours broadcasts; the Modbus
serial-line specification obliges every server to, so the simulator does, and the
driver never sends one.

Fault knobs: those of `modbus_common.ModbusFaults` (drop the link after N messages,
slow replies, malformed frames), plus `drop_object()` (the held sphere falls: vacuum
loss) and `inject_fault(code)` (e.g. 0x8 over temperature) on the server.
"""

from __future__ import annotations

import math
import threading
import time

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.grippers.epick_registers import (
    ATMOSPHERE_KPA,
    BLOCK_REGISTERS,
    COMMAND_ADDRESS,
    DEFAULT_DEVICE_ID,
    FAULT_GRIP_TIMEOUT,
    FAULT_NOT_ACTIVATED,
    MIN_GRIP_PRESSURE_KPA,
    OBJ_AT_MAX,
    OBJ_AT_MIN,
    OBJ_NONE,
    OBJ_REGULATING,
    STA_NOT_ACTIVATED,
    STA_OPERATIONAL,
    VAS_ACTIVE_RELEASE,
    VAS_GRIPPING,
    VAS_PASSIVE_RELEASE,
    VAS_STANDBY,
    EPickCommand,
    EPickStatus,
    decode_command,
    encode_status,
)
from drivers.interfaces import VacuumLost
from drivers.sim.servers import run_until, sim_device, world_of
from drivers.sim.servers.modbus_common import ModbusFaults, SimModbusServer

TCP_PORT = 54321  # the UR tool-communication forwarder's port
OPEN_NOZZLE_VACUUM_KPA = 3.0  # what the generator pulls through an open nozzle
STA_IN_PROGRESS = 1


class EPickModel:
    """The gripper's behaviour: command registers in, status registers out, over wall-clock time."""

    def __init__(self, gripper, tau_s: float = 0.15, activation_s: float = 0.05):
        self.gripper = gripper  # a connected SimGripper on the shared world
        self.tau_s = tau_s
        self.activation_s = activation_s
        self.lock = threading.Lock()
        self.command = EPickCommand(activate=False, mode=0, pressure_kpa=0, min_pressure_kpa=0)
        self.pressure = float(ATMOSPHERE_KPA)
        self.sealed = False  # an object closes the nozzle
        self.activated_at: float | None = None
        self.action_started = 0.0  # when the current grip / release began
        self.detected = False  # the current grip reached rFR at least once
        self.object = OBJ_REGULATING
        self.fault = 0
        self.injected_fault = 0
        self.updated = time.monotonic()

    # -- commands -----------------------------------------------------------------
    def apply(self, command: EPickCommand, now: float) -> None:
        with self.lock:
            self._advance(now)
            previous, self.command = self.command, command
            if not command.activate:  # reset: clears faults, generator off
                self.activated_at = None
                self.fault = 0
                self.object = OBJ_REGULATING
                return
            if not previous.activate or self.activated_at is None:
                self.activated_at = now
            if command.regulate and not self._operational(now):
                self.fault = FAULT_NOT_ACTIVATED
                return
            self.fault = 0
            if not command.regulate:
                return
            changed = (not previous.regulate or previous.pressure_kpa != command.pressure_kpa
                       or previous.activate != command.activate)
            if not changed:
                return
            self.action_started = now
            if command.pressure_kpa < ATMOSPHERE_KPA:  # grip
                self.detected = False
                self.object = OBJ_REGULATING
                self.sealed = self._world_grip()
            else:  # passive or active release
                self.gripper.release()
                self.sealed = False

    def _world_grip(self) -> bool:
        try:
            return self.gripper.grip()
        except VacuumLost:  # the world's own vacuum-loss fault: the sphere did not stay on
            return False

    def drop_object(self) -> bool:
        """Fault knob: the held sphere falls off the nozzle. True if there was one."""
        with self.lock:
            self._advance(time.monotonic())
            held = self.sealed
            if held:
                self.gripper.release()
                self.sealed = False
            return held

    # -- status -------------------------------------------------------------------
    def status_registers(self, now: float) -> list[int]:
        with self.lock:
            self._advance(now)
            cmd = self.command
            operational = self._operational(now)
            activation = STA_NOT_ACTIVATED
            if cmd.activate:
                activation = STA_OPERATIONAL if operational else STA_IN_PROGRESS
            status = EPickStatus(
                activated=cmd.activate, mode=cmd.mode, regulating=cmd.regulate, activation=activation,
                object=self.object, actuator=self._actuator(now), fault=self.injected_fault or self.fault,
                controller_fault=0, pressure_request_kpa=cmd.pressure_kpa,
                pressure_kpa=max(0, min(255, round(self.pressure))))
            return encode_status(status)

    def _operational(self, now: float) -> bool:
        return self.activated_at is not None and now - self.activated_at >= self.activation_s

    def _regulating(self) -> bool:
        return self.command.activate and self.command.regulate and self.fault != FAULT_NOT_ACTIVATED

    def _actuator(self, now: float) -> int:
        if not self._regulating():
            return VAS_STANDBY
        request = self.command.pressure_kpa
        if request < ATMOSPHERE_KPA:
            return VAS_GRIPPING
        if request == ATMOSPHERE_KPA:
            return VAS_PASSIVE_RELEASE if self.pressure < ATMOSPHERE_KPA - 0.5 else VAS_STANDBY
        blowing = now - self.action_started < max(self.command.timeout_ticks * 0.1, 0.05)
        return VAS_ACTIVE_RELEASE if blowing else VAS_STANDBY

    def _target(self, now: float) -> tuple[float, float]:
        """(pressure the nozzle tends to, time constant) for the present command."""
        if not self._regulating():
            return ATMOSPHERE_KPA, (5.0 if self.sealed else self.tau_s / 3)  # generator off: a sealed part leaks slowly
        request = self.command.pressure_kpa
        if request < ATMOSPHERE_KPA:
            if request == 0:  # generator always on, full power
                request = MIN_GRIP_PRESSURE_KPA
            if self.sealed:
                return max(request, MIN_GRIP_PRESSURE_KPA), self.tau_s
            return ATMOSPHERE_KPA - OPEN_NOZZLE_VACUUM_KPA, self.tau_s / 3
        if request > ATMOSPHERE_KPA and self._actuator(now) == VAS_ACTIVE_RELEASE:
            return min(request, ATMOSPHERE_KPA + 20), self.tau_s / 3  # blow-off
        return ATMOSPHERE_KPA, self.tau_s / 2

    def _advance(self, now: float) -> None:
        """Integrate the first-order pressure response up to `now` and update gOBJ."""
        dt = max(0.0, now - self.updated)
        self.updated = now
        target, tau = self._target(now)
        self.pressure = target + (self.pressure - target) * math.exp(-dt / tau)
        cmd = self.command
        if not self._regulating():
            return
        if cmd.pressure_kpa >= ATMOSPHERE_KPA:  # releasing
            self.object = OBJ_NONE if self.pressure > cmd.min_pressure_kpa else OBJ_AT_MIN
            return
        if self.pressure <= cmd.min_pressure_kpa:
            self.detected = True
            self.fault = 0
            at_request = self.pressure <= max(cmd.pressure_kpa, MIN_GRIP_PRESSURE_KPA) + 1
            self.object = OBJ_AT_MAX if at_request else OBJ_AT_MIN
        elif self.detected:
            self.object = OBJ_NONE  # lost
        elif cmd.timeout_ticks and now - self.action_started >= cmd.timeout_ticks * 0.1:
            self.object = OBJ_NONE
            self.fault = FAULT_GRIP_TIMEOUT
        else:
            self.object = OBJ_REGULATING


class EPickServer(SimModbusServer):
    """The EPick simulator in-process: `EPickServer(gripper, kind=...).start()`, then `close()`.

    `gripper` is a SimGripper on the world the test shares with its arm and cameras
    (it is connected here if it is not yet). `kind` is "rtu-over-tcp" (port 0 picks
    a free one) or "serial" (`serial_port`: e.g. one end of a socat pty pair).
    """

    def __init__(self, gripper, kind: str = "rtu-over-tcp", host: str = "127.0.0.1", port: int = 0,
                 serial_port: str | None = None, baudrate: int = 115200, device_id: int = DEFAULT_DEVICE_ID,
                 faults: ModbusFaults | None = None, tau_s: float = 0.15, activation_s: float = 0.05):
        if kind not in ("rtu-over-tcp", "serial"):
            raise ValueError(f"the EPick speaks Modbus RTU: kind must be 'rtu-over-tcp' or 'serial', got {kind!r}")
        if not 1 <= device_id <= 247:
            raise ValueError(f"device_id {device_id}: a Modbus RTU device has an id 1..247 (0 is the broadcast)")
        if gripper.state.value != "ready":
            gripper.connect()
        self.model = EPickModel(gripper, tau_s=tau_s, activation_s=activation_s)
        device = SimDevice(
            id=device_id,
            simdata=[
                SimData(COMMAND_ADDRESS, count=BLOCK_REGISTERS, values=0, datatype=DataType.REGISTERS),
                SimData(0x07D0, count=BLOCK_REGISTERS, values=0, datatype=DataType.REGISTERS, readonly=True),
            ],
            action=self._action,
        )
        super().__init__(device, kind, host, port, serial_port, baudrate, faults)

    def drop_object(self) -> bool:
        """Fault knob: the held sphere drops off the nozzle (vacuum loss). True if one was held."""
        return self.model.drop_object()

    def inject_fault(self, code: int) -> None:
        """Fault knob: the gripper reports gFLT `code` (0 clears it), e.g. 0x8 over temperature."""
        self.model.injected_fault = code & 0x0F

    async def _action(self, function_code, start_address, address, count, registers, values):
        now = time.monotonic()
        end = address + count
        if values is not None:  # a write (only the command block is writable)
            offset = COMMAND_ADDRESS - start_address
            block = list(registers[offset:offset + BLOCK_REGISTERS])
            for i, value in enumerate(values):
                block[address + i - COMMAND_ADDRESS] = int(value)
            command = decode_command(block)
            if command.mode > 1:
                return ExcCodes.ILLEGAL_VALUE  # rMOD 2 and 3 are reserved
            self.model.apply(command, now)
            return None
        if address < 0x07D0 + BLOCK_REGISTERS and end > 0x07D0:  # a read touching the status block
            offset = 0x07D0 - start_address
            registers[offset:offset + BLOCK_REGISTERS] = self.model.status_registers(now)
        return None


def start(world, host: str = "127.0.0.1", port: int = TCP_PORT, options: dict | None = None,
          serial_port: str | None = None) -> EPickServer:
    """Serve the nozzle of `world` (shared with the caller's arm and cameras): RTU over TCP on `port`,
    or RTU on `serial_port` if given. `options` are `ModbusFaults` fields and `device_id`, `baudrate`,
    `tau_s`, `activation_s`. Returns the running server; close() stops it."""
    options = dict(options or {})
    settings_keys = ("device_id", "baudrate", "tau_s", "activation_s")
    settings = {key: options.pop(key) for key in settings_keys if key in options}
    faults = ModbusFaults.from_options(options, extra_allowed=settings_keys)
    kind = "serial" if serial_port else "rtu-over-tcp"
    return EPickServer(sim_device("gripper", world), kind, host, port, serial_port, faults=faults, **settings).start()


def start_for_cell(world, spec, arm_limits: dict | None = None) -> EPickServer:
    """The simulator of a cell file's `sim.servers` entry (protocol epick): RTU over TCP, or RTU on its serial_port."""
    return start(world, spec.host, TCP_PORT if spec.port is None else spec.port, options=spec.options, serial_port=spec.serial_port)


def serve(world_config=None, host: str = "127.0.0.1", port: int = TCP_PORT, options: dict | None = None,
          stop: threading.Event | None = None, world=None, serial_port: str | None = None) -> None:
    """Serve until `stop` is set (see `start`); the world is `world` or one built from `world_config`."""
    run_until(start(world_of(world_config, world), host, port, options, serial_port), stop)
