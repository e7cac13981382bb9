"""The calibrated inverse kinematics (geometry/kinematic_table.py) from a start far from the solution: a plan's
reach check is made from where the arm stands, not from the neighbouring pose."""

import numpy as np
import pytest

from geometry import kinematic_table as kt


def test_inverse_from_a_far_start_converges_to_the_pose():
    table = kt.nominal_table("irb120")
    home = np.radians([0.0, 0.0, 0.0, 0.0, 90.0, 0.0])
    target = np.radians([-13.0, 45.0, 28.0, -10.0, 51.0, -5.0])  # the IRB 120's iso9283 P2, seen from home
    T = table.forward(target)
    q = table.inverse(T, home)
    assert np.abs(table.forward(q) - T).max() < 1e-8
    assert not table.within_limits(q)  # no problem: within the joint limits


def test_without_the_step_limit_the_same_start_diverges(monkeypatch):
    """The test above can fail: full Gauss-Newton steps from home overshoot and leave the joint limits."""
    monkeypatch.setattr(kt, "MAX_STEP_RAD", 1e9)
    table = kt.nominal_table("irb120")
    T = table.forward(np.radians([-13.0, 45.0, 28.0, -10.0, 51.0, -5.0]))
    with pytest.raises(kt.IKFailed):
        table.inverse(T, np.radians([0.0, 0.0, 0.0, 0.0, 90.0, 0.0]))
