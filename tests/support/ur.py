"""The UR tests share: a known joint position, and an arm at it whose moves take wall time."""

from __future__ import annotations

import time

from drivers.interfaces import Pose
from drivers.registry import DriverContext, backend_class

from tests.conftest import microcell_data

# the UR5e's angles for KNOWN (default mounting: base at (-65, -390, 0) mm, turned 180 deg)
KNOWN_Q = (-1.527980001572173, -2.2363946304580242, -2.3158684172299604, -0.16012593269670505,
           1.5707963267948983, -0.4571836747772764)


class TestArm:
    """An arm at a known pose; a move takes `seconds` of wall time (MotionTimed), so a client sees it move."""

    __test__ = False

    def __init__(self, pose: Pose, seconds: float = 0.0):
        self._pose = pose
        self.seconds = seconds

    def move_linear(self, target: Pose, speed=None) -> None:
        time.sleep(self.seconds)
        self._pose = target

    def pose(self) -> Pose:
        return self._pose

    def stop(self) -> None:
        pass

    def wall_seconds(self, start, target) -> float:
        return self.seconds


LIMITS = microcell_data()["arm"]["limits"]


def ur_arm(host: str, **options):
    """A UrArm on the micro cell's limits, for a simulator at `host`."""
    return backend_class("arm", "ur").create("arm", {"host": host, "limits": LIMITS, **options}, DriverContext())
