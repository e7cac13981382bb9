"""Backend name -> "module:Class", imported only when a cell file chooses it.

Vendor SDKs (ur_rtde, harvesters, depthai) stay optional: a cell that does not use
a backend never imports its module. The simulated fake is one more backend, as
python-can's `virtual` bus is.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any

BACKENDS: dict[str, dict[str, str]] = {
    "arm": {
        "sim": "drivers.sim.devices:SimArm",
        "sim-irb120": "drivers.sim.six_axis.devices:SimSixAxisArm",
        "sim-vr": "drivers.sim.vr.devices:VrArm",
        "abb": "drivers.arms.abb:AbbArm",
        "ur": "drivers.arms.ur:UrArm",
    },
    "gripper": {
        "sim": "drivers.sim.devices:SimGripper",
        "epick": "drivers.grippers.epick:EPickGripper",
        "vgc10": "drivers.grippers.vgc10:Vgc10Gripper",
    },
    "camera": {
        "sim": "drivers.sim.devices:SimCamera",
        "sim-vr": "drivers.sim.vr.devices:VrCameraDevice",
        "genicam": "drivers.cameras.genicam:GenICamCamera",
        "uvc": "drivers.cameras.uvc:UvcCamera",
        "oak": "drivers.cameras.oak:OakCamera",
    },
    "operator": {"sim": "drivers.sim.devices:SimOperator", "console": "drivers.console:ConsoleOperator",
                 "sim-vr": "drivers.sim.vr.devices:VrOperator"},
}


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
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:  # a vendor SDK that is not installed
        raise UnknownBackend(
            f"{kind} backend {backend!r} needs a package that is not installed: {exc}"
        ) from exc
    return getattr(module, class_name)


@dataclass
class DriverContext:
    """What drivers of one cell share: for the simulated backends, the one world."""

    sim_config: Any = None  # the cell file's sim section (e.g. drivers.sim.config.SimWorldConfig): has build_world()
    _shared: dict = field(default_factory=dict)

    @property
    def existing_world(self):
        """The simulated world if one was built for this cell, else None."""
        return self._shared.get("world")

    def sim_world(self):
        if "world" not in self._shared:
            if self.sim_config is None:
                raise UnknownBackend("a 'sim' backend needs the cell file's 'sim:' section")
            self._shared["world"] = self.sim_config.build_world()  # each kind of world config builds its own
        return self._shared["world"]
