"""What the Modbus protocol simulators share: a pymodbus server in a thread, with fault knobs.

The register model is pymodbus 3.16's simulator datastore (`SimDevice` / `SimData`,
real protocol addresses, an async action callback that sees every access before
it lands); the device behaviour lives in that callback. The server runs its own
asyncio loop in a daemon thread so tests and `cellctl sim` can use it from plain
synchronous code: `start()`, then `close()` (or a `with` block).

Framings: "tcp" (Modbus TCP, MBAP header), "rtu-over-tcp" (RTU frames on a TCP
socket, as a UR wrist forwards the RS-485 bytes) and "serial" (RTU on a serial
port, e.g. one end of a `socat` pty pair).

Addressing on the RTU framings, as the Modbus serial-line specification has it (every
device on the line hears every frame): a request for another device id gets no reply
at all -- not an exception, nothing -- and is not executed; device id 0 is a
broadcast: a write (FC 5, 6, 15, 16, 22) is executed and never answered, anything
else addressed to 0 is ignored. Frames are cut one at a time
(`drivers.grippers.modbus_link.RtuLineFramer`), so a request that arrives in the same
read as another device's traffic is still seen. On "tcp" a unit id this server does not
have is answered with exception 4 (server device failure), as pymodbus's simulator does.

Function codes: `functions` (if given) is the set the device implements; any other
is answered with exception 1 (illegal function) before its address or data are looked
at, the order of checks in the Modbus application protocol.

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
import collections
import threading
from dataclasses import dataclass, fields

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import SimDevice

from drivers.grippers.modbus_link import RtuLineFramer
from drivers.sim.servers.knobs import check_link_knobs

KINDS = ("tcp", "rtu-over-tcp", "serial")
BROADCAST_ID = 0
BROADCAST_WRITES = frozenset({5, 6, 15, 16, 22})  # what a broadcast may carry: writes (nobody answers a read)


class SimulatorStartError(OSError):
    """The simulator could not listen (a TCP port taken, a serial device missing): an OSError, as a failed
    bind is, so that callers handle it as the address problem it is."""


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
        faults = cls(**options)
        check_link_knobs(faults)
        return faults


class _FaultyHandler(ServerRequestHandler):
    """pymodbus's per-connection request handler, with addressing, the function-code check and the fault
    knobs in front of it. Every complete frame of a read is handled, in order (pymodbus takes one per read
    and leaves the rest until more bytes come)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._requests: collections.deque = collections.deque()
        self._one_at_a_time = asyncio.Lock()

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        used = 0
        while used < len(data):
            n = super().callback_data(data[used:], addr)  # frames one request, schedules handle_request
            if self.last_pdu:
                self._requests.append((self.last_pdu, self.last_addr))
            if not n:
                break
            used += n
        return used

    async def handle_request(self):
        async with self._one_at_a_time:  # requests are answered in the order they came, one at a time
            if not self._requests:
                return
            request, addr = self._requests.popleft()
            await self._handle(request, addr)

    async def _handle(self, request, addr):
        """One request: pymodbus's handle_request, on this request (not on `last_pdu`, which the next read
        may have replaced meanwhile), with the device's addressing, functions and faults first."""
        sim: SimModbusServer = self.server.sim
        rtu = sim.kind != "tcp"
        if rtu and request.dev_id not in (sim.device.id, BROADCAST_ID):
            return  # another device's request: this one stays silent and does nothing
        limit = sim.faults.drop_after_messages
        if limit is not None and sim.messages_on_connection >= limit:
            if sim.kind != "serial":
                self.close()  # the TCP connection drops
            return  # a serial device just stops answering
        implemented = sim.functions is None or request.function_code in sim.functions
        if rtu and request.dev_id == BROADCAST_ID:
            if implemented and request.function_code in BROADCAST_WRITES:
                sim.broadcasts += 1
                try:  # executed as if addressed to this device; its outcome is never sent
                    await request.datastore_update(self.server.context, sim.device.id)
                except Exception:  # noqa: BLE001 -- a broadcast that fails has nobody to tell
                    pass
            return
        if sim.faults.reply_delay_s > 0:
            await asyncio.sleep(sim.faults.reply_delay_s)
        if not implemented:
            self.server_send(ExceptionResponse(request.function_code, ExcCodes.ILLEGAL_FUNCTION,
                                               device_id=request.dev_id, transaction=request.transaction_id), addr)
            return
        try:  # the datastore, and the device's action callback in front of it
            response = await request.datastore_update(self.server.context, request.dev_id)
        except Exception:  # noqa: BLE001 -- as pymodbus: the device failed (e.g. a Modbus TCP unit it does not have)
            response = ExceptionResponse(request.function_code, ExcCodes.DEVICE_FAILURE)
        response.transaction_id = request.transaction_id
        response.dev_id = request.dev_id
        self.server_send(response, addr)

    def server_send(self, pdu, addr):
        sim: SimModbusServer = self.server.sim
        if not pdu:
            return
        if sim.kind != "tcp" and pdu.dev_id != sim.device.id:
            return  # never answer for another device id (nor a broadcast), whichever path built the reply
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
                 serial_port: str | None = None, baudrate: int = 115200, faults: ModbusFaults | None = None,
                 functions: frozenset[int] | None = None):
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
        self.functions = functions  # function codes the device implements (None: all pymodbus serves)
        self.messages_on_connection = 0  # replies sent on the current connection
        self.messages_total = 0
        self.broadcasts = 0  # broadcast writes executed (RTU, device id 0)
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
            raise SimulatorStartError(f"Modbus simulator ({self.kind}) could not start on {self.where}: "
                                      f"{self._error}") from self._error
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
        if self.kind != "tcp":
            server.framer = RtuLineFramer  # one frame at a time: a frame that follows another in one read is kept
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
