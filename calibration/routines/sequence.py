"""A sequence: routines run one after the other as one job, each into its own folder of the job's.

Declared by a family (its `__init__.py`: `SEQUENCES`), read by the core without importing a routine. A
sequence's folder holds one folder per routine, numbered in its order ("03-hybrid-area2")."""

from __future__ import annotations

from dataclasses import dataclass, field

from calibration.errors import UnknownName


@dataclass(frozen=True)
class Item:
    """One routine of a sequence: `name` is how results and folders call it ("hybrid.area2"), `params` what it
    sets of the routine's parameters (the rest come from the cell file, as for a routine run alone)."""

    name: str
    routine: str
    params: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Sequence:
    name: str
    items: tuple[Item, ...]
    description: str = ""

    @classmethod
    def of(cls, name: str, *items: str | Item, description: str = "") -> "Sequence":
        """Items given as a routine's name run that routine with the cell file's parameters."""
        return cls(name, tuple(i if isinstance(i, Item) else Item(i, i) for i in items), description)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.items)

    def index(self, item: str) -> int:
        try:
            return self.names.index(item)
        except ValueError:
            raise UnknownName(f"item: {item!r} is not part of {self.name} (its items: {', '.join(self.names)})") from None

    def folder(self, item: str) -> str:
        """The run folder of one of its routines, inside the sequence's folder (e.g. "03-hybrid-area2")."""
        return f"{self.index(item) + 1:02d}-{item.replace('.', '-')}"

    def number(self, item: str) -> str:
        """"2/4" for the second of its four routines."""
        return f"{self.index(item) + 1}/{len(self.items)}"
