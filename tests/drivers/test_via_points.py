"""Via points (MovesThrough, issue 31): passed without settling, the move's time still counted; a wrapper that
changes targets changes its via points too; an arm without the capability settles as before."""

import numpy as np
import pytest

from drivers.interfaces import MovesThrough, Pose, move_via

from calibration.usage import ToolCompensatedArm

from cellctl.config import load_cell_file
from cellctl.core.cell import Cell

from tests.conftest import MICROCELL


def test_a_via_point_counts_the_motion_and_skips_the_settling():
    config, text = load_cell_file(MICROCELL)
    with Cell(config, text) as cell:
        arm, world = cell.arm, cell.sim_world
        assert isinstance(arm, MovesThrough)
        start, above = arm.pose(), Pose(0.040, 0.030, 0.010, 0.0)
        motion = world.motion_time(world.arm.commanded, above)
        t0 = world.clock.now()
        arm.move_through(above)
        assert world.clock.now() - t0 == pytest.approx(motion)
        down = Pose(0.040, 0.030, 0.0, 0.0)
        motion = world.motion_time(world.arm.commanded, down)
        t0 = world.clock.now()
        arm.move_linear(down)
        assert world.clock.now() - t0 == pytest.approx(motion + config.sim.motion.settle_s)
        assert arm.pose() != start


class Recording:
    """An arm that records what it is sent; `via`: whether it offers MovesThrough."""

    def __init__(self):
        self.sent = []

    def move_linear(self, target, speed=None):
        self.sent.append(("linear", target))


class RecordingVia(Recording):
    def move_through(self, target, speed=None):
        self.sent.append(("through", target))


class Shift:
    def tool_shift(self, alpha):
        return np.array([1e-4, -2e-4]) * alpha


def test_a_wrapper_compensates_its_via_points_and_an_arm_without_them_settles():
    target = Pose(0.05, 0.03, 0.001, 0.5)
    plain = Recording()
    move_via(plain, target)
    assert plain.sent == [("linear", target)]  # no capability: a settled move, as before

    inner = RecordingVia()
    move_via(ToolCompensatedArm(inner, Shift(), 0.0), target)
    kind, sent = inner.sent[0]
    assert kind == "through" and (sent.x, sent.y) == pytest.approx((0.05 - 0.5e-4, 0.03 + 1e-4))

    inner = Recording()  # the wrapper over an arm without via points: its compensated move, settled
    move_via(ToolCompensatedArm(inner, Shift(), 0.0), target)
    assert inner.sent[0][0] == "linear" and inner.sent[0][1].x == pytest.approx(0.05 - 0.5e-4)
