"""The one table of simulated world kinds: what a cell file's `sim:` section builds, and which fakes run on it.

`sim: {world: KIND, ...}` picks a row (no `world` key: micro-cell, as cell files written before there were
several kinds): the model that validates the section, the world class built from it (imported only when a
cell simulates, so renderers and pinocchio load only then), and for each device kind the fake backend that
runs on that world. drivers/registry.py offers these fakes beside the real drivers; cellctl/config.py
validates `sim:` by this table; drivers/sim/servers serves each world through its own fakes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

from pydantic import BaseModel

from drivers.lazy import load, target_of
from drivers.sim.base import SimWorld
from drivers.sim.irb120_csm.config import SixAxisWorldConfig
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.ur5e_handeye.config import HandEyeWorldConfig
from drivers.sim.vr.config import VrWorldConfig

DEFAULT_KIND = "micro-cell"


class Fake(NamedTuple):
    backend: str  # the name a cell file gives (`backend: sim`)
    target: str  # "module:Class"


@dataclass(frozen=True)
class WorldKind:
    config: type[BaseModel]  # the `sim:` section
    world: str  # "module:Class" built from it
    fakes: dict[str, Fake]  # device kind (arm, gripper, camera, operator) -> the fake on this world


_CAMERA = "drivers.sim.devices:SimCamera"  # renders whichever world it is on
_OPERATOR = "drivers.sim.devices:SimOperator"

WORLD_KINDS: dict[str, WorldKind] = {
    "micro-cell": WorldKind(SimWorldConfig, "drivers.sim.micro.world:World", {
        "arm": Fake("sim", "drivers.sim.devices:SimArm"),
        "gripper": Fake("sim", "drivers.sim.devices:SimGripper"),
        "camera": Fake("sim", _CAMERA),
        "operator": Fake("sim", _OPERATOR)}),
    "irb120-csm": WorldKind(SixAxisWorldConfig, "drivers.sim.irb120_csm.world:SixAxisWorld", {
        "arm": Fake("sim-irb120", "drivers.sim.irb120_csm.devices:SimSixAxisArm"),
        "camera": Fake("sim", _CAMERA),
        "operator": Fake("sim", _OPERATOR)}),
    "ur5e-handeye": WorldKind(HandEyeWorldConfig, "drivers.sim.ur5e_handeye.world:HandEyeWorld", {
        "arm": Fake("sim-ur5e", "drivers.sim.ur5e_handeye.devices:SimUr5eArm"),
        "gripper": Fake("sim", "drivers.sim.devices:SimGripper"),
        "camera": Fake("sim", _CAMERA),
        "operator": Fake("sim", _OPERATOR)}),
    "vr": WorldKind(VrWorldConfig, "drivers.sim.vr.world:VrWorld", {
        "arm": Fake("sim-vr", "drivers.sim.vr.devices:VrArm"),
        "camera": Fake("sim-vr", _CAMERA),
        "operator": Fake("sim-vr", "drivers.sim.vr.devices:VrOperator")}),
}


def world_kind(section: Any) -> str:
    """The kind of a `sim:` section, validated (a model) or not yet (a mapping)."""
    if isinstance(section, dict):
        return section.get("world", DEFAULT_KIND)
    return getattr(section, "world", DEFAULT_KIND)


def build_world(section: BaseModel) -> SimWorld:
    """The simulated world a validated `sim:` section describes."""
    return load(WORLD_KINDS[world_kind(section)].world)(section)


def fake_backends() -> dict[str, dict[str, str]]:
    """Device kind -> {backend: "module:Class"} of every world's fakes, for the driver registry."""
    table: dict[str, dict[str, str]] = {}
    for kind in WORLD_KINDS.values():
        for device, fake in kind.fakes.items():
            known = table.setdefault(device, {}).setdefault(fake.backend, fake.target)
            assert known == fake.target, f"{device} backend {fake.backend!r} names two fakes"
    return table


def fake_of(section: BaseModel, device: str) -> str:
    """The backend of this world's own `device` fake; ValueError if the world has none."""
    kind = world_kind(section)
    fake = WORLD_KINDS[kind].fakes.get(device)
    if fake is None:
        raise ValueError(f"the {kind} world simulates no {device} (it has: {', '.join(WORLD_KINDS[kind].fakes)})")
    return fake.backend


def offers(section: BaseModel, device: str, backend: str) -> bool:
    """Whether `backend` is the `device` fake of this `sim:` section's world."""
    fake = WORLD_KINDS[world_kind(section)].fakes.get(device)
    return fake is not None and fake.backend == backend


def is_fake(device: str, backend: str) -> bool:
    return backend in fake_backends().get(device, {})


def check_runs_on(fake_class: type, name: str, world: SimWorld) -> None:
    """A fake refuses a world whose kind does not list it (that very class: VrOperator is a SimOperator, yet needs
    the VR world): it would fail later, on a part of the world that is missing."""
    kind = world_kind(world.config)
    target = target_of(fake_class)
    if any(fake.target == target for fake in WORLD_KINDS[kind].fakes.values()):
        return
    homes = [(n, f.backend) for n, k in WORLD_KINDS.items() for f in k.fakes.values() if f.target == target]
    wanted = " or ".join(f"world: {n} (backend {b!r})" for n, b in homes)
    raise ValueError(f"{name}: {fake_class.__name__} needs a 'sim:' section with {wanted}; this one has world: {kind}")
