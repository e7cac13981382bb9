"""The UR simulator: dashboard (29999), primary and secondary interfaces (30001, 30002), script port
(30003) and RTDE (30004) around one Controller.

Ports are fixed as on a real controller (ur_rtde hard-codes 30004), so several
simulated robots run side by side on different loopback addresses (127.0.0.2, …).

A 500 Hz cycle (125 Hz if the announced controller version is a CB3, major < 5)
advances the controller: the emulated control script takes one step, then every
started RTDE connection gets a data package for each of its output recipes that is
due. The timestamp is the cycle count times the period. A host too busy to keep the pace
(this is Python on a shared machine, not a real-time controller) runs late cycles at
once, up to 10 periods (20 ms) behind; after a longer stall the missed cycles are
skipped and the timestamp jumps, so a benchmark sees the gap (tools/bench_rtde.py
reports both the timestamp gaps and the arrival intervals).

The simulator MUST run in its own process when its client is ur_rtde in Python: the
pybind11 constructors hold the GIL while they wait for the controller, so a simulator
thread in the client's process would never run. `SimulatorProcess` starts one with
`python -m drivers.sim.servers.ur`, waits until it says it serves (every port listening; exit
status 3 and PortsTaken if another simulator or controller holds the address), and stops it
with SIGTERM (sockets closed, exit status 0).
"""

from __future__ import annotations

import fcntl
import itertools
import json
import logging
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from drivers.limits import WorkspaceBox
from drivers.registry import DriverContext, backend_class
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.remote import ArmHost, RemoteArm
from drivers.sim.servers import ANY_TURN, accepted, received, sim_device
from drivers.sim.servers.ur import dashboard, primary, rtde
from drivers.sim.servers.ur.controller import RUNNING, ArmSource, Controller, UrSimFaults, UrSimOptions, parse_options
from drivers.sim.servers.ur.script import ControlScript, is_rtde_control_script, register_offset

log = logging.getLogger(__name__)

PORTS = {"dashboard": 29999, **primary.PORTS, "script": 30003, "rtde": 30004}
EXIT_PORTS_TAKEN = 3  # the child's exit status when it cannot listen (another simulator or controller is there)
READY_LINE = "ur sim: serving on "  # the child prints this line on stdout once every port listens
AUTHKEY_ENV = "CELLCTL_SIM_AUTHKEY"
ROOT = Path(__file__).resolve().parents[4]
_POLL_S = 0.5  # server-side reads wake up this often to notice a shutdown
_SEND_TIMEOUT_S = 1.0  # a client that does not read its data packages for this long is dropped
_CATCH_UP_CYCLES = 10  # a cycle up to this many periods late is still run (sent at once); later ones are skipped


