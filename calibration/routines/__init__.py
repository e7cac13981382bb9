"""The routines the orchestrator can run, by name."""

from ..errors import UnknownName
from .check import Check
from .csm_positioning import CsmPositioning
from .hybrid import Hybrid
from .onboard_camera import OnboardCamera
from .pick_place import PickPlace
from .place_test import PlaceTest
from .repeatability import Repeatability
from .rotation_sweep import RotationSweep
from .virtual_grid import VirtualGrid
from .virtual_grid_area2 import VirtualGridArea2
from .vr_approach import VrApproach
from .vr_coarse import VrCoarse
from .vr_experiments import VrExperiments
from .vr_fine import VrFine

ROUTINES = {cls.name: cls for cls in (VirtualGrid, VirtualGridArea2, Hybrid, RotationSweep, OnboardCamera, PlaceTest,
                                         CsmPositioning)}
ROUTINES.update({cls.name: cls for cls in (VrCoarse, VrFine, VrApproach, VrExperiments)})
ROUTINES[Repeatability.name] = Repeatability
ROUTINES[Check.name] = Check
ROUTINES[PickPlace.name] = PickPlace


def routine_class(name: str):
    try:
        return ROUTINES[name]
    except KeyError:
        raise UnknownName(f"unknown routine {name!r}; allowed: {', '.join(sorted(ROUTINES))}") from None
