"""A Universal Robots arm's nominal kinematics (UR5e): its DH table, forward kinematics and the closed-form
inverse kinematics on one chosen branch.

Standard DH, as UR publishes it: T_i = Rz(q_i) · Tz(d_i) · Tx(a_i) · Rx(alpha_i), every theta offset zero.
UR5E_DH is the UR5e row of Universal Robots' "DH parameters for calculations of kinematics and dynamics"
(universal-robots.com, support article 45257, valid for e-Series software 5.1 and later):

| joint | a (m) | d (m) | alpha (rad) |
|---|---|---|---|
| 1 base | 0 | 0.1625 | pi/2 |
| 2 shoulder | -0.425 | 0 | 0 |
| 3 elbow | -0.3922 | 0 | 0 |
| 4 wrist 1 | 0 | 0.1333 | pi/2 |
| 5 wrist 2 | 0 | 0.0997 | -pi/2 |
| 6 wrist 3 | 0 | 0.0996 | 0 |

A URSim 5.8 UR5e reports these same values in its primary interface's kinematics and configuration
packages (alpha rounded to 1.570796327, which it also computes with: its TCP pose for a reported q is this
forward kinematics with that rounding to 1e-15 m, and with pi/2 to 1e-10 m). `forward(q)` is the flange
(tool0) in the base frame, as a UR controller reports actual_TCP_pose for a zero TCP offset.

The inverse is the usual closed form for a UR's geometry (three parallel middle axes, offset wrist):
eight solutions in general, one per `Branch` (shoulder, elbow, wrist sign). A caller that holds one branch
and unwraps each angle near a reference configuration (`inverse(..., near=q_ref)`) gets joint angles that
are continuous along any path that keeps clear of the branch's singular poses. Only numpy here (fast to
import in a simulator process); `pinocchio_model()` builds the same chain in pinocchio (as
geometry/irb120.py does for the IRB 120), which the tests use as an independent forward kinematics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# (a m, d m, alpha rad) per joint, theta offsets all 0: the UR5e row of UR's published DH table (see above)
UR5E_DH: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.1625, math.pi / 2),
    (-0.425, 0.0, 0.0),
    (-0.3922, 0.0, 0.0),
    (0.0, 0.1333, math.pi / 2),
    (0.0, 0.0997, -math.pi / 2),
    (0.0, 0.0996, 0.0),
)
# every UR5e joint turns +-360 degrees (UR5e technical specifications)
UR5E_LIMITS_RAD: tuple[tuple[float, float], ...] = ((-2 * math.pi, 2 * math.pi),) * 6
JOINT_NAMES = ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
SINGULAR_TOLERANCE = 1e-9


class Unreachable(ValueError):
    """No joint angles of the asked branch reach the pose (out of reach, or at a singular pose)."""


@dataclass(frozen=True)
class Branch:
    """One of the eight inverse-kinematics solutions, by the sign each closed-form step takes.

    shoulder: +1 or -1, the sign before acos(d4 / r) in q1 (which side of the base the arm reaches from);
    elbow: +1 or -1, the sign of q3 (for a UR's negative a2, a3: -1 puts the elbow above the line from the
    shoulder to the wrist when the arm reaches forward, the "elbow up" pose of UR's own programs);
    wrist: +1 or -1, the sign of q5 (wrist 2)."""

    shoulder: int = -1
    elbow: int = -1
    wrist: int = 1

    def __post_init__(self):
        if {self.shoulder, self.elbow, self.wrist} - {1, -1}:
            raise ValueError(f"branch signs must be +1 or -1, got {self}")


def dh_matrix(q: float, a: float, d: float, alpha: float) -> np.ndarray:
    """Rz(q) · Tz(d) · Tx(a) · Rx(alpha) as a 4x4."""
    cq, sq, ca, sa = math.cos(q), math.sin(q), math.cos(alpha), math.sin(alpha)
    return np.array([[cq, -sq * ca, sq * sa, a * cq],
                     [sq, cq * ca, -cq * sa, a * sq],
                     [0.0, sa, ca, d],
                     [0.0, 0.0, 0.0, 1.0]])


def forward(q, dh=UR5E_DH) -> np.ndarray:
    """The flange (tool0) in the base frame for joint angles q (rad), 4x4."""
    values = [float(v) for v in q]
    if len(values) != 6:
        raise ValueError(f"expected 6 joint angles, got {len(values)}")
    T = np.eye(4)
    for value, row in zip(values, dh):
        T = T @ dh_matrix(value, *row)
    return T


def _inverse_rigid(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _acos(value: float, what: str) -> float:
    if abs(value) > 1.0 + 1e-12:
        raise Unreachable(f"{what}: cos = {value:.6f} is outside [-1, 1] (the pose is out of reach)")
    return math.acos(max(-1.0, min(1.0, value)))


def inverse(T, branch: Branch = Branch(), dh=UR5E_DH, near=None) -> np.ndarray:
    """Joint angles (rad) of `branch` that put the flange at T (4x4, base frame); Unreachable if none do.

    Each angle comes from atan2/acos in (-pi, pi]; with `near` (six angles) each is moved by whole turns to
    the value nearest near[i], so a caller can follow a path without jumps of 2 pi."""
    T = np.asarray(T, dtype=float)
    (_, d1, _), (a2, _, _), (a3, _, _), (_, d4, _), (_, d5, _), (_, d6, _) = dh
    R, p = T[:3, :3], T[:3, 3]
    p05 = p - d6 * R[:, 2]  # the wrist 2 centre
    r = math.hypot(p05[0], p05[1])
    if r < abs(d4) + SINGULAR_TOLERANCE:
        raise Unreachable(f"the wrist centre is {r * 1e3:.1f} mm from the base axis, within the shoulder offset "
                          f"d4 = {d4 * 1e3:.1f} mm (no shoulder angle reaches it)")
    q1 = math.atan2(p05[1], p05[0]) + branch.shoulder * math.acos(d4 / r) + math.pi / 2
    s1, c1 = math.sin(q1), math.cos(q1)
    q5 = branch.wrist * _acos((p[0] * s1 - p[1] * c1 - d4) / d6, "wrist 2")
    s5 = math.sin(q5)
    if abs(s5) < SINGULAR_TOLERANCE:
        raise Unreachable("wrist singularity: the tool axis is parallel to the shoulder axis (q5 = 0 or pi)")
    q6 = math.atan2(-(R[0, 1] * s1 - R[1, 1] * c1) / s5, (R[0, 0] * s1 - R[1, 0] * c1) / s5)
    T14 = _inverse_rigid(dh_matrix(q1, *dh[0])) @ T @ _inverse_rigid(dh_matrix(q5, *dh[4]) @ dh_matrix(q6, *dh[5]))
    p13 = T14[:3, 3] - d4 * T14[:3, 1]  # the elbow-to-wrist-1 segment ends here, in frame 1
    n = math.hypot(p13[0], p13[1])
    q3 = branch.elbow * _acos((n * n - a2 * a2 - a3 * a3) / (2.0 * a2 * a3), "elbow")
    if abs(math.sin(q3)) < SINGULAR_TOLERANCE:
        raise Unreachable("elbow singularity: the arm is fully stretched or folded")
    q2 = -math.atan2(p13[1], -p13[0]) + math.asin(max(-1.0, min(1.0, a3 * math.sin(q3) / n)))
    T13 = dh_matrix(q2, *dh[1]) @ dh_matrix(q3, *dh[2])
    T34 = _inverse_rigid(T13) @ T14
    q4 = math.atan2(T34[1, 0], T34[0, 0])
    q = np.array([q1, q2, q3, q4, q5, q6])
    q = np.arctan2(np.sin(q), np.cos(q))
    if near is not None:
        ref = np.asarray(near, dtype=float)
        q = ref + np.remainder(q - ref + math.pi, 2 * math.pi) - math.pi
    return q


def branch_of(q, dh=UR5E_DH) -> Branch:
    """The branch a configuration q lies on (the one whose inverse gives q back, up to whole turns)."""
    T = forward(q, dh)
    for branch in (Branch(s, e, w) for s in (1, -1) for e in (-1, 1) for w in (1, -1)):
        try:
            got = inverse(T, branch, dh, near=q)
        except Unreachable:
            continue
        if np.max(np.abs(got - np.asarray(q, dtype=float))) < 1e-6:
            return branch
    raise Unreachable(f"q = {list(q)} is at a singular pose: no single branch holds it")


def pinocchio_model(dh=UR5E_DH, limits=UR5E_LIMITS_RAD):
    """The same chain as a pinocchio Model (revolute z joints, DH placements); frame 'tool0' is the flange."""
    import pinocchio as pin  # only here: a simulator that never asks for it starts faster

    def placement(a, d, alpha):
        return (pin.SE3(np.eye(3), np.array([0.0, 0.0, d])) * pin.SE3(np.eye(3), np.array([a, 0.0, 0.0]))
                * pin.SE3(pin.utils.rotate("x", alpha), np.zeros(3)))

    model = pin.Model()
    parent, offset = 0, pin.SE3.Identity()
    for i, (row, (lo, hi)) in enumerate(zip(dh, limits)):
        joint = model.addJoint(parent, pin.JointModelRZ(), offset, JOINT_NAMES[i], np.full(1, 150.0),
                               np.full(1, math.pi), np.full(1, lo), np.full(1, hi))
        model.appendBodyToJoint(joint, pin.Inertia.Zero(), pin.SE3.Identity())
        parent, offset = joint, placement(*row)
    model.addFrame(pin.Frame("tool0", parent, offset, pin.FrameType.OP_FRAME))
    return model
