"""Serve an object's calls to another process on loopback: `ObjectHost` (server) and `ObjectClient`.

Used twice: drivers/sim/remote.py shares a simulated arm between processes, and
drivers/arms/ur/child.py runs the ur_rtde driver in a child process of its own.

Requests are pickled `(name, args)` tuples over `multiprocessing.connection` with an HMAC
authkey, on loopback only; replies are `("ok", value)` or `("error", kind, message)`.
Each connection is served on its own thread and the client opens one connection per
calling thread, so a call from a second thread (a stop) never queues behind a long one
(a move). Every request has a time-out. Typed driver errors (drivers/interfaces.py) and
ValueError come back as the same types; anything else as DeviceError. A host that went
away (EOF, reset, time-out) is ConnectionLost, built by `ObjectClient.lost` (overridable).
"""

from __future__ import annotations

import logging
import secrets
import socket
import threading
import time
import weakref
from multiprocessing import AuthenticationError
from multiprocessing.connection import Client, Connection, Listener

from drivers import interfaces
from drivers.interfaces import ConnectionLost, DeviceError

log = logging.getLogger(__name__)


class ObjectHost:
    """Serves `calls` (method names) of `target` until `close()`; `address` and `authkey` for the clients."""

    typed_errors: tuple[type[Exception], ...] = (DeviceError, ValueError)  # sent back with their type

    def __init__(self, target, calls, host: str = "127.0.0.1", port: int = 0, authkey: bytes | None = None,
                 name: str = "host"):
        if not host.startswith("127.") and host != "localhost":
            raise ValueError(f"{name} host {host!r}: only loopback addresses (127.x.x.x) are allowed")
        self.target = target
        self.calls = frozenset(calls)
        self.name = name
        self.authkey = authkey or secrets.token_bytes(16)
        self._listener = Listener((host, port), authkey=self.authkey)
        self.address: tuple[str, int] = self._listener.address
        self._closed = threading.Event()
        self._connections: set[Connection] = set()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._accept, name=name, daemon=True)
        self._thread.start()

    @property
    def address_text(self) -> str:
        return f"{self.address[0]}:{self.address[1]}"

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                conn = self._listener.accept()
            except Exception as exc:  # noqa: BLE001 - closed listener, failed authentication, aborted handshake
                if self._closed.is_set():
                    return
                log.warning("%s: refused a connection: %s", self.name, exc)
                continue
            with self._lock:
                self._connections.add(conn)
            threading.Thread(target=self._serve, args=(conn,), name=f"{self.name}-conn", daemon=True).start()

    def _serve(self, conn: Connection) -> None:
        try:
            while not self._closed.is_set():
                try:
                    request = conn.recv()
                except (EOFError, OSError, TypeError):  # TypeError: the handle was closed under us
                    return
                conn.send(self.call(request))
        except (OSError, EOFError):
            return
        finally:
            with self._lock:
                self._connections.discard(conn)
            conn.close()

    def call(self, request):
        """One request -> its reply tuple (never raises)."""
        try:
            name, args = request
        except (TypeError, ValueError):
            return ("error", "DeviceError", f"malformed request {request!r}: expected (name, args)")
        if name not in self.calls:
            return ("error", "DeviceError", f"unknown call {name!r}; allowed: {', '.join(sorted(self.calls))}")
        try:
            return ("ok", self.dispatch(name, args))
        except self.typed_errors as exc:
            return ("error", type(exc).__name__, str(exc))
        except Exception as exc:  # anything else is the target's bug: report it, keep serving
            log.exception("%s: %s failed", self.name, name)
            return ("error", "DeviceError", f"{name} failed in the serving process: {type(exc).__name__}: {exc}")

    def dispatch(self, name: str, args: tuple):
        return getattr(self.target, name)(*args)

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        try:  # wake the thread blocked in accept() (closing the listener alone does not)
            socket.create_connection(self.address, timeout=1.0).close()
        except OSError:
            pass
        self._thread.join(timeout=2.0)
        self._listener.close()
        with self._lock:
            for conn in list(self._connections):  # EOF for the serving threads, which then close their end
                try:
                    with socket.fromfd(conn.fileno(), socket.AF_INET, socket.SOCK_STREAM) as sock:
                        sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass


class ObjectClient:
    """Client side of ObjectHost. Thread-safe: one connection per calling thread.

    `alive`: optional callable, polled while a reply is awaited; False ends the wait at once (a dead child)."""

    def __init__(self, address, authkey: bytes, timeout_s: float = 5.0, what: str = "host", alive=None):
        self.address = parse_address(address)
        self.authkey = authkey
        self.timeout_s = timeout_s
        self.what = what
        self.alive = alive
        self.on_reply = None  # optional callable, given every reply tuple (e.g. to mirror extra fields)
        self._local = threading.local()
        self._all: weakref.WeakSet[Connection] = weakref.WeakSet()  # a finished thread's connection closes
        self._lock = threading.Lock()

    def _conn(self) -> Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            try:
                conn = Client(self.address, authkey=self.authkey)
            except AuthenticationError as exc:
                raise DeviceError(f"{self.what} at {self.address[0]}:{self.address[1]} refused the key: {exc}; "
                                  f"pass the host's authkey") from exc
            except (OSError, EOFError) as exc:
                raise self.lost("connect", exc, unreachable=True) from exc
            self._local.conn = conn
            with self._lock:
                self._all.add(conn)
        return conn

    def request(self, name: str, *args, timeout_s: float | None = None):
        conn = self._conn()
        try:
            conn.send((name, args))
            deadline = time.monotonic() + (timeout_s or self.timeout_s)
            while not conn.poll(0.05 if self.alive else max(0.0, deadline - time.monotonic())):
                if self.alive is not None and not self.alive():
                    raise EOFError("the serving process exited")
                if time.monotonic() >= deadline:
                    raise TimeoutError
            reply = conn.recv()
        except (OSError, EOFError, TimeoutError) as exc:
            self._local.conn = None
            conn.close()
            raise self.lost(name, exc) from exc
        if self.on_reply is not None:
            self.on_reply(reply)
        if reply[0] == "ok":
            return reply[1]
        _, kind, message = reply[:3]
        error = ValueError if kind == "ValueError" else getattr(interfaces, kind, DeviceError)
        if not (isinstance(error, type) and issubclass(error, (DeviceError, ValueError))):
            error = DeviceError
        raise error(message)

    def lost(self, name: str, exc: BaseException, unreachable: bool = False) -> ConnectionLost:
        where = f"{self.what} at {self.address[0]}:{self.address[1]}"
        if unreachable:
            return ConnectionLost(f"{where} is unreachable: {exc}")
        return ConnectionLost(f"{where}: no reply to {name} ({type(exc).__name__})")

    def close(self) -> None:
        with self._lock:
            for conn in list(self._all):
                conn.close()
            self._all.clear()
        self._local = threading.local()


def parse_address(address) -> tuple[str, int]:
    if isinstance(address, str):
        host, sep, port = address.rpartition(":")
        if not sep or not port.isdigit():
            raise ValueError(f"address {address!r}: expected HOST:PORT, e.g. 127.0.0.1:40123")
        return host, int(port)
    host, port = address
    return str(host), int(port)
