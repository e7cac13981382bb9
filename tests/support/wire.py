"""The other end of a wire, played from a script: pymodbus's `expected_protocol` way of testing a driver's bytes.

A `WirePeer` expects exact request bytes and answers each with its scripted reply: bytes, a list of chunks sent
`chunk_gap_s` apart (a reply split across reads), or None (it stays silent). It records what it received; each
request that differs from the script is in `errors` (unanswered), for the test to check (`finish()` asserts none).

Requests are framed as the protocol frames them: up to a `terminator` (open_abb's "#"), else by the expected
request's length (Modbus RTU/TCP, whose lengths the script fixes). On TCP (`port` once built) or on the simulator
end of a pty pair (`serial_port`)."""

from __future__ import annotations

import socket
import threading
import time

Reply = bytes | list[bytes] | None


class WirePeer:
    def __init__(self, script: list[tuple[bytes, Reply]], *, terminator: bytes | None = None,
                 serial_port: str | None = None, chunk_gap_s: float = 0.02, timeout_s: float = 5.0):
        self.script, self.terminator, self.chunk_gap_s, self.timeout_s = list(script), terminator, chunk_gap_s, timeout_s
        self.received: list[bytes] = []
        self.errors: list[str] = []
        self._listener = self._serial = None
        if serial_port is None:
            self._listener = socket.create_server(("127.0.0.1", 0))
            self._listener.settimeout(timeout_s)
            self.port = self._listener.getsockname()[1]
        else:
            import serial

            self._serial = serial.Serial(serial_port, 115200, timeout=timeout_s)
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="wire-peer", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        if self._serial is not None:
            self._play(self._serial.read, self._serial.write)
            return
        try:
            conn, _ = self._listener.accept()
        except OSError as exc:
            self.errors.append(f"no client: {exc}")
            return
        with conn:
            conn.settimeout(self.timeout_s)
            self._play(conn.recv, conn.sendall)

    def _play(self, recv, send) -> None:
        buffer = b""
        script = list(self.script)
        while script or self.terminator is not None:
            expected, reply = script.pop(0) if script else (None, None)
            request, buffer = self._next_request(recv, buffer, expected)
            if request is None:
                return  # the client went away
            self.received.append(request)
            if expected is None:
                continue  # beyond the script: recorded, unanswered
            if request != expected:
                self.errors.append(f"expected {_shown(expected)}, got {_shown(request)}")
                if self.terminator is None:
                    return  # framed by the script's lengths: nothing after a wrong request can be framed
                continue
            for i, chunk in enumerate([] if reply is None else reply if isinstance(reply, list) else [reply]):
                if i:
                    time.sleep(self.chunk_gap_s)  # let a split reply arrive in pieces
                send(chunk)
        self._done.wait(self.timeout_s)  # keep the link open until the test is done with it

    def _next_request(self, recv, buffer: bytes, expected: bytes | None) -> tuple[bytes | None, bytes]:
        while True:
            if self.terminator is not None and self.terminator in buffer:
                request, _, rest = buffer.partition(self.terminator)
                return request + self.terminator, rest
            if self.terminator is None and len(buffer) >= len(expected):
                return buffer[:len(expected)], buffer[len(expected):]
            try:
                chunk = recv(1024 if self.terminator is not None else len(expected) - len(buffer))
            except OSError:
                chunk = b""
            if not chunk:
                return (buffer or None) if self.terminator is None else None, b""
            buffer += chunk

    def close(self) -> None:
        self._done.set()
        self._thread.join(self.timeout_s)
        if self._listener is not None:
            self._listener.close()
        if self._serial is not None:
            self._serial.close()

    def finish(self) -> None:
        """Close, and fail the test if a request differed from the script."""
        self.close()
        assert not self.errors, self.errors


def _shown(data: bytes) -> str:
    return repr(data) if data.isascii() and data.decode(errors="replace").isprintable() else data.hex(" ")
