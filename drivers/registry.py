"""Backend name -> "module:Class", imported only when a cell file chooses it.

Vendor SDKs (ur_rtde, harvesters, depthai) stay optional: a cell that does not use
a backend never imports its module. The simulated fakes are more backends, as
python-can's `virtual` bus is; which fake runs on which simulated world is the
world-kind table's (drivers/sim/kinds.py), merged in here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.lazy import load
from drivers.sim.kinds import build_world, fake_backends

DRIVERS: dict[str, dict[str, str]] = {
    "arm": {
        "abb": "drivers.arms.abb:AbbArm",
        "ur": "drivers.arms.ur.arm:UrArm",
    },
    "gripper": {
        "epick": "drivers.grippers.epick:EPickGripper",
        "vgc10": "drivers.grippers.vgc10:Vgc10Gripper",
    },
    "camera": {
        "genicam": "drivers.cameras.genicam:GenICamCamera",
        "uvc": "drivers.cameras.uvc:UvcCamera",
        "oak": "drivers.cameras.oak:OakCamera",
    },
    "operator": {
        "console": "drivers.operators.terminal:ConsoleOperator",
        "web": "drivers.operators.web:WebOperator",  # a person at the daemon's web console
    },
}

BACKENDS: dict[str, dict[str, str]] = {kind: {**fake_backends().get(kind, {}), **real} for kind, real in DRIVERS.items()}


class UnknownBackend(LookupError):
    pass


def backend_names(kind: str) -> list[str]:
    return sorted(BACKENDS.get(kind, {}))


def backend_class(kind: str, backend: str) -> Any:
    """The driver class for `backend`; a clear error names the backends that exist."""
    if kind not in BACKENDS:
        raise UnknownBackend(f"unknown device kind {kind!r}; allowed: {', '.join(sorted(BACKENDS))}")
    try:
        target = BACKENDS[kind][backend]
    except KeyError:
        raise UnknownBackend(
            f"unknown {kind} backend {backend!r}; allowed: {', '.join(backend_names(kind))}"
        ) from None
    try:
        return load(target)
    except ImportError as exc:  # a vendor SDK that is not installed
        raise UnknownBackend(
            f"{kind} backend {backend!r} needs a package that is not installed: {exc}"
        ) from exc


@dataclass
class DriverContext:
    """What drivers of one cell share: for the simulated backends, the one world."""

    sim_config: Any = None  # the cell file's sim section (a model of the drivers/sim/kinds.py table)
    store_dir: Path | None = None  # where the cell keeps its results, for a backend that keeps state beside them
    _world: Any = field(default=None, init=False, repr=False)

    @classmethod
    def around(cls, world) -> "DriverContext":
        """A context whose drivers share `world`, which already exists (a protocol simulator's, a test's)."""
        context = cls(sim_config=world.config)
        context._world = world
        return context

    @property
    def existing_world(self):
        """The simulated world if one was built for this cell, else None."""
        return self._world

    def sim_world(self):
        if self._world is None:
            if self.sim_config is None:
                raise UnknownBackend("a 'sim' backend needs the cell file's 'sim:' section")
            self._world = build_world(self.sim_config)
        return self._world
