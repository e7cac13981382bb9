"""The true IRB 120 of the simulated cell: the catalogue DH table plus hidden errors, in pinocchio.

Kept apart from calibration/models/irb120.py on purpose (drivers never import calibration): the
estimator builds its own nominal model, and only this module knows the drawn errors.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

NOMINAL_DH = (  # (d m, a m, alpha rad, theta offset rad): /work/shared/PROTOCOLS.md
    (0.290, 0.0, -math.pi / 2, 0.0),
    (0.0, 0.270, 0.0, -math.pi / 2),
    (0.0, 0.070, -math.pi / 2, 0.0),
    (0.302, 0.0, math.pi / 2, 0.0),
    (0.0, 0.0, -math.pi / 2, 0.0),
    (0.072, 0.0, 0.0, math.pi),
)
JOINT_LIMITS_DEG = ((-165, 165), (-110, 110), (-110, 70), (-160, 160), (-120, 120), (-400, 400))


def draw_true_dh(rng: np.random.Generator, length_mm: float, joint_deg: float):
    """Every d and a off by up to +/- length_mm, every joint zero by up to +/- joint_deg."""
    rows = []
    for d, a, alpha, offset in NOMINAL_DH:
        dd, da = rng.uniform(-1, 1, 2) * length_mm * 1e-3
        rows.append((d + dd, a + da, alpha, offset + math.radians(rng.uniform(-1, 1) * joint_deg)))
    return tuple(rows)


def _dh(d, a, alpha, offset) -> pin.SE3:
    """Rz(offset) · Tz(d) · Tx(a) · Rx(alpha): the fixed part of one DH row."""
    return (pin.SE3(pin.utils.rotate("z", offset), np.zeros(3)) * pin.SE3(np.eye(3), np.array([a, 0.0, d]))
            * pin.SE3(pin.utils.rotate("x", alpha), np.zeros(3)))


class ArmKinematics:
    """Forward kinematics of the fixture frame and of points on it, for one DH table."""

    def __init__(self, dh, tool_m: tuple[float, float]):
        model = pin.Model()
        parent, placement = 0, pin.SE3.Identity()
        for i, ((lo, hi), row) in enumerate(zip(JOINT_LIMITS_DEG, dh), start=1):
            joint = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint_{i}", np.full(1, 1e3),
                                   np.full(1, 10.0), np.full(1, math.radians(lo)), np.full(1, math.radians(hi)))
            model.appendBodyToJoint(joint, pin.Inertia.Zero(), pin.SE3.Identity())
            parent, placement = joint, _dh(*row)
        fixture = placement * pin.SE3(np.eye(3), np.array([tool_m[1], 0.0, tool_m[0]]))
        self.fixture_id = model.addFrame(pin.Frame("fixture", parent, fixture, pin.FrameType.OP_FRAME))
        self.model, self.data = model, model.createData()
        self.lower, self.upper = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()

    def fixture_pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of the fixture (seventh) frame in the base frame."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        m = self.data.oMf[self.fixture_id]
        return m.rotation.copy(), m.translation.copy()

    def solve_fixture_pose(self, rotation, translation, q0, iters: int = 200) -> np.ndarray | None:
        """Joints that put the fixture frame at (rotation, translation), nearest q0; None if not reached
        within the joint limits (what a controller's move_linear needs)."""
        target = pin.SE3(np.asarray(rotation, dtype=float), np.asarray(translation, dtype=float))
        q = np.array(q0, dtype=float)
        for _ in range(iters):
            pin.framesForwardKinematics(self.model, self.data, q)
            to_target = self.data.oMf[self.fixture_id].actInv(target)
            err = pin.log6(to_target).vector
            if np.linalg.norm(err) < 1e-11:
                return q
            pin.computeJointJacobians(self.model, self.data, q)
            J = pin.Jlog6(to_target.inverse()) @ pin.getFrameJacobian(self.model, self.data, self.fixture_id,
                                                                       pin.ReferenceFrame.LOCAL)
            q = np.clip(q + J.T @ np.linalg.solve(J @ J.T + 1e-8 * np.eye(6), err), self.lower, self.upper)
        return None