class _Connection:
    """A client socket the server may have to close from another thread."""

    def __init__(self, sock: socket.socket, peer):
        self.sock = sock
        self.peer = peer
        self.closed = threading.Event()
        self.send_lock = threading.RLock()
        sock.settimeout(_POLL_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send(self, data: bytes) -> bool:
        with self.send_lock:
            if self.closed.is_set():
                return False
            try:
                self.sock.settimeout(_SEND_TIMEOUT_S)
                self.sock.sendall(data)
                return True
            except OSError as exc:
                log.info("ur sim: dropping %s: send failed (%s)", self.peer, exc)
                self.close()
                return False
            finally:
                if not self.closed.is_set():
                    self.sock.settimeout(_POLL_S)

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class _OutputRecipe:
    def __init__(self, recipe: rtde.Recipe, frequency: float, base_hz: float):
        self.recipe = recipe
        self.every = max(1, round(base_hz / frequency)) if frequency > 0 else 1


class RtdeSession(_Connection):
    """One RTDE client: handshake and inputs in its own thread, data packages from the cycle thread."""

    _ids = itertools.count(1)

    def __init__(self, sock, peer, server: UrSimulator):
        super().__init__(sock, peer)
        self.server = server
        self.session_id = next(self._ids)
        self.outputs: list[_OutputRecipe] = []
        self.inputs: dict[int, rtde.Recipe] = {}
        self.owned_inputs: set[str] = set()
        self.started = False
        self.packets = 0
        self.silenced = False  # fault knob silent_after_packets has stopped its data packages

    def run(self) -> None:
        c = self.server.controller
        try:
            while not self.closed.is_set():
                try:
                    kind, payload = rtde.read_message(self.sock)
                except TimeoutError:
                    continue
                self.handle(kind, payload)
        except (ConnectionError, OSError):
            pass
        except (rtde.ProtocolError, struct.error) as exc:
            log.warning("ur sim: RTDE client %s sent a malformed message: %s; closing it", self.peer, exc)
            c.note(f"RTDE malformed message from {self.peer}: {exc}")
        finally:
            self.close()
            with c.lock:
                self.server.release_inputs(self)

    def _reply(self, kind: int, payload: bytes) -> None:
        self.send(rtde.frame(kind, payload))

    def handle(self, kind: int, payload: bytes) -> None:
        server, c = self.server, self.server.controller
        if kind == rtde.REQUEST_PROTOCOL_VERSION:
            if len(payload) != 2:
                raise rtde.ProtocolError(f"protocol version request has {len(payload)} bytes, expected 2 (>H)")
            (version,) = struct.unpack(">H", payload)
            self._reply(kind, struct.pack(">B", 1 if version in (1, 2) else 0))
        elif kind == rtde.GET_URCONTROL_VERSION:
            self._reply(kind, struct.pack(">IIII", *c.options.version))
        elif kind == rtde.CONTROL_PACKAGE_SETUP_OUTPUTS:
            if len(payload) < 8:
                raise rtde.ProtocolError(f"output setup has {len(payload)} bytes, expected a >d frequency and names")
            (frequency,) = struct.unpack(">d", payload[:8])
            names = rtde.parse_names(payload[8:])
            types = tuple(rtde.OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names)
            valid = bool(names) and all(t != "NOT_FOUND" for t in types) and 0 < frequency <= server.base_hz
            recipe = rtde.Recipe(len(self.outputs) + 1 if valid else 0, tuple(names), types)
            if valid:
                self.outputs.append(_OutputRecipe(recipe, frequency, server.base_hz))
            else:
                c.note(f"RTDE output setup refused (frequency {frequency}, unknown: "
                       f"{[n for n, t in zip(names, types) if t == 'NOT_FOUND']})")
            self._reply(kind, struct.pack(">B", recipe.recipe_id) + ",".join(types).encode())
        elif kind == rtde.CONTROL_PACKAGE_SETUP_INPUTS:
            names = rtde.parse_names(payload)
            with c.lock:
                types = tuple(server.input_type(self, n) for n in names)
                valid = bool(names) and all(t in rtde.TYPE_CODES for t in types)
                if valid:  # a refused recipe claims nothing
                    server.claim_inputs(self, names)
            recipe_id = len(self.inputs) + 1 if valid else 0
            recipe = rtde.Recipe(recipe_id, tuple(names), types)
            if valid:
                self.inputs[recipe_id] = recipe
            self._reply(kind, struct.pack(">B", recipe_id) + ",".join(types).encode())
        elif kind == rtde.CONTROL_PACKAGE_START:
            with self.send_lock:  # the reply must precede the first data package
                ok = bool(self.outputs)
                self._reply(kind, struct.pack(">B", 1 if ok else 0))
                self.started = ok
        elif kind == rtde.CONTROL_PACKAGE_PAUSE:
            with self.send_lock:
                self.started = False
            self._reply(kind, struct.pack(">B", 1))
        elif kind == rtde.DATA_PACKAGE:
            if not payload:
                raise rtde.ProtocolError("data package without a recipe id")
            recipe = self.inputs.get(payload[0])
            if recipe is None:
                raise rtde.ProtocolError(f"data package for input recipe {payload[0]}, which was never set up "
                                         f"(set up: {sorted(self.inputs) or 'none'})")
            c.write_inputs(recipe.unpack(payload))
        # text messages (M) from a client need no answer

    def send_due(self, cycle: int, values: dict) -> None:
        if not self.started:
            return
        faults = self.server.controller.faults
        for out in self.outputs:
            if cycle % out.every:
                continue
            if faults.silent_after_packets and self.packets >= faults.silent_after_packets:
                if not self.silenced:
                    self.silenced = True
                    self.server.controller.note(f"RTDE data to {self.peer} stops, socket kept open (fault knob)")
                return
            self.packets += 1
            if faults.malformed_after_packets and self.packets > faults.malformed_after_packets:
                self.server.controller.note(f"sending a malformed RTDE frame to {self.peer} (fault knob)")
                self.send(rtde.HEADER.pack(2, rtde.DATA_PACKAGE))  # size below the header itself
                self.close()
                return
            self.send(rtde.frame(rtde.DATA_PACKAGE, out.recipe.pack(values)))


class PortsTaken(OSError):
    """The simulator cannot listen on its fixed ports at that address (something else already does)."""


class UrSimulator:
    """The ports of a simulated UR controller on `host` (PORTS), around one Controller and its arm."""

    def __init__(self, arm, host: str = "127.0.0.1", options: UrSimOptions | dict | None = None,
                 ports: dict[str, int] | None = None):
        options = parse_options(options)
        self.host = host
        self.ports = {**PORTS, **(ports or {})}
        unknown = set(self.ports) - set(PORTS)
        if unknown:
            raise ValueError(f"ports: unknown {sorted(unknown)}; allowed: {', '.join(PORTS)}")
        self.controller = Controller(arm, options)
        self.controller.on_drop = self._drop_all
        self.base_hz = 500.0 if options.version[0] >= 5 else 125.0
        self._closed = threading.Event()
        self._listeners: dict[str, socket.socket] = {}
        self._connections: set[_Connection] = set()
        self._sessions: set[RtdeSession] = set()
        self._input_owner: dict[str, int] = {}
        self._refuse_until = 0.0
        self._threads: list[threading.Thread] = []
        self.missed_cycles = 0

    # -- life cycle ------------------------------------------------------------------------------
    def start(self) -> UrSimulator:
        try:
            for name in PORTS:  # RTDE last: once 30004 accepts, everything is up
                try:
                    sock = socket.create_server((self.host, self.ports[name]), reuse_port=False)
                except OSError as exc:
                    raise PortsTaken(exc.errno, f"cannot listen on {self.host}:{self.ports[name]} ({name}): "
                                                f"{exc.strerror or exc}; another UR simulator or controller is "
                                                "there: pick another loopback address") from exc
                sock.settimeout(_POLL_S)
                self._listeners[name] = sock
                self.ports[name] = sock.getsockname()[1]
        except OSError:
            self.close()
            raise
        handlers = {"dashboard": self._dashboard, "primary": self._client_interface,
                    "secondary": self._client_interface, "script": self._script, "rtde": self._rtde}
        for name in PORTS:
            self._spawn(self._accept, name, handlers[name])
        self._spawn(self._cycle)
        log.info("ur sim on %s: %s", self.host, self.ports)
        return self

    def _spawn(self, target, *args) -> None:
        thread = threading.Thread(target=target, args=args, name=f"ur-sim-{target.__name__}", daemon=True)
        thread.start()
        self._threads.append(thread)

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        for sock in self._listeners.values():
            try:
                sock.shutdown(socket.SHUT_RDWR)  # wakes a thread blocked in accept()
            except OSError:
                pass
            sock.close()
        for conn in list(self._connections):
            conn.close()
        with self.controller.lock:
            if self.controller.script is not None:
                self.controller.script.halt()
        for thread in self._threads:
            thread.join(timeout=2.0)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    # -- connections ----------------------------------------------------------------------------------
    def _accept(self, name: str, handler) -> None:
        listener = self._listeners[name]
        for sock, peer in accepted(listener, self._closed):
            if time.monotonic() < self._refuse_until:  # the simulated network is down
                sock.close()
                continue
            threading.Thread(target=handler, args=(sock, peer), name=f"ur-sim-{name}", daemon=True).start()

    def _track(self, conn: _Connection) -> None:
        self._connections.add(conn)

    def _untrack(self, conn: _Connection) -> None:
        self._connections.discard(conn)
        if isinstance(conn, RtdeSession):
            self._sessions.discard(conn)

    def _drop_all(self) -> None:
        """Fault knob: the network goes down (every connection closed, new ones refused for a while)."""
        self._refuse_until = time.monotonic() + self.controller.faults.outage_s
        for conn in list(self._connections):
            conn.close()

    def _rtde(self, sock, peer) -> None:
        session = RtdeSession(sock, peer, self)
        self._track(session)
        self._sessions.add(session)
        try:
            session.run()
        finally:
            self._untrack(session)

    def input_type(self, session: RtdeSession, name: str) -> str:
        """The type of an input variable, or NOT_FOUND, or IN_USE when another connection writes it."""
        kind = rtde.INPUT_TYPES.get(name)
        if kind is None:
            return "NOT_FOUND"
        owner = self._input_owner.get(name)
        return "IN_USE" if owner is not None and owner != session.session_id else kind

    def claim_inputs(self, session: RtdeSession, names) -> None:
        for name in names:
            self._input_owner[name] = session.session_id
            session.owned_inputs.add(name)

    def release_inputs(self, session: RtdeSession) -> None:
        for name in session.owned_inputs:
            if self._input_owner.get(name) == session.session_id:
                del self._input_owner[name]

    def _dashboard(self, sock, peer) -> None:
        conn = _Connection(sock, peer)
        self._track(conn)
        c = self.controller
        try:
            if not conn.send((dashboard.WELCOME + "\n").encode()):
                return
            buffer = b""
            for chunk in received(sock, conn.closed, 4096):
                buffer += chunk
                if len(buffer) > 4096 and b"\n" not in buffer:
                    conn.send(b"could not understand: request longer than 4096 bytes without a newline\n")
                    return
                while b"\n" in buffer:
                    line, buffer = buffer.split(b"\n", 1)
                    request = line.decode("utf-8", "replace").rstrip("\r")
                    delay = c.dashboard_delay_s(request)
                    if delay and conn.closed.wait(delay):  # a dropped connection ends the wait
                        return
                    reply, close = dashboard.answer(c, request)
                    conn.send((reply + "\n").encode())
                    if close:
                        return
        except OSError:
            return
        finally:
            conn.close()
            self._untrack(conn)

    def _script(self, sock, peer) -> None:
        conn = _Connection(sock, peer)
        self._track(conn)
        try:
            self._read_programs(conn)
        finally:
            conn.close()
            self._untrack(conn)

    def _read_programs(self, conn: _Connection) -> None:
        """URScript text from a connection until it closes: each complete program replaces the running one."""
        text = ""
        try:
            for chunk in received(conn.sock, conn.closed, 65536):
                text += chunk.decode("utf-8", "replace")
                while True:
                    program, text = split_program(text)
                    if program is None:
                        break
                    self.load_program(program)
        except OSError:
            return

    def _client_interface(self, sock, peer) -> None:
        """Primary or secondary interface: the version message, robot state at 10 Hz, URScript in."""
        conn = _Connection(sock, peer)
        self._track(conn)
        try:
            if not conn.send(primary.version_message(self.controller.options.version)):
                return
            self._spawn_daemon(self._stream_state, conn)
            self._read_programs(conn)
        finally:
            conn.close()
            self._untrack(conn)

    def _stream_state(self, conn: _Connection) -> None:
        c = self.controller
        start = time.monotonic()
        tick = 0
        while not conn.closed.is_set() and not self._closed.is_set():
            now = time.monotonic()
            message = primary.robot_state_message(c, int((now - c.started) * 1e6))
            if not conn.send(message):
                return
            tick += 1
            delay = start + tick * primary.PERIOD_S - time.monotonic()
            if delay < -primary.PERIOD_S:  # a stall: go on from now rather than send a burst
                start, tick = time.monotonic(), 0
            elif conn.closed.wait(max(delay, 0.0)):
                return

    def _spawn_daemon(self, target, *args) -> None:
        threading.Thread(target=target, args=args, name=f"ur-sim-{target.__name__}", daemon=True).start()

    def load_program(self, program: str) -> None:
        """A complete program arrived on the script port: it replaces the running one."""
        c = self.controller
        first = program.lstrip().splitlines()[0] if program.strip() else ""
        with c.lock:
            c.stop_program("replaced by a newly received program")
            if c.robot_mode != RUNNING or c.protective_stopped:
                c.note(f"program {first!r} not started: robot mode {c.robot_mode}, safety mode {c.safety_mode}")
                return
            if not is_rtde_control_script(program):
                c.note(f"program {first!r} received; only ur_rtde's rtde_control script is emulated, it ends at once")
                return
            c.script = ControlScript(c, register_offset(program))
            c.script.start()
            c.note(f"rtde_control script started ({len(program)} characters, register offset {c.script.reg_offset})")

    # -- the controller cycle --------------------------------------------------------------------------------
    def _cycle(self) -> None:
        period = 1.0 / self.base_hz
        start = time.monotonic()
        cycle = 0
        while not self._closed.is_set():
            cycle += 1
            deadline = start + cycle * period
            delay = deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif -delay > _CATCH_UP_CYCLES * period:  # a long stall: skip those cycles (a gap a client can see)
                skipped = int(-delay / period)
                self.missed_cycles += skipped
                cycle += skipped
            c = self.controller
            with c.lock:
                if c.script is not None:
                    c.script.step()
                sessions = [s for s in self._sessions if s.started]
                if not sessions:
                    continue
                names = {n for s in sessions for o in s.outputs for n in o.recipe.names}
                values = output_values(c, names, cycle * period)
            for session in sessions:
                session.send_due(cycle, values)


# --- output values ----------------------------------------------------------------------------


_ZERO = {"BOOL": False, "UINT8": 0, "UINT32": 0, "UINT64": 0, "INT32": 0, "DOUBLE": 0.0,
         "VECTOR3D": (0.0,) * 3, "VECTOR6D": (0.0,) * 6, "VECTOR6INT32": (0,) * 6, "VECTOR6UINT32": (0,) * 6}
_REGISTER = re.compile(r"^(input|output)_(int|double)_register_(\d+)$")


def output_values(c: Controller, names, timestamp: float) -> dict:
    """Values of the requested output variables at this cycle (the arm stands still between moves)."""
    actual = c.actual_flange()
    moving = c.script is not None and c.script._busy()
    known = {
        "timestamp": lambda: timestamp,
        "actual_q": lambda: c.joints(actual), "target_q": lambda: c.joints(c.target_flange),
        "actual_TCP_pose": lambda: c.tcp_pose(actual), "target_TCP_pose": lambda: c.tcp_pose(c.target_flange),
        "robot_mode": lambda: c.robot_mode, "safety_mode": lambda: c.safety_mode,
        "safety_status": lambda: c.safety_mode, "runtime_state": lambda: c.runtime_state,
        "robot_status_bits": c.robot_status_bits, "safety_status_bits": c.safety_status_bits,
        # JOINT_RUNNING / JOINT_POWER_OFF
        "joint_mode": lambda: (253,) * 6 if c.robot_mode == RUNNING else (236,) * 6,
        "speed_scaling": lambda: 1.0, "target_speed_fraction": lambda: 1.0,
        "actual_main_voltage": lambda: 48.0,
        "actual_robot_voltage": lambda: 48.0 if c.robot_mode == RUNNING else 0.0,
        "actual_robot_current": lambda: 0.6 if moving else 0.3,
        "actual_joint_voltage": lambda: (47.9,) * 6, "joint_temperatures": lambda: (32.0,) * 6,
        "actual_execution_time": lambda: 0.2, "tool_temperature": lambda: 30.0,
        "output_bit_registers0_to_31": lambda: 0, "output_bit_registers32_to_63": lambda: 0,
        "input_bit_registers0_to_31": lambda: c.in_bits & 0xFFFFFFFF,
        "input_bit_registers32_to_63": lambda: c.in_bits >> 32,
        "actual_tool_accelerometer": lambda: (0.0, 0.0, -9.81),
    }
    values = {}
    for name in names:
        if name in known:
            values[name] = known[name]()
            continue
        match = _REGISTER.match(name)
        if match:
            direction, kind, index = match.group(1), match.group(2), int(match.group(3))
            bank = {("input", "int"): c.in_int, ("input", "double"): c.in_double,
                    ("output", "int"): c.out_int, ("output", "double"): c.out_double}[(direction, kind)]
            values[name] = bank[index]
        else:
            values[name] = _ZERO[rtde.OUTPUT_TYPES[name]]
    return values


def split_program(text: str) -> tuple[str | None, str]:
    """The first complete `def|sec name(): ... end` program in `text` and the rest after it."""
    lines = text.splitlines(keepends=True)
    begin = None
    for i, line in enumerate(lines):
        if begin is None:
            if re.match(r"^(def|sec)\s+\w+\s*\(\s*\)\s*:", line):
                begin = i
        elif re.match(r"^end\s*$", line) and line.endswith("\n"):
            return "".join(lines[begin:i + 1]), "".join(lines[i + 1:])
    if begin is None:  # stray lines outside a program: nothing to keep but a trailing partial line
        keep = lines[-1] if lines and not lines[-1].endswith("\n") else ""
        return None, keep
    return None, "".join(lines[begin:])


# --- serving and process helpers -------------------------------------------------------------


def build_arm(source, limits=None):
    """The arm a simulator drives: an arm object, a RemoteArm address, or a new SimArm on a world config."""
    if isinstance(source, ArmSource):
        return source
    if isinstance(source, str) and re.match(r"^[\w.\-]+:\d+$", source):
        key = os.environ.get(AUTHKEY_ENV)
        if not key:
            raise ValueError(f"a remote arm address needs its key in the environment variable {AUTHKEY_ENV} (hex)")
        return RemoteArm(source, bytes.fromhex(key))
    config, cell_limits = _world_config(source)
    box = limits or cell_limits or WorkspaceBox(x_mm=(-1000, 1000), y_mm=(-1000, 1000), z_mm=(-1000, 1000),
                                                alpha_deg=(-720, 720))
    if not isinstance(box, WorkspaceBox):
        box = WorkspaceBox(**box)
    arm = backend_class("arm", "sim").create("arm", {"limits": box}, DriverContext(sim_config=config))
    arm.connect()
    return arm


def _world_config(source):
    """(SimWorldConfig, the cell's arm limits or None) from a config object, a dict or a cell file path."""
    if isinstance(source, SimWorldConfig):
        return source, None
    data = source
    if isinstance(source, (str, Path)):
        import yaml

        data = yaml.safe_load(Path(source).read_text())
    if not isinstance(data, dict):
        raise TypeError(f"world source {source!r}: expected a SimWorldConfig, a dict, a cell file or an arm")
    if "sim" in data:  # a whole cell file
        return SimWorldConfig(**data["sim"]), (data.get("arm") or {}).get("limits")
    return SimWorldConfig(**data), None


def serve(source, host: str = "127.0.0.1", stop: threading.Event | None = None,
          faults: UrSimFaults | dict | None = None, options: UrSimOptions | dict | None = None,
          ports: dict[str, int] | None = None, on_ready=None) -> None:
    """Serve a simulated UR on `host` until `stop` is set. `source`: world config, cell file, arm or 'HOST:PORT';
    `on_ready(simulator)` is called once every port listens."""
    opts = parse_options(options)
    if faults is not None:
        opts = opts.model_copy(update={"faults": faults if isinstance(faults, UrSimFaults) else UrSimFaults(**faults)})
    stop = stop or threading.Event()
    with UrSimulator(build_arm(source), host, opts, ports) as simulator:
        if on_ready is not None:
            on_ready(simulator)
        stop.wait()


class SimulatorProcess:
    """A UR simulator in a child process (python -m drivers.sim.servers.ur), for tests and tools.

    `source`: a cell file path, or an ArmHost (the child then drives that arm).
    """

    def __init__(self, host: str, source=None, options: dict | None = None, ready_timeout_s: float = 30.0):
        self.host = host
        self.source = source
        parse_options(options)  # a bad option is a ValueError listing the allowed ones, here, not in the child
        self.options = options or {}
        self.ready_timeout_s = ready_timeout_s
        self.process: subprocess.Popen | None = None
        self._terminated = False
        self.log_lines: list[str] = []

    def start(self) -> SimulatorProcess:
        cmd = [sys.executable, "-m", "drivers.sim.servers.ur", "--host", self.host,
               "--options", json.dumps(self.options), "--parent-pid", str(os.getpid())]
        env = dict(os.environ)
        if isinstance(self.source, ArmHost):  # serving an arm of this process
            cmd += ["--arm-address", self.source.address_text]
            env[AUTHKEY_ENV] = self.source.authkey.hex()
        elif self.source is not None:
            cmd += ["--config", str(self.source)]
        env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
        self.process = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
        self._collector = threading.Thread(target=self._collect_output, daemon=True)
        self._collector.start()
        deadline = time.monotonic() + self.ready_timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                self._drain()
                if self.process.returncode == EXIT_PORTS_TAKEN:
                    said = [line for line in self.log_lines if "cannot listen on" in line]
                    raise PortsTaken(98, (said[-1].split(" ur sim: ", 1)[-1].strip() if said else
                                          f"cannot listen on {self.host}: another UR simulator or controller is "
                                          "there"))
                raise RuntimeError(f"UR simulator exited with {self.process.returncode} before serving:\n"
                                   + "".join(self.log_lines[-30:]))
            if any(line.startswith(READY_LINE) for line in self.log_lines):  # its own word, not a port that
                return self  # accepts: that could be another simulator's on the same address
            time.sleep(0.02)
        self.stop()
        raise TimeoutError(f"UR simulator on {self.host} did not serve within {self.ready_timeout_s} s")

    def _collect_output(self) -> None:
        for line in self.process.stdout:
            self.log_lines.append(line)

    def said(self, text: str, timeout_s: float = 5.0) -> bool:
        """Whether the simulator logs a line containing `text` within `timeout_s` (its log comes through a pipe
        and a reader thread: a line can arrive after what it reports has been seen on the wire)."""
        deadline = time.monotonic() + timeout_s
        while not any(text in line for line in self.log_lines):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def _drain(self) -> None:
        """The exited child's last lines are read (its pipe is at EOF soon after the exit)."""
        self._collector.join(2.0)

    def terminate(self) -> None:
        """Send SIGTERM without waiting (stop() then collects the exit status): stops several at once."""
        if self.process is not None and self.process.poll() is None and not self._terminated:
            self._terminated = True  # a second SIGTERM could land while the child is exiting
            self.process.send_signal(signal.SIGTERM)

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, then wait; the exit status (0 for a clean stop). Kills it only if it does not exit."""
        if self.process is None:
            return 0
        if self.process.poll() is None:
            self.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout_s)
        if self.process.stdout:
            self.process.stdout.close()
        return self.process.returncode

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


class AddressClaim:
    """One cell at a time owns a simulated robot address on this machine, as one cell owns a robot.

    The UR ports are fixed, so two cells started from the same cell file (two runs, two test processes) would
    both want its address: the second waits until the first has closed its simulator (an flock on a file named
    after the address in the temporary directory), up to `wait_s`, then PortsTaken says who holds it. Within one
    process a second claim on a held address fails at once (it would wait for itself)."""

    held: set[str] = set()  # the addresses this process's simulators hold
    _guard = threading.Lock()

    def __init__(self, host: str, wait_s: float):
        self.host = host
        self.wait_s = wait_s
        self.path = Path(tempfile.gettempdir()) / f"cellctl-ur-sim-{host}.lock"
        self._fd: int | None = None
        self._held = False

    def acquire(self) -> AddressClaim:
        with self._guard:
            if self.host in self.held:
                raise PortsTaken(98, f"this process already runs a UR simulator on {self.host}: close that cell "
                                     "first, or give this one another loopback address")
            self.held.add(self.host)
            self._held = True
        try:
            self._fd = os.open(self.path, os.O_RDONLY | os.O_CREAT, 0o666)
        except OSError as exc:  # a lock file we may not open (another user's): the ports alone decide
            log.warning("ur sim: cannot open %s (%s); not waiting for other cells on %s", self.path, exc, self.host)
            return self
        deadline = time.monotonic() + self.wait_s
        waiting = False
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return self
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    self.release()
                    raise PortsTaken(98, f"another cell has run a UR simulator on {self.host} for the last "
                                         f"{self.wait_s:g} s (it holds {self.path}): close it, or give this cell "
                                         "another loopback address") from None
                if not waiting:
                    log.warning("ur sim: another cell's UR simulator holds %s; waiting up to %g s for it to close",
                                self.host, self.wait_s)
                    waiting = True
                time.sleep(0.05)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # drops the lock
            self._fd = None
        with self._guard:
            if self._held:
                self.held.discard(self.host)
                self._held = False


class WorldArmSimulator:
    """A UR simulator process that moves the SimArm of a World owned by this process.

    This is how a cell whose arm is `backend: ur` (host 127.0.0.x) runs against the same simulated
    world its simulated cameras render: the World stays here, its arm fake (the micro cell's four-axis SimArm,
    the hand-eye cell's UR5e) is served by an ArmHost
    (drivers/sim/remote.py), and the simulator process drives that arm. `world`: the cell's World
    (`cell.context.sim_world()`). Start it before connecting the UrArm. It claims its address first (AddressClaim:
    a second cell on the same address waits up to `claim_wait_s` for this one to close).
    """

    CLAIM_WAIT_S = 300.0

    def __init__(self, world, host: str, limits, options: dict | None = None, claim_wait_s: float | None = None):
        parse_options(options)  # before anything starts: a bad option is a ValueError listing the allowed ones
        self.world = world
        self.host = host
        self.limits = limits
        self.options = options
        self.claim_wait_s = self.CLAIM_WAIT_S if claim_wait_s is None else claim_wait_s
        self.arm_host = None
        self.process: SimulatorProcess | None = None
        self.claim: AddressClaim | None = None

    def start(self) -> WorldArmSimulator:
        self.claim = AddressClaim(self.host, self.claim_wait_s).acquire()
        try:
            arm = sim_device("arm", self.world, {"limits": self.limits})  # the world's own arm: 4 axes or a UR5e
            self.arm_host = ArmHost(arm)
            self.process = SimulatorProcess(self.host, self.arm_host, self.options).start()
        except BaseException:
            if self.arm_host is not None:
                self.arm_host.close()
            self.claim.release()
            raise
        return self

    def close(self) -> int:
        code = self.process.stop() if self.process is not None else 0
        if self.arm_host is not None:
            self.arm_host.close()
        if self.claim is not None:
            self.claim.release()
            self.claim = None
        return code

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()


def start_for_cell(world, spec, arm_limits: dict | None = None) -> WorldArmSimulator:
    """The simulator of a cell file's `sim.servers` entry (protocol ur), moving the cell world's arm."""
    if spec.port is not None:
        raise ValueError("sim.servers: a UR simulator listens on the fixed UR ports; pick the address with host")
    return WorldArmSimulator(world, spec.host, WorkspaceBox(**(arm_limits or ANY_TURN)), spec.options).start()


def _watch_parent(pid: int, stop: threading.Event) -> None:
    while not stop.wait(0.5):
        if os.getppid() != pid:
            log.warning("ur sim: parent process %d is gone; stopping", pid)
            stop.set()


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m drivers.sim.servers.ur",
                                     description="Simulated Universal Robots controller (dashboard, primary, "
                                                 "secondary, script port, RTDE)")
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to bind (127.0.0.x)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--config", help="cell file (with a sim: section) or a sim world YAML")
    source.add_argument("--arm-address", help=f"HOST:PORT of an ArmHost (key in ${AUTHKEY_ENV}, hex)")
    parser.add_argument("--options", default="{}", help="UrSimOptions as JSON (version, faults, ...)")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument("--parent-pid", type=int, help="exit when this process is gone (no orphaned simulators)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(message)s", stream=sys.stdout)
    stop = threading.Event()

    def on_signal(*_):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # already stopping: a repeated SIGTERM must not kill us
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    if args.parent_pid:
        threading.Thread(target=_watch_parent, args=(args.parent_pid, stop), daemon=True).start()
    src = args.arm_address or args.config or str(ROOT / "config" / "sim-microcell.yaml")
    def ready(simulator: UrSimulator) -> None:
        print(f"{READY_LINE}{simulator.host} {json.dumps(simulator.ports)}", flush=True)

    try:
        serve(src, args.host, stop, options=json.loads(args.options), on_ready=ready)
    except PortsTaken as exc:
        log.error("ur sim: %s", exc.strerror)
        return EXIT_PORTS_TAKEN
    return 0


