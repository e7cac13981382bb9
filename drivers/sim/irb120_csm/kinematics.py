"""The true IRB 120 of the simulated cell: the catalogue DH table (geometry.irb120) plus hidden errors.

Only this module draws the errors; the estimator builds its chain from the catalogue table alone
(calibration/models/irb120.py).
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from geometry.irb120 import IRB120_DH, Chain


def draw_true_dh(rng: np.random.Generator, length_mm: float, joint_deg: float):
    """Every d and a off by up to +/- length_mm, every joint zero by up to +/- joint_deg."""
    rows = []
    for d, a, alpha, offset in IRB120_DH:
        dd, da = rng.uniform(-1, 1, 2) * length_mm * 1e-3
        rows.append((d + dd, a + da, alpha, offset + math.radians(rng.uniform(-1, 1) * joint_deg)))
    return tuple(rows)


class ArmKinematics(Chain):
    """Chain(dh, tool_m): forward kinematics of the fixture frame for one DH table, and the joints a
    controller's move_linear needs."""

    def fixture_pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of the fixture (seventh) frame in the base frame."""
        m = self.placement(q)
        return m.rotation.copy(), m.translation.copy()

    def solve_fixture_pose(self, rotation, translation, q0, iters: int = 200) -> np.ndarray | None:
        """Joints that put the fixture frame at (rotation, translation), nearest q0; None if not reached
        within the joint limits."""
        target = pin.SE3(np.asarray(rotation, dtype=float), np.asarray(translation, dtype=float))
        q, reached = self.reach_pose(target, q0, tol=1e-11, max_iter=iters)
        return q if reached else None
