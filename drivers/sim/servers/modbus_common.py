"""What the Modbus protocol simulators share: a pymodbus server in a thread, with fault knobs.

The register model is pymodbus 3.16's simulator datastore (`SimDevice` / `SimData`,
real protocol addresses, an async action callback that sees every access before
it lands); the device behaviour lives in that callback. The server runs its own
asyncio loop in a daemon thread so tests and `cellctl sim` can use it from plain
synchronous code: `start()`, then `close()` (or a `with` block).

Framings: "tcp" (Modbus TCP, MBAP header), "rtu-over-tcp" (RTU frames on a TCP
socket, as a UR wrist forwards the RS-485 bytes) and "serial" (RTU on a serial
port, e.g. one end of a `socat` pty pair).

Fault knobs (`ModbusFaults`, changeable while serving):
- `drop_after_messages`: once N replies were sent on a connection, the next request
  closes the TCP connection instead of being answered; on a serial line (nothing
  to close) the device falls silent, as an unplugged one does;
- `reply_delay_s`: every reply waits this long;
- `malformed_replies`: replies are corrupted (RTU: wrong CRC; TCP: the PDU is cut short
  of the length its MBAP header announces).
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, fields

from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import SimDevice

KINDS = ("tcp", "rtu-over-tcp", "serial")


@dataclass
class ModbusFaults:
    drop_after_messages: int | None = None
    reply_delay_s: float = 0.0
    malformed_replies: bool = False

    @classmethod
    def from_options(cls, options: dict, extra_allowed: tuple[str, ...] = ()) -> ModbusFaults:
        known = {f.name for f in fields(cls)}
        unknown = set(options) - known
        if unknown:
            raise ValueError(f"unknown Modbus simulator option(s) {sorted(unknown)}; "
                             f"allowed: {sorted(known | set(extra_allowed))}")
        return cls(**options)


class _FaultyHandler(ServerRequestHandler):
    """pymodbus's per-connection request handler, with the fault knobs in front of it."""

    async def handle_request(self):
        sim: SimModbusServer = self.server.sim
        if not self.last_pdu:
            return
        limit = sim.faults.drop_after_messages
        if limit is not None and sim.messages_on_connection >= limit:
            if sim.kind != "serial":
                self.close()  # the TCP connection drops
            return  # a serial device just stops answering
        if sim.faults.reply_delay_s > 0:
            await asyncio.sleep(sim.faults.reply_delay_s)
        await super().handle_request()

    def server_send(self, pdu, addr):
        sim: SimModbusServer = self.server.sim
        if not pdu:
            return
        sim.messages_on_connection += 1
        sim.messages_total += 1
        if not sim.faults.malformed_replies:
            super().server_send(pdu, addr)
            return
        frame = bytearray(self.framer.buildFrame(pdu))
        if sim.kind == "tcp":
            frame = frame[:-1]  # shorter than the MBAP length field says
        else:
            frame[-1] ^= 0xFF  # CRC no longer matches
        self.send(bytes(frame), addr=addr)


class _TcpServer(ModbusTcpServer):
    def callback_new_connection(self):
        self.sim.messages_on_connection = 0
        self.sim.connections += 1
        return _FaultyHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class _SerialServer(ModbusSerialServer):
    def callback_new_connection(self):
        self.sim.messages_on_connection = 0
        self.sim.connections += 1
        return _FaultyHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class SimModbusServer:
    """A pymodbus server for one `SimDevice`, served from a background thread.

    `kind` is one of "tcp", "rtu-over-tcp", "serial". For TCP kinds, port 0 picks a
    free ephemeral port (see `port` after `start()`); for "serial", `serial_port` is
    the device path (e.g. one end of a socat pty pair).
    """

    def __init__(self, device: SimDevice, kind: str, host: str = "127.0.0.1", port: int = 0,
                 serial_port: str | None = None, baudrate: int = 115200, faults: ModbusFaults | None = None):
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {', '.join(KINDS)}; got {kind!r}")
        if kind == "serial" and not serial_port:
            raise ValueError("kind 'serial' needs serial_port (a device path such as /dev/ttyUSB0 or a pty)")
        self.device = device
        self.kind = kind
        self.host = host
        self.port = port
        self.serial_port = serial_port
        self.baudrate = baudrate
        self.faults = faults or ModbusFaults()
        self.messages_on_connection = 0  # replies sent on the current connection
        self.messages_total = 0
        self.connections = 0
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    # -- lifecycle ----------------------------------------------------------------
    def start(self):
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"modbus-sim-{self.kind}")
        self._thread.start()
        if not self._started.wait(10.0):
            raise RuntimeError(f"Modbus simulator ({self.kind}) did not start within 10 s")
        if self._error is not None:
            self._thread.join(5.0)
            raise RuntimeError(f"Modbus simulator ({self.kind}) could not start: {self._error}") from self._error
        return self

    def close(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:  # the loop already ended
                pass
        if self._thread is not None:
            self._thread.join(10.0)
            self._thread = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def where(self) -> str:
        return self.serial_port if self.kind == "serial" else f"{self.host}:{self.port}"

    # -- the server thread ----------------------------------------------------------
    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 -- reported to start(); never kills the test process
            self._error = self._error or exc
            self._started.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if self.kind == "serial":
            server = _SerialServer(self.device, framer=FramerType.RTU, port=self.serial_port,
                                   baudrate=self.baudrate, timeout=1.0, reconnect_delay=0.1)
        else:
            framer = FramerType.RTU if self.kind == "rtu-over-tcp" else FramerType.SOCKET
            server = _TcpServer(self.device, framer=framer, address=(self.host, self.port))
        server.sim = self
        try:
            await server.serve_forever(background=True)
        except Exception as exc:  # noqa: BLE001 -- a port in use, a missing device: reported to start()
            self._error = exc
            self._started.set()
            return
        if self.kind != "serial":
            self.port = server.transport.sockets[0].getsockname()[1]
        self._started.set()
        try:
            await self._stop.wait()
        finally:
            await server.shutdown()
