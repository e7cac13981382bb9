"""Protocol-level simulators: the simulated world behind the real wire protocols.

Each module serves one protocol on loopback so the real drivers in `drivers/arms`,
`drivers/grippers` and `drivers/cameras` can be tested over real sockets and serial
ports. Every server module offers `start(world, host, port, options, ...)`, which returns
the running server (close() it), and `serve(world_config, host, port, ..., stop)`, which
blocks until `stop` is set (or SIGTERM, from `cellctl sim`); options hold the fault knobs.

`start_server` starts the one a cell file's `sim.servers` entry names on the cell's world (the table
drivers.sim.protocols.SIMULATORS: protocol -> its module's `start_for_cell(world, spec, arm_limits)`), so
the cell's real driver of that protocol sees the same truth as its simulated cameras.
"""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

from drivers.interfaces import ConnectionLost
from drivers.lazy import load
from drivers.registry import DriverContext, backend_class
from drivers.sim.base import SIMULATORS
from drivers.sim.kinds import build_world, fake_of

ANY_TURN = {"x_mm": (-1e4, 1e4), "y_mm": (-1e4, 1e4), "z_mm": (-1e4, 1e4), "alpha_deg": (-1e4, 1e4)}



def sim_device(kind: str, world, options: dict | None = None):
    """A connected simulated `kind` ("arm", "gripper") on `world`: the world's own fake, as its cell's would be."""
    device = backend_class(kind, fake_of(world.config, kind)).create(kind, options or {}, DriverContext.around(world))
    device.connect()
    return device


def world_of(world_config, world):
    """The world to serve: the caller's, or a new one built from `world_config`."""
    if world is not None:
        return world
    if world_config is None:
        raise ValueError("a simulator needs a world: pass world= or a world_config")
    return build_world(world_config)


def run_until(server, stop: threading.Event | None) -> None:
    """Keep a started server up until `stop` is set, then close it."""
    try:
        (stop or threading.Event()).wait()
    finally:
        server.close()


def accepted(listener: socket.socket, closing: threading.Event):
    """The connections (socket, peer) `listener` accepts (its accept time-out set, so that `closing`
    is seen), until `closing` is set or the listener is closed."""
    while not closing.is_set():
        try:
            connection = listener.accept()
        except TimeoutError:
            continue
        except OSError:
            return
        yield connection


def received(sock: socket.socket, closing: threading.Event, size: int):
    """What `sock` receives (its receive time-out set, so that `closing` is seen), at most `size` bytes
    at a time, until `closing` is set or the peer closes."""
    while not closing.is_set():
        try:
            chunk = sock.recv(size)
        except TimeoutError:
            continue
        if not chunk:
            return
        yield chunk


def free_ports(n: int = 1, host: str = "127.0.0.1") -> list[int]:
    """`n` distinct TCP ports on `host` that nothing listens on now, for simulators to be served on
    (a cell file's fixed ports may be taken on a test machine)."""
    probes = [socket.socket() for _ in range(n)]
    try:
        for probe in probes:
            probe.bind((host, 0))
        return [probe.getsockname()[1] for probe in probes]
    finally:
        for probe in probes:
            probe.close()


def connect_when_up(device, timeout_s: float = 5.0) -> None:
    """connect() `device` to a simulator that is still starting (`serve` in another thread or process):
    retried while the connection is refused, the last ConnectionLost raised after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            device.connect()
            return
        except ConnectionLost:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def start_server(spec, world, arm_limits: dict | None = None) -> Any:
    """Start the simulator a cell file's `sim.servers` entry (drivers.sim.base.SimServer) names on
    `world`; returns it running (close() stops it). `arm_limits`: the cell's workspace box."""
    if spec.protocol not in SIMULATORS:
        raise ValueError(f"sim.servers: unknown protocol {spec.protocol!r}; allowed: {', '.join(SIMULATORS)}")
    return load(SIMULATORS[spec.protocol])(world, spec, arm_limits)
