"""Import "module:Name" targets only when used: tables of backends, worlds and simulators name their classes
this way, so a cell imports only the vendor SDKs and renderers it chooses."""

from __future__ import annotations

import importlib
from typing import Any


def load(target: str) -> Any:
    """The object `target` ("package.module:Name") names; ImportError if its module cannot load."""
    module_name, _, name = target.partition(":")
    return getattr(importlib.import_module(module_name), name)


def target_of(obj: Any) -> str:
    """The "module:Name" that `load` turns back into `obj`."""
    return f"{obj.__module__}:{obj.__qualname__}"
