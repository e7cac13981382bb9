"""Share one simulated arm between processes: the world's owner serves it, a protocol simulator drives it.

Why: a protocol simulator for a client library that holds the GIL (ur_rtde's
constructors do) must run in its own process, yet the cameras that watch the arm live
in the process that owns the World. So the owner exposes its SimArm on loopback and
the simulator process moves that very arm:

    # the process that owns the World (a test, or `cellctl` running a sim cell)
    host = ArmHost(sim_arm)                         # listens on 127.0.0.1, random port and key
    start the simulator with host.address and host.authkey (e.g. `python -m drivers.sim.servers.ur
    --arm-address 127.0.0.1:PORT` with the key in the environment variable CELLCTL_SIM_AUTHKEY)
    ...
    host.close()

    # the simulator process
    arm = RemoteArm(address, authkey)               # same calls as the SimArm: move_linear, pose, stop
    arm.move_linear(Pose(...))

Requests are pickled tuples over `multiprocessing.connection` with an HMAC authkey,
on loopback only. Every call has a time-out; a host that went away is ConnectionLost.
Typed driver errors raised by the arm (MotionStopped, ProtectiveStop, MotionRejected,
ConnectionLost …) come back as the same types.

The GIL trap: the host answers from a thread of the owner's process, which needs that
process's GIL. Call the remote arm only when the owner is known to release the GIL
(inside ur_rtde's moveL/moveJ, which release it, or a plain Python wait) — never while
it may be inside a ur_rtde constructor. The UR simulator therefore reads the pose once
at start and then only after the moves it executes.
"""

from __future__ import annotations

import logging
import secrets
import socket
import threading
from multiprocessing import AuthenticationError
from multiprocessing.connection import Client, Connection, Listener

from .. import interfaces
from ..interfaces import ConnectionLost, DeviceError, JointState, Pose

log = logging.getLogger(__name__)

_CALLS = {"move_linear", "move_joints", "pose", "joints", "stop", "wall_seconds"}


class ArmHost:
    """Serves an arm (normally the World's SimArm) to other processes until `close()`."""

    def __init__(self, arm, host: str = "127.0.0.1", port: int = 0, authkey: bytes | None = None):
        if not host.startswith("127.") and host != "localhost":
            raise ValueError(f"ArmHost host {host!r}: only loopback addresses (127.x.x.x) are allowed")
        self.arm = arm
        self.authkey = authkey or secrets.token_bytes(16)
        self._listener = Listener((host, port), authkey=self.authkey)
        self.address: tuple[str, int] = self._listener.address
        self._closed = threading.Event()
        self._connections: set[Connection] = set()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._accept, name="arm-host", daemon=True)
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
                log.warning("arm host: refused a connection: %s", exc)
                continue
            with self._lock:
                self._connections.add(conn)
            threading.Thread(target=self._serve, args=(conn,), name="arm-host-conn", daemon=True).start()

    def _serve(self, conn: Connection) -> None:
        try:
            while not self._closed.is_set():
                try:
                    request = conn.recv()
                except (EOFError, OSError, TypeError):  # TypeError: the handle was closed under us
                    return
                conn.send(self._call(request))
        except (OSError, EOFError):
            return
        finally:
            with self._lock:
                self._connections.discard(conn)
            conn.close()

    def _call(self, request):
        try:
            name, args = request
        except (TypeError, ValueError):
            return ("error", "DeviceError", f"malformed request {request!r}: expected (name, args)")
        if name not in _CALLS:
            return ("error", "DeviceError", f"unknown call {name!r}; allowed: {', '.join(sorted(_CALLS))}")
        try:
            if name == "wall_seconds":
                return ("ok", self.wall_seconds(*args))
            return ("ok", getattr(self.arm, name)(*args))
        except DeviceError as exc:
            return ("error", type(exc).__name__, str(exc))
        except Exception as exc:  # anything else is the arm's bug: report it, keep serving
            log.exception("arm host: %s failed", name)
            return ("error", "DeviceError", f"{name} failed in the arm's process: {type(exc).__name__}: {exc}")

    def wall_seconds(self, start: Pose, target: Pose) -> float:
        """Wall time a move will take (a simulator shows the arm moving meanwhile); 0 if moves are instant."""
        world = getattr(self.arm, "world", None)
        if world is None:
            return 0.0
        return world.motion_time(start, target) * world.clock.realtime_factor

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


class RemoteArm:
    """Client side of ArmHost: the arm's calls, each with a time-out. Thread-safe; stop() never waits for a move."""

    def __init__(self, address, authkey: bytes, timeout_s: float = 5.0, move_timeout_s: float = 300.0):
        self.address = _parse_address(address)
        self.authkey = authkey
        self.timeout_s = timeout_s
        self.move_timeout_s = move_timeout_s
        self._local = threading.local()  # one connection per calling thread: a stop need not queue behind a move
        self._all: list[Connection] = []
        self._lock = threading.Lock()

    def _conn(self) -> Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            try:
                conn = Client(self.address, authkey=self.authkey)
            except AuthenticationError as exc:
                raise DeviceError(f"simulated arm at {self.address[0]}:{self.address[1]} refused the key: {exc}; "
                                  f"pass the ArmHost's authkey") from exc
            except (OSError, EOFError) as exc:
                raise ConnectionLost(f"simulated arm at {self.address[0]}:{self.address[1]} is unreachable: {exc}") from exc
            self._local.conn = conn
            with self._lock:
                self._all.append(conn)
        return conn

    def _request(self, name: str, *args, timeout_s: float | None = None):
        conn = self._conn()
        try:
            conn.send((name, args))
            if not conn.poll(timeout_s or self.timeout_s):
                raise TimeoutError
            reply = conn.recv()
        except (OSError, EOFError, TimeoutError) as exc:
            self._local.conn = None
            conn.close()
            raise ConnectionLost(f"simulated arm at {self.address[0]}:{self.address[1]}: no reply to {name} "
                                 f"({type(exc).__name__})") from exc
        if reply[0] == "ok":
            return reply[1]
        _, kind, message = reply
        error = getattr(interfaces, kind, DeviceError)
        raise (error if isinstance(error, type) and issubclass(error, DeviceError) else DeviceError)(message)

    def move_linear(self, target: Pose, speed: float | None = None) -> None:
        self._request("move_linear", target, speed, timeout_s=self.move_timeout_s)

    def move_joints(self, joints: JointState, speed: float | None = None) -> None:
        self._request("move_joints", joints, speed, timeout_s=self.move_timeout_s)

    def pose(self) -> Pose:
        return self._request("pose")

    def joints(self) -> JointState:
        return self._request("joints")

    def stop(self) -> None:
        self._request("stop")

    def wall_seconds(self, start: Pose, target: Pose) -> float:
        return self._request("wall_seconds", start, target)

    def close(self) -> None:
        with self._lock:
            for conn in self._all:
                conn.close()
            self._all.clear()
        self._local = threading.local()


def _parse_address(address) -> tuple[str, int]:
    if isinstance(address, str):
        host, sep, port = address.rpartition(":")
        if not sep or not port.isdigit():
            raise ValueError(f"arm address {address!r}: expected HOST:PORT, e.g. 127.0.0.1:40123")
        return host, int(port)
    host, port = address
    return str(host), int(port)
