"""Device backends that live in cellctl, looked up before drivers/registry.py.

The web operator (`operator: {backend: web}`, drivers/operators/web.py) is a person
answering through the daemon's API and console, so it belongs to cellctl; drivers/
imports nothing from cellctl, so drivers/registry.py cannot name it. The cell file's
check (config.py) and the cell's assembly (cell.py) ask here; every other backend is
the registry's, unchanged.
"""

from __future__ import annotations

import importlib
from typing import Any

from drivers import registry
from drivers.registry import UnknownBackend

CELLCTL_BACKENDS: dict[str, dict[str, str]] = {
    "operator": {"web": "drivers.operators.web:WebOperator"},
}


def backend_names(kind: str) -> list[str]:
    return sorted(set(registry.backend_names(kind)) | set(CELLCTL_BACKENDS.get(kind, {})))


def backend_class(kind: str, backend: str) -> Any:
    """The class for `backend`: cellctl's own, else the driver registry's; errors name every allowed backend."""
    target = CELLCTL_BACKENDS.get(kind, {}).get(backend)
    if target is None:
        if kind in registry.BACKENDS and backend not in registry.BACKENDS[kind]:
            raise UnknownBackend(f"unknown {kind} backend {backend!r}; allowed: {', '.join(backend_names(kind))}")
        return registry.backend_class(kind, backend)
    module_name, _, class_name = target.partition(":")
    return getattr(importlib.import_module(module_name), class_name)
