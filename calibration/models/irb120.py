"""What the CSM estimator knows about the ABB IRB 120 (seed 002 Table I): the catalogue DH table
(geometry.irb120) and the fixture drawing, never the robot's true (hidden) geometry.

`f(θ)` of seed eq. 5 is `Kinematics.points(q)`; the numerical inverse kinematics of eq. 11 is
`solve_point` (damped least squares with the pinocchio Jacobian, inside the joint limits). The fixture's
features are points in the seventh DH frame, which the row (d7, a7) places on the flange.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from geometry.irb120 import IRB120_DH, Chain


@dataclass(frozen=True)
class Fixture:
    """The end-effector fixture (seed Fig. 3): feature centres in the seventh frame (m)."""

    tool: tuple[float, float]  # (d7, a7) m
    features: dict[str, tuple[float, float, float]]


class Kinematics(Chain):
    """Forward kinematics of feature points and numerical IK on the nominal chain."""

    @classmethod
    def nominal(cls, fixture: Fixture) -> Kinematics:
        return cls(IRB120_DH, fixture.tool, fixture.features)

    def solve_point(self, name: str, target, q0, active=(0, 1, 2, 3, 4, 5), tol: float = 1e-9,
                    max_iter: int = 100, damping: float = 1e-6) -> np.ndarray:
        """Joints putting feature `name` at `target` (eq. 11), moving only the `active` joints and as little
        as possible from q0: damped Gauss-Newton steps dθ = (JᵀJ + λI)⁻¹ Jᵀ dP, clipped to the limits."""
        q = np.array(q0, dtype=float)
        active = list(active)
        fid = self.frame_ids[name]
        target = np.asarray(target, dtype=float)
        for _ in range(max_iter):
            self._update(q)
            dp = target - self.data.oMf[fid].translation
            if np.linalg.norm(dp) < tol:
                break
            pin.computeJointJacobians(self.model, self.data, q)
            J = pin.getFrameJacobian(self.model, self.data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3, active]
            # the damping grows near singularities (small singular values) and keeps steps bounded
            lam = damping + 1e-4 * max(0.0, 1e-2 - np.linalg.svd(J, compute_uv=False).min())
            dq = J.T @ np.linalg.solve(J @ J.T + lam * np.eye(3), dp) if len(active) > 3 else \
                np.linalg.solve(J.T @ J + lam * np.eye(len(active)), J.T @ dp)
            q[active] = np.clip(q[active] + dq, self.lower[active], self.upper[active])
        return q

    def solve_pose(self, target: pin.SE3, q0, name: str = "fixture", tol: float = 1e-10,
                   max_iter: int = 200) -> np.ndarray:
        """Joints putting frame `name` at a full pose, damped, within limits (unreached: the last iterate)."""
        return self.reach_pose(target, q0, name, tol, max_iter)[0]
