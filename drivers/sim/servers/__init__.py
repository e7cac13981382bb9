"""Protocol-level simulators: the simulated world behind the real wire protocols.

Each module serves one protocol on loopback so the real drivers in `drivers/arms`,
`drivers/grippers` and `drivers/cameras` can be tested over real sockets and serial
ports. Every server module offers `start(world, host, port, options, ...)`, which returns
the running server (close() it), and `serve(world_config, host, port, ..., stop)`, which
blocks until `stop` is set (or SIGTERM, from `cellctl sim`); options hold the fault knobs.

`start_server` starts the one a cell file's `sim.servers` entry names on the cell's world,
so the cell's real driver of that protocol sees the same truth as its simulated cameras.
"""

from __future__ import annotations

import threading
from typing import Any

ANY_TURN = {"x_mm": (-1e4, 1e4), "y_mm": (-1e4, 1e4), "z_mm": (-1e4, 1e4), "alpha_deg": (-1e4, 1e4)}


def sim_backend(world_config, kind: str) -> str:
    """The registry backend of the in-process `kind` fake on this kind of world: a world config may name
    its own (`sim_backends`, e.g. the IRB 120 world's arm is "sim-irb120"); otherwise "sim"."""
    return getattr(world_config, "sim_backends", {}).get(kind, "sim")


def sim_device(kind: str, world, options: dict | None = None):
    """A connected simulated `kind` ("arm", "gripper") on `world`: the world's own fake, as its cell's would be."""
    from ...registry import DriverContext, backend_class

    context = DriverContext(sim_config=world.config)
    context._shared["world"] = world
    device = backend_class(kind, sim_backend(world.config, kind)).create(kind, options or {}, context)
    device.connect()
    return device


def world_of(world_config, world):
    """The world to serve: the caller's, or a new one built from `world_config`."""
    if world is not None:
        return world
    if world_config is None:
        raise ValueError("a simulator needs a world: pass world= or a world_config")
    return world_config.build_world()


def run_until(server, stop: threading.Event | None) -> None:
    """Keep a started server up until `stop` is set, then close it."""
    try:
        (stop or threading.Event()).wait()
    finally:
        server.close()


def start_server(spec, world, arm_limits: dict | None = None) -> Any:
    """Start the simulator a cell file's `sim.servers` entry (drivers.sim.config.SimServer) names on
    `world`; returns it running (close() stops it). `arm_limits`: the cell's workspace box."""
    options = dict(spec.options)
    if spec.protocol == "abb":
        from .abb import MOTION_PORT, start

        return start(world, spec.host, MOTION_PORT if spec.port is None else spec.port, options=options, limits=arm_limits)
    if spec.protocol == "ur":
        from drivers.limits import WorkspaceBox

        from .ur.server import WorldArmSimulator

        if spec.port is not None:
            raise ValueError("sim.servers: a UR simulator listens on the fixed UR ports; pick the address with host")
        return WorldArmSimulator(world, spec.host, WorkspaceBox(**(arm_limits or ANY_TURN)), options).start()
    if spec.protocol == "epick":
        from .epick import TCP_PORT, start

        return start(world, spec.host, TCP_PORT if spec.port is None else spec.port, options=options,
                     serial_port=spec.serial_port)
    if spec.protocol == "vgc10":
        from .vgc10 import TCP_PORT, start

        return start(world, spec.host, TCP_PORT if spec.port is None else spec.port, options=options)
    raise ValueError(f"sim.servers: unknown protocol {spec.protocol!r}; allowed: abb, ur, epick, vgc10")
