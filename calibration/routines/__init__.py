"""The routines the orchestrator can run, by name.

The table names each routine's class as "module:Class", imported on first use (as the driver and world
tables do), so listing the names (the CLI's `run` choices) imports no routine and its numerics."""

import importlib

from calibration.errors import UnknownName

TABLE = {
    "virtual-grid": "virtual_grid:VirtualGrid",
    "virtual-grid-area2": "virtual_grid_area2:VirtualGridArea2",
    "hybrid": "hybrid:Hybrid",
    "rotation-sweep": "rotation_sweep:RotationSweep",
    "onboard-camera": "onboard_camera:OnboardCamera",
    "place-test": "place_test:PlaceTest",
    "csm-positioning": "csm_positioning:CsmPositioning",
    "vr-coarse": "vr_coarse:VrCoarse",
    "vr-fine": "vr_fine:VrFine",
    "vr-approach": "vr_approach:VrApproach",
    "vr-experiments": "vr_experiments:VrExperiments",
    "repeatability": "repeatability:Repeatability",
    "check": "check:Check",
    "pick-place": "pick_place:PickPlace",
}
NAMES = tuple(TABLE)


def routine_class(name: str):
    try:
        module, _, cls = TABLE[name].partition(":")
    except KeyError:
        raise UnknownName(f"unknown routine {name!r}; allowed: {', '.join(sorted(TABLE))}") from None
    return getattr(importlib.import_module(f"{__name__}.{module}"), cls)


def __getattr__(attr: str):
    """`ROUTINES`: name -> class for every routine (imports them all, once)."""
    if attr == "ROUTINES":
        routines = globals()["ROUTINES"] = {name: routine_class(name) for name in TABLE}
        return routines
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")
