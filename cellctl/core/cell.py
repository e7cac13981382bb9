"""A cell assembled from its cell file: devices built by the registry, connected, closed.

Every backend of the driver registry (drivers/registry.py), the web operator's too, is built the
same way, from its options and the cell's shared DriverContext (the simulated world; the store,
whose daemon answers the web operator).
"""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

from drivers.interfaces import DeviceError
from drivers.registry import DriverContext, backend_class

from calibration.routines.base import Devices

from cellctl.config import CellFile


@runtime_checkable
class StepAware(Protocol):
    """An optional device capability: it keeps something per run step (the web operator: a stop it was
    asked for) and forgets it when the next step begins."""

    def begin_step(self) -> None: ...


class WallClock:
    def now(self) -> float:
        return time.monotonic()


class Cell:
    def __init__(self, config: CellFile, cell_text: str = ""):
        self.config = config
        self.cell_text = cell_text
        self.context = DriverContext(sim_config=config.sim, store_dir=config.store_path())
        built = {(kind, name): backend_class(kind, dev.backend).create(name, dev.options, self.context)
                 for kind, name, dev in config.devices()}
        self.arm = built[("arm", "arm")]
        self.gripper = built.get(("gripper", "gripper"))
        self.operator = built[("operator", "operator")]
        self.cameras = {name: dev for (kind, name), dev in built.items() if kind == "camera"}
        self._named = built  # in the cell file's order
        self.devices = Devices(self.arm, self.cameras, self.gripper, config.areas_by_name(), operator=self.operator)
        self.sim_servers: list = []  # protocol simulators running for this cell (sim.servers)

    @property
    def sim_world(self):
        """The simulated world when this cell has one (truth for reports and tests), else None."""
        return self.context.existing_world

    @property
    def clock(self):
        world = self.sim_world
        return world.clock if world is not None else WallClock()

    def named_devices(self):
        """(kind, name, device) for every device, in the cell file's order."""
        for (kind, name), dev in self._named.items():
            yield kind, name, dev

    def all_devices(self):
        return [self.arm, *([self.gripper] if self.gripper else []), *self.cameras.values(), self.operator]

    def connect(self) -> None:
        self.start_sim_servers()
        try:
            for dev in self.all_devices():
                dev.connect()
        except BaseException:
            self.close()
            raise

    def start_sim_servers(self) -> None:
        """The cell file's protocol simulators, on this cell's world, before the real drivers connect (once: a
        second call leaves the running ones)."""
        specs = getattr(self.config.sim, "servers", None) or []
        if not specs or self.sim_servers:
            return
        from drivers.sim.servers import start_server

        limits = self.config.arm.options.get("limits")
        for i, spec in enumerate(specs):
            try:
                self.sim_servers.append(start_server(spec, self.context.sim_world(), limits))
            except Exception as exc:
                self._stop_sim_servers()
                where = f"{spec.host}:{spec.port}" if spec.port else spec.host
                raise DeviceError(f"sim.servers[{i}]: the {spec.protocol} simulator on {where} could not start: "
                                  f"{exc}") from exc

    def stop(self) -> None:
        for dev in self.all_devices():
            dev.stop()

    def close(self) -> None:
        for dev in self.all_devices():
            try:
                dev.close()
            except Exception:  # closing is best effort; the next device still gets closed
                pass
        self._stop_sim_servers()

    def _stop_sim_servers(self) -> None:
        while self.sim_servers:
            try:
                self.sim_servers.pop().close()
            except Exception:  # best effort, as for the devices
                pass

    def begin_step(self, key: int) -> None:
        """Sim: key the world's noise by step so a resumed run equals an uninterrupted one. Any cell: a device
        that remembers a stop (the web operator) forgets the previous step's."""
        world = self.sim_world
        if world is not None:
            world.begin_step(key)
        if isinstance(self.operator, StepAware):
            self.operator.begin_step()

    def __enter__(self) -> "Cell":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
