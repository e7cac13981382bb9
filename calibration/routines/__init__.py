"""The routines and sequences the orchestrator can run, found by their files.

Routines come in families, one folder each: `micro` (seed 001's micro cell), `csm` (seed 002), `vr`
(seed 000), `health` (does a calibration still hold?), and the six-axis routines to come. In a family's
folder:
- a routine is one module named for it (`virtual_grid.py` is the routine `virtual-grid`), holding one
  `Routine` class with that `name`;
- a module whose name starts with `_` is the family's own helper;
- `__init__.py` may declare the family's `SEQUENCES` (`Sequence`s, by name) and `ALIASES` (other names
  `cellctl fit` takes for a routine), and imports nothing heavy.

So adding a routine is adding its file, and listing the names reads file names only: the CLI's choices
import no routine and none of their numerics. Nothing outside a family names its routines: the core
asks a routine what it can do (`JudgesCalibrations`, its `truth`), never which one it is."""

from __future__ import annotations

import functools
import importlib
import pkgutil
from pathlib import Path

from calibration.errors import UnknownName
from calibration.routines.sequence import Item, Sequence

__all__ = ["Item", "Sequence", "routine_names", "runnable_names", "routine_class", "all_routines", "sequences",
           "sequence", "is_sequence", "fit_aliases", "judging_routine", "rescan"]

HERE = Path(__file__).parent


@functools.cache
def _families() -> tuple[str, ...]:
    return tuple(sorted(m.name for m in pkgutil.iter_modules([str(HERE)]) if m.ispkg and not m.name.startswith("_")))


@functools.cache
def _routine_modules() -> dict[str, str]:
    """Routine name -> its module, from the file names in the family folders (each family package's __path__)."""
    found: dict[str, str] = {}
    for family in _families():
        for m in pkgutil.iter_modules(importlib.import_module(f"{__name__}.{family}").__path__):
            if m.ispkg or m.name.startswith("_"):
                continue
            name = m.name.replace("_", "-")
            if name in found:
                raise RuntimeError(f"routine {name!r} is in two families: {found[name]} and {family}.{m.name}")
            found[name] = f"{__name__}.{family}.{m.name}"
    return dict(sorted(found.items()))


def routine_names() -> tuple[str, ...]:
    """Every routine's name, sorted (file names only: no routine imported)."""
    return tuple(_routine_modules())


def runnable_names() -> tuple[str, ...]:
    """What a job can run: every routine, then every sequence, each sorted."""
    return routine_names() + tuple(sequences())


@functools.cache
def _family_declarations() -> tuple[dict[str, Sequence], dict[str, str]]:
    seqs: dict[str, Sequence] = {}
    aliases: dict[str, str] = {}
    for family in _families():
        module = importlib.import_module(f"{__name__}.{family}")
        for seq in getattr(module, "SEQUENCES", ()):
            if seq.name in seqs or seq.name in _routine_modules():
                raise RuntimeError(f"sequence {seq.name!r} of {family} is declared twice or names a routine")
            seqs[seq.name] = seq
        aliases.update(getattr(module, "ALIASES", {}))
    return dict(sorted(seqs.items())), aliases


def sequences() -> dict[str, Sequence]:
    """Every family's sequences, by name (their `__init__`s only: light)."""
    return _family_declarations()[0]


def is_sequence(name: str) -> bool:
    return name in sequences()


def sequence(name: str) -> Sequence:
    try:
        return sequences()[name]
    except KeyError:
        raise UnknownName(f"unknown sequence {name!r}; allowed: {', '.join(sequences())}") from None


def fit_aliases() -> dict[str, str]:
    """Other names `cellctl fit` takes, each for a routine (`csm`: csm-positioning's view parameters)."""
    return _family_declarations()[1]


def routine_class(name: str):
    """The routine's class (imports its module, and so its numerics)."""
    try:
        module = _routine_modules()[name]
    except KeyError:
        raise UnknownName(f"unknown routine {name!r}; allowed: {', '.join(_routine_modules())}") from None
    found = [c for c in vars(importlib.import_module(module)).values()
             if isinstance(c, type) and c.__module__ == module and getattr(c, "name", None) == name]
    if len(found) != 1:
        raise RuntimeError(f"{module} must define one routine class named {name!r}; it defines {len(found)}")
    return found[0]


def rescan() -> None:
    """Look at the family folders again (after a routine's file was added while running: a test's example)."""
    for found in (_families, _routine_modules, _family_declarations):
        found.cache_clear()


def all_routines() -> dict[str, type]:
    """name -> class for every routine (imports them all)."""
    return {name: routine_class(name) for name in _routine_modules()}


def judging_routine() -> str:
    """The routine that judges whether the active calibrations still hold (a scheduled check, a touch-up)."""
    from calibration.routines.base import JudgesCalibrations  # numpy, pydantic: only once routines are loaded

    judges = [name for name, cls in all_routines().items() if issubclass(cls, JudgesCalibrations)]
    if len(judges) != 1:
        raise RuntimeError(f"expected one routine that judges calibrations, found {judges or 'none'}")
    return judges[0]
