"""A six-axis arm's geometry as a table of joints, nominal or calibrated, with its forward and inverse kinematics.

Each row is a revolute joint in standard DH with Hayati's extra turn for nearly parallel axes:

    T_i(q_i) = Rz(q_i + theta_i) · Tz(d_i) · Tx(a_i) · Rx(alpha_i) · Ry(beta_i)

and the flange is T_base_flange(q) = base · T_1(q_1) ··· T_6(q_6). With every beta zero and `base` the identity this
is the published table (geometry/ur.py for the UR5e, geometry/irb120.py for the IRB 120). Standard DH alone cannot
describe two parallel axes that are slightly out of parallel (the common normal jumps along the axis): the turn
beta about the new y axis can, and d of that row is then the one to hold at nominal (Hayati and Mirmirani, 1985).

Calibration (calibration/models/arm_kinematics.py) identifies the small deviations of every row from the published
one; the drivers' calibrated moves (`inverse`) and the URDF export read the same table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from geometry.irb120 import IRB120_DH, IRB120_LIMITS_DEG
from geometry.ur import JOINT_NAMES as UR_JOINT_NAMES
from geometry.ur import UR5E_DH, UR5E_LIMITS_RAD

ROW_PARAMETERS = ("theta", "d", "a", "alpha", "beta")  # the order of a row's deviations in a parameter vector
ARM_MODELS = ("ur5e", "irb120")
MAX_STEP_RAD = 0.2  # the largest joint step of one Gauss-Newton iteration of `inverse`


class IKFailed(ValueError):
    """The calibrated inverse kinematics found no joints for the pose (out of reach, or outside the limits)."""


@dataclass(frozen=True)
class Joint:
    """One row: lengths in m, angles in rad; limits (min, max) of the joint angle in rad."""

    name: str
    a: float
    d: float
    alpha: float
    theta: float = 0.0
    beta: float = 0.0
    limits: tuple[float, float] = (-2 * math.pi, 2 * math.pi)

    def values(self) -> np.ndarray:
        return np.array([getattr(self, p) for p in ROW_PARAMETERS])


@dataclass(frozen=True)
class KinematicTable:
    """An arm's joints, the base frame in the cell (T_cell_base) and nothing after the flange: tools and cameras are
    their own transforms (T_flange_tool)."""

    model: str
    joints: tuple[Joint, ...]
    base: np.ndarray = field(default_factory=lambda: np.eye(4))

    # -- forward -------------------------------------------------------------------------------------------------
    def forward(self, q) -> np.ndarray:
        """T_base_flange (4x4, in the cell frame) for joint angles q (rad)."""
        return self.forward_batch(np.asarray(q, dtype=float)[None, :])[0]

    def forward_batch(self, Q) -> np.ndarray:
        """(n, 4, 4) flange poses for (n, 6) joint angles, all at once (numpy broadcasting over the poses)."""
        Q = np.asarray(Q, dtype=float)
        if Q.ndim != 2 or Q.shape[1] != len(self.joints):
            raise ValueError(f"expected (n, {len(self.joints)}) joint angles, got shape {Q.shape}")
        T = np.broadcast_to(self.base, (len(Q), 4, 4)).copy()
        for i, j in enumerate(self.joints):
            T = T @ row_matrices(Q[:, i] + j.theta, j.d, j.a, j.alpha, j.beta)
        return T

    # -- deviations ----------------------------------------------------------------------------------------------
    def parameter_names(self) -> list[str]:
        """`<parameter>_<joint>` for every row parameter, in ROW_PARAMETERS order per joint."""
        return [f"{p}_{j.name}" for j in self.joints for p in ROW_PARAMETERS]

    def vector(self) -> np.ndarray:
        return np.concatenate([j.values() for j in self.joints])

    def with_vector(self, v) -> KinematicTable:
        v = np.asarray(v, dtype=float).reshape(len(self.joints), len(ROW_PARAMETERS))
        rows = tuple(replace(j, **dict(zip(ROW_PARAMETERS, map(float, values))))
                     for j, values in zip(self.joints, v))
        return replace(self, joints=rows)

    def within_limits(self, q) -> str | None:
        """What is wrong with q against the joint limits, or None."""
        for j, value in zip(self.joints, np.asarray(q, dtype=float)):
            if not math.isfinite(value):
                return f"joint {j.name}={value} is not a finite number"
            lo, hi = j.limits
            if not lo - 1e-9 <= value <= hi + 1e-9:
                return (f"joint {j.name}={math.degrees(value):.3f} deg is outside its limits "
                        f"[{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg")
        return None

    # -- inverse -------------------------------------------------------------------------------------------------
    def inverse(self, T_target: np.ndarray, q0, tolerance_m: float = 1e-9, max_iterations: int = 100) -> np.ndarray:
        """The joints near q0 that put the flange at T_target (4x4, cell frame): Gauss-Newton on the pose error from
        q0 (a nominal solution is an excellent start: the tables differ by millimetres). IKFailed if it does not
        converge or leaves the joint limits."""
        q = np.array(q0, dtype=float)
        T_target = np.asarray(T_target, dtype=float)
        for _ in range(max_iterations):
            error = pose_error(self.forward(q), T_target)
            if np.linalg.norm(error[:3]) < tolerance_m and np.linalg.norm(error[3:]) < tolerance_m:
                problem = self.within_limits(q)
                if problem:
                    raise IKFailed(f"the calibrated joints for this pose leave the limits: {problem}")
                return q
            J = self._jacobian(q)
            step = np.linalg.lstsq(J, error, rcond=None)[0]
            # from a start far off (no nominal solution at hand) a full step overshoots and diverges: at most
            # MAX_STEP_RAD per joint, which leaves the last steps near a solution whole
            q = q + step * min(1.0, MAX_STEP_RAD / max(float(np.max(np.abs(step))), 1e-300))
        raise IKFailed(f"the calibrated inverse kinematics did not converge near q0 (pose error "
                       f"{np.linalg.norm(error[:3]) * 1e3:.4f} mm, {math.degrees(np.linalg.norm(error[3:])):.5f} deg): "
                       "the pose is out of reach or at a singularity")

    def _jacobian(self, q, h: float = 1e-7) -> np.ndarray:
        """d(pose error)/dq by central differences: (6, n) with the translation rows first."""
        Q = np.repeat(np.asarray(q, dtype=float)[None, :], 2 * len(q), axis=0)
        for i in range(len(q)):
            Q[2 * i, i] += h
            Q[2 * i + 1, i] -= h
        T = self.forward_batch(Q)
        return np.column_stack([pose_error(T[2 * i + 1], T[2 * i]) / (2 * h) for i in range(len(q))])

    # -- stored form ---------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Lengths in mm, angles in deg (what a person reads, and the stored `arm` calibration's table)."""
        return {"model": self.model, "base": matrix_rows(self.base),
                "joints": [{"name": j.name, "a_mm": j.a * 1e3, "d_mm": j.d * 1e3, "alpha_deg": math.degrees(j.alpha),
                            "theta_deg": math.degrees(j.theta), "beta_deg": math.degrees(j.beta),
                            "limits_deg": [math.degrees(j.limits[0]), math.degrees(j.limits[1])]}
                           for j in self.joints]}

    @classmethod
    def from_dict(cls, d: dict) -> KinematicTable:
        try:
            joints = tuple(Joint(str(j["name"]), float(j["a_mm"]) * 1e-3, float(j["d_mm"]) * 1e-3,
                                 math.radians(float(j["alpha_deg"])), math.radians(float(j["theta_deg"])),
                                 math.radians(float(j.get("beta_deg", 0.0))),
                                 tuple(math.radians(float(v)) for v in j["limits_deg"]))
                           for j in d["joints"])
            base = np.asarray(d.get("base", np.eye(4)), dtype=float)
            model = str(d["model"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"kinematic table: {exc!r}; expected model, base (4x4) and joints with name, a_mm, d_mm, "
                             "alpha_deg, theta_deg, beta_deg, limits_deg") from None
        if base.shape != (4, 4) or not np.all(np.isfinite(base)):
            raise ValueError(f"kinematic table: base must be a finite 4x4 matrix, got shape {base.shape}")
        if len(joints) != 6:
            raise ValueError(f"kinematic table: expected 6 joints, got {len(joints)}")
        return cls(model, joints, base)


def row_matrices(theta, d: float, a: float, alpha: float, beta: float) -> np.ndarray:
    """(n, 4, 4) of Rz(theta) · Tz(d) · Tx(a) · Rx(alpha) · Ry(beta) for n angles theta."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
    # the fixed part Tz(d) Tx(a) Rx(alpha) Ry(beta), then turned by Rz(theta)
    F = np.array([[cb, 0.0, sb, a],
                  [sa * sb, ca, -sa * cb, 0.0],
                  [-ca * sb, sa, ca * cb, d],
                  [0.0, 0.0, 0.0, 1.0]])
    M = np.zeros((len(ct), 4, 4))
    M[:, 0, :] = ct[:, None] * F[0] - st[:, None] * F[1]
    M[:, 1, :] = st[:, None] * F[0] + ct[:, None] * F[1]
    M[:, 2, :] = F[2]
    M[:, 3, :] = F[3]
    return M


def pose_error(T_from: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """(dx, dy, dz, rx, ry, rz): the translation and the small rotation (rotation vector, cell axes) from T_from to
    T_to."""
    R = T_to[:3, :3] @ T_from[:3, :3].T
    angle_axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    s = np.linalg.norm(angle_axis)
    c = (np.trace(R) - 1.0) / 2.0
    rotation = angle_axis * (math.atan2(s, c) / s) if s > 1e-12 else angle_axis
    return np.concatenate([T_to[:3, 3] - T_from[:3, 3], rotation])


def matrix_rows(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(T, dtype=float)]


def nominal_table(model: str) -> KinematicTable:
    """The published table of `model` ("ur5e" or "irb120"), with its joint limits."""
    if model == "ur5e":
        return KinematicTable("ur5e", tuple(Joint(name, a, d, alpha, 0.0, 0.0, limits) for name, (a, d, alpha), limits
                                            in zip(UR_JOINT_NAMES, UR5E_DH, UR5E_LIMITS_RAD)))
    if model == "irb120":
        return KinematicTable("irb120", tuple(
            Joint(f"joint_{i}", a, d, alpha, offset, 0.0, (math.radians(lo), math.radians(hi)))
            for i, ((d, a, alpha, offset), (lo, hi)) in enumerate(zip(IRB120_DH, IRB120_LIMITS_DEG), start=1)))
    raise ValueError(f"arm model {model!r}: expected one of {', '.join(ARM_MODELS)}")
