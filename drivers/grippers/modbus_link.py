"""One Modbus link (pymodbus synchronous client) with the error rules the gripper drivers share.

- Every exchange has a time-out (the client's) and a bounded number of attempts;
  replies are read by framing, never by sleeping.
- A Modbus exception response, a reply that does not frame (bad CRC, wrong length)
  or one with the wrong number of registers is `ModbusReplyError`, naming what came
  back and what was expected; the link stays up.
- RTU (serial line, RTU over TCP): a well-formed frame from another device id is not
  our answer, whatever it says (on an RS-485 line every device hears every frame and
  only the addressed one answers; a frame from another id is another conversation on
  the line, or a device configured with the wrong id). It is set aside (`wire_log`
  "stray") and the driver keeps waiting for its own reply until the time-out. Frames
  are cut one at a time (`RtuLineFramer`), so our reply arriving in the same read as
  a stray frame is still found.
- No reply at all within the time-out is `NoReply` (a `ConnectionLost`): on a
  serial line a device that does not answer is as good as unplugged, and a late
  reply would be taken for the answer to the next request. The link is closed. The
  message names the stray frames it ignored meanwhile, if any.
- A socket closed by the peer or a serial port that vanished is `ConnectionLost`.
- Once down, the link is never reopened behind the caller's back: pymodbus's
  clients reconnect on their own inside `execute`, so every call checks first.
- Requests are paced: at most one every `min_interval_s` (the EPick asks for 5 ms).

Framings: RTU on a serial port, RTU over a TCP socket (a UR wrist forwarding the
RS-485 bytes), or Modbus TCP (MBAP header).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer.rtu import FramerRTU

from drivers.interfaces import ConnectionLost, DeviceError

EXCEPTION_CODES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


class ModbusReplyError(DeviceError):
    """The device answered, but with a Modbus exception or with a reply that makes no sense."""


class NoReply(ConnectionLost):
    """No reply within the time-out: the link is treated as lost (reconnect before going on)."""


@dataclass(frozen=True)
class LinkConfig:
    """Where the device is and how to talk to it."""

    kind: str  # "serial" (RTU on a serial port), "rtu-over-tcp", "tcp" (Modbus TCP)
    device_id: int
    timeout_s: float
    retries: int = 0
    min_interval_s: float = 0.0
    serial_port: str = ""
    baudrate: int = 115200
    host: str = ""
    port: int = 0

    @property
    def where(self) -> str:
        if self.kind == "serial":
            return f"serial port {self.serial_port} ({self.baudrate} 8N1), device id {self.device_id}"
        framing = "RTU over TCP" if self.kind == "rtu-over-tcp" else "Modbus TCP"
        return f"{self.host}:{self.port} ({framing}), device id {self.device_id}"


def hex_bytes(data: bytes) -> str:
    return data.hex(" ").upper() if data else "(nothing)"


class RtuLineFramer(FramerRTU):
    """pymodbus's RTU framer, reading a shared line one frame at a time.

    pymodbus 3.16's `FramerRTU.decode` counts every byte it was handed as used once one
    frame in them checks out, so a second frame that arrived in the same read (another
    device's reply, then ours; or two requests back to back) is thrown away. Here only
    the frame itself (and any bytes skipped before it) is used; the rest waits for the
    next call. A frame whose CRC fails still takes the whole buffer with it, as in
    pymodbus: without the line's timing nothing says where the next frame starts.
    The simulators' servers use it too (drivers/sim/servers/modbus_common.py).
    """

    def next_frame(self, data: bytes) -> tuple[int, int, bool] | None:
        """(start, end, CRC good) of the first frame in `data`; None while none is complete."""
        for start in range(len(data)):
            if len(data) - start < self.MIN_SIZE:
                return None
            pdu_class = self.decoder.lookupPduClass(data[start:])
            if pdu_class is None:
                continue  # not a function code this side knows: not the start of a frame
            size = pdu_class.calculateRtuFrameSize(data[start:])
            if not size or len(data) < start + size:
                return None
            end = start + size
            return start, end, self.check_CRC(data[start:end - 2], int.from_bytes(data[end - 2:end], "big"))
        return None

    def decode(self, data: bytes) -> tuple[int, int, int, bytes]:
        found = self.next_frame(data)
        if found is None:
            return 0, 0, 0, self.EMPTY
        start, end, crc_ok = found
        if not crc_ok:
            return len(data), 0, 0, self.EMPTY
        return end, data[start], 0, data[start + 1:end - 2]


class _AddressedRtuFramer(RtuLineFramer):
    """The driver's side of an RTU line: a frame from another device id is set aside (`strays`), never
    taken for the reply; bytes that do not frame are kept (`unframed()`) for the error message."""

    def __init__(self, decoder):
        super().__init__(decoder)
        self.reset()

    def reset(self) -> None:
        self.strays: list[bytes] = []
        self.garbage = b""  # bytes consumed without framing (a bad CRC, bytes skipped before a frame)
        self.pending = b""  # bytes not consumed yet (an incomplete frame)

    def unframed(self) -> bytes:
        return self.garbage + self.pending

    def handleFrame(self, data: bytes, exp_devid: int, exp_tid: int):
        used = 0
        while True:
            rest = data[used:]
            found = self.next_frame(rest) if rest else None
            if found is None:
                self.pending = rest
                return used, None
            start, end, crc_ok = found
            if not crc_ok:
                self.garbage += rest
                self.pending = b""
                return len(data), None
            self.garbage += rest[:start]
            frame = rest[start:end]
            used += end
            if exp_devid and frame[0] != exp_devid:
                self.strays.append(frame)  # not ours: keep waiting for our device's reply
                continue
            self.pending = data[used:]
            pdu = self.decoder.decode(frame[1:-2])
            if pdu is None:
                raise ModbusIOException("Unable to decode response", dev_id=frame[0])
            pdu.dev_id = frame[0]
            pdu.transaction_id = 0
            return used, pdu


class _FramedSerialClient(ModbusSerialClient):
    """pymodbus's serial client polls the port every millisecond until the byte count stops
    changing (about 2 ms per reply at best). Here a read returns as soon as bytes are there:
    block for the first byte (up to the time-out), then take what has arrived; pymodbus's
    RTU framer asks again until the frame is complete."""

    def recv(self, size: int | None) -> bytes:
        if size is not None or self.socket is None:
            return super().recv(size)
        try:
            first = self.socket.read(1)  # the port's read time-out is the link time-out
            if not first:
                return b""
            return first + self.socket.read(self.socket.in_waiting)
        except OSError:
            self.close()
            raise ConnectionException(str(self)) from None


class ModbusLink:
    """Synchronous request/reply over one pymodbus client. Thread-safe (one exchange at a time)."""

    def __init__(self, name: str, config: LinkConfig):
        self.name = name
        self.config = config
        self.client: ModbusSerialClient | ModbusTcpClient | None = None
        self.wire_log: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=64)  # ("tx"|"rx"|"stray"|"stale", bytes)
        self._received = b""
        self._framer: _AddressedRtuFramer | None = None  # RTU kinds: the client's framer
        self._last_request = 0.0
        self._lock = threading.Lock()

    # -- lifecycle ------------------------------------------------------------
    def open(self) -> None:
        self.close()
        cfg = self.config
        common = {"timeout": cfg.timeout_s, "retries": cfg.retries, "trace_packet": self._trace}
        if cfg.kind == "serial":
            client = _FramedSerialClient(cfg.serial_port, framer=FramerType.RTU, baudrate=cfg.baudrate,
                                        bytesize=8, parity="N", stopbits=1, **common)
        elif cfg.kind in ("rtu-over-tcp", "tcp"):
            framer = FramerType.RTU if cfg.kind == "rtu-over-tcp" else FramerType.SOCKET
            client = ModbusTcpClient(cfg.host, port=cfg.port, framer=framer, **common)
        else:
            raise ValueError(f"link kind must be 'serial', 'rtu-over-tcp' or 'tcp', got {cfg.kind!r}")
        client.set_max_no_responses(1 << 30)  # we decide when the link is lost, not pymodbus
        self._framer = None
        if cfg.kind != "tcp":  # RTU: frames from other device ids are set aside, frames cut one at a time
            self._framer = _AddressedRtuFramer(client.framer.decoder)
            client.framer = client.transaction.framer = self._framer
        if not client.connect():
            client.close()
            what = "could not open" if cfg.kind == "serial" else "could not connect to"
            raise ConnectionLost(f"{self.name}: {what} {cfg.where}; check the cable, the address and that "
                                 "nothing else holds the port")
        self.client = client
        self._last_request = 0.0

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    @property
    def is_open(self) -> bool:
        return self.client is not None and self.client.connected

    # -- exchanges ------------------------------------------------------------
    def read(self, address: int, count: int, function: int = 3) -> list[int]:
        """Read `count` registers with FC03 (holding) or FC04 (input)."""
        what = f"FC{function:02d} read of {count} registers at 0x{address:04X}"

        def call(client):
            if function == 4:
                return client.read_input_registers(address, count=count, device_id=self.config.device_id)
            return client.read_holding_registers(address, count=count, device_id=self.config.device_id)

        response = self._exchange(what, call)
        registers = list(getattr(response, "registers", []))
        if len(registers) != count:
            raise ModbusReplyError(f"{self.name}: reply to the {what} carried {len(registers)} registers, "
                                   f"expected {count} (reply {hex_bytes(self._received)})")
        return registers

    def write(self, address: int, values: list[int]) -> None:
        """Write registers with FC16 and check the echo of address and count."""
        what = f"FC16 write of {len(values)} registers at 0x{address:04X}"
        response = self._exchange(
            what, lambda client: client.write_registers(address, list(values), device_id=self.config.device_id))
        echoed = (getattr(response, "address", None), getattr(response, "count", None))
        if echoed != (address, len(values)):
            raise ModbusReplyError(f"{self.name}: reply to the {what} echoed address/count {echoed}, "
                                   f"expected ({address}, {len(values)})")

    def _exchange(self, what: str, call):
        with self._lock:
            client = self.client
            if client is None or not client.connected:
                self.close()
                raise ConnectionLost(f"{self.name}: the link to {self.config.where} is down; reconnect before going on")
            self._pace()
            self._drain(client, what)
            self._received = b""
            if self._framer is not None:
                self._framer.reset()
            try:
                response = call(client)
            except ConnectionException as exc:
                self.close()
                raise ConnectionLost(f"{self.name}: the link to {self.config.where} dropped during the {what} "
                                     f"({exc}); reconnect before going on") from None
            except ModbusIOException as exc:
                return self._no_frame(what, exc)
            except (ModbusException, OSError) as exc:
                self.close()
                raise ConnectionLost(f"{self.name}: {what} on {self.config.where} failed: {exc}; "
                                     "reconnect before going on") from None
            finally:
                self._log_strays()
                self._last_request = time.monotonic()
            if response.isError():
                code = getattr(response, "exception_code", None)
                meaning = EXCEPTION_CODES.get(code, "unknown exception code")
                raise ModbusReplyError(f"{self.name}: device {self.config.device_id} answered the {what} with "
                                       f"Modbus exception {code} ({meaning})")
            return response

    def _no_frame(self, what: str, exc: Exception):
        attempts = self.config.retries + 1
        received = self._received if self._framer is None else self._framer.unframed()
        strays = [] if self._framer is None else self._framer.strays
        ignored = ""
        if strays:
            shown = ", ".join(f"{hex_bytes(frame)} (device {frame[0]})" for frame in strays[:3])
            more = f" and {len(strays) - 3} more" if len(strays) > 3 else ""
            ignored = (f"; ignored {len(strays)} frame{'s' if len(strays) > 1 else ''} from other device ids: "
                       f"{shown}{more} (on an RTU line only the addressed device answers)")
        if received:
            raise ModbusReplyError(
                f"{self.name}: malformed reply to the {what} from {self.config.where}: got {hex_bytes(received)}, "
                f"which is not a valid {'RTU frame (device id, function, data, CRC)' if self.config.kind != 'tcp' else 'Modbus TCP reply (MBAP header + PDU)'} "
                f"answering it ({exc}){ignored}")
        self.close()
        raise NoReply(f"{self.name}: no reply to the {what} from {self.config.where} within {self.config.timeout_s} s "
                      f"({attempts} attempt{'s' if attempts > 1 else ''}){ignored}; check the cable, the power and the "
                      "device id, then reconnect")

    def _log_strays(self) -> None:
        if self._framer is not None:
            for frame in self._framer.strays:
                self.wire_log.append(("stray", frame))

    def _pace(self) -> None:
        """At most one request per min_interval_s: the device drops commands that come faster."""
        wait = self._last_request + self.config.min_interval_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)

    def _drain(self, client, what: str) -> None:
        """Throw away bytes that arrived after an earlier exchange ended (a late reply), so they
        are never taken for the answer to this request. pymodbus does this itself on serial ports."""
        sock = getattr(client, "socket", None)
        if self.config.kind == "serial" or sock is None:
            return
        sock.setblocking(False)
        try:
            while True:
                stale = sock.recv(4096)
                if not stale:
                    self.close()
                    raise ConnectionLost(f"{self.name}: {self.config.where} closed the connection before the "
                                         f"{what}; reconnect before going on")
                self.wire_log.append(("stale", stale))
        except (BlockingIOError, InterruptedError):
            pass
        except OSError as exc:
            self.close()
            raise ConnectionLost(f"{self.name}: the link to {self.config.where} failed: {exc}; reconnect") from None

    def _trace(self, sending: bool, data: bytes) -> bytes:
        if sending:
            self.wire_log.append(("tx", bytes(data)))
        else:
            self._received = bytes(data)  # pymodbus passes everything buffered so far for this reply
            self.wire_log.append(("rx", bytes(data)))
        return data
