"""The ABB IRB 120's nominal kinematics (seed 002 Table I), built with pinocchio from its DH table.

Standard DH: T_i = Rz(θ_i + offset_i) · Tz(d_i) · Tx(a_i) · Rx(α_i); a seventh, fixed row (d7, a7) places
the fixture frame on the flange, and a fixture's features are points in that seventh frame.

`Chain` serves any DH table: the CSM estimator builds it from the catalogue table (calibration/models/irb120.py),
the simulated cell also from the table with its hidden drawn errors (drivers/sim/six_axis/kinematics.py).
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

# (d m, a m, alpha rad, theta offset rad) per joint: /work/shared/PROTOCOLS.md
IRB120_DH = (
    (0.290, 0.0, -math.pi / 2, 0.0),
    (0.0, 0.270, 0.0, -math.pi / 2),
    (0.0, 0.070, -math.pi / 2, 0.0),
    (0.302, 0.0, math.pi / 2, 0.0),
    (0.0, 0.0, -math.pi / 2, 0.0),
    (0.072, 0.0, 0.0, math.pi),
)
IRB120_LIMITS_DEG = ((-165, 165), (-110, 110), (-110, 70), (-160, 160), (-120, 120), (-400, 400))


def dh_placement(d: float, a: float, alpha: float, offset: float) -> pin.SE3:
    """The fixed part of one DH row: Rz(offset) · Tz(d) · Tx(a) · Rx(alpha)."""
    rz = pin.SE3(pin.utils.rotate("z", offset), np.zeros(3))
    tz = pin.SE3(np.eye(3), np.array([0.0, 0.0, d]))
    tx = pin.SE3(np.eye(3), np.array([a, 0.0, 0.0]))
    rx = pin.SE3(pin.utils.rotate("x", alpha), np.zeros(3))
    return rz * tz * tx * rx


def build_model(dh, limits_deg, tool: tuple[float, float], features: dict[str, np.ndarray]) -> pin.Model:
    """A serial revolute chain from a DH table; `tool` = (d7, a7); one operational frame per feature."""
    model = pin.Model()
    parent, placement = 0, pin.SE3.Identity()
    for i, (row, (lo, hi)) in enumerate(zip(dh, limits_deg), start=1):
        joint = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint_{i}",
                               np.full(1, 1e3), np.full(1, 10.0), np.full(1, math.radians(lo)),
                               np.full(1, math.radians(hi)))
        model.appendBodyToJoint(joint, pin.Inertia.Zero(), pin.SE3.Identity())
        parent, placement = joint, dh_placement(*row)
    flange = placement  # after joint 6's own row
    fixture = flange * pin.SE3(np.eye(3), np.array([tool[1], 0.0, tool[0]]))
    model.addFrame(pin.Frame("fixture", parent, fixture, pin.FrameType.OP_FRAME))
    for name, p in features.items():
        model.addFrame(pin.Frame(name, parent, fixture * pin.SE3(np.eye(3), np.asarray(p, float)),
                                 pin.FrameType.OP_FRAME))
    return model


class Chain:
    """Forward kinematics of the fixture frame and its feature points for one DH table, and the joints that
    reach a full pose."""

    def __init__(self, dh, tool: tuple[float, float], features: dict | None = None,
                 limits_deg=IRB120_LIMITS_DEG):
        features = features or {}
        self.model = build_model(dh, limits_deg, tool, features)
        self.data = self.model.createData()
        self.names = tuple(features)
        self.frame_ids = {n: self.model.getFrameId(n) for n in (*self.names, "fixture")}
        self.lower = self.model.lowerPositionLimit.copy()
        self.upper = self.model.upperPositionLimit.copy()

    def _update(self, q) -> None:
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))

    def placement(self, q, name: str = "fixture") -> pin.SE3:
        self._update(q)
        return self.data.oMf[self.frame_ids[name]].copy()

    def point(self, q, name: str) -> np.ndarray:
        self._update(q)
        return self.data.oMf[self.frame_ids[name]].translation.copy()

    def points(self, q, names=None) -> np.ndarray:
        """(n, 3) positions of the named features (default: all)."""
        self._update(q)
        return np.array([self.data.oMf[self.frame_ids[n]].translation for n in (names or self.names)])

    def within_limits(self, q) -> bool:
        q = np.asarray(q)
        return bool(np.all(q >= self.lower - 1e-9) and np.all(q <= self.upper + 1e-9))

    def reach_pose(self, target: pin.SE3, q0, name: str = "fixture", tol: float = 1e-10,
                   max_iter: int = 200) -> tuple[np.ndarray, bool]:
        """Joints putting frame `name` at a full pose (position and orientation), damped, within the limits,
        and whether they reach it within `tol` (the twist's norm); unreached: the last iterate."""
        q = np.array(q0, dtype=float)
        fid = self.frame_ids[name]
        for _ in range(max_iter):
            self._update(q)
            to_target = self.data.oMf[fid].actInv(target)
            err = pin.log6(to_target).vector
            if np.linalg.norm(err) < tol:
                return q, True
            pin.computeJointJacobians(self.model, self.data, q)
            J = pin.getFrameJacobian(self.model, self.data, fid, pin.ReferenceFrame.LOCAL)
            J = pin.Jlog6(to_target.inverse()) @ J
            dq = J.T @ np.linalg.solve(J @ J.T + 1e-8 * np.eye(6), err)
            q = np.clip(q + dq, self.lower, self.upper)
        return q, False
