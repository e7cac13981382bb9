"""geometry/ur.py: the UR5e's nominal kinematics, and the simulator's mounting of it in the micro cell."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from geometry import ur

from drivers.interfaces import Pose
from drivers.sim.servers.ur.kinematics import BRANCH, UrKinematics

# A URSim 5.8 UR5e's first robot state message (a public capture of its primary interface): joint data q and the
# cartesian info's TCP pose (zero TCP offset) of the same message.
URSIM_Q = (-1.6006999999999998, -1.7271, -2.2029999999999994, -0.8079999999999998, 1.5951, -0.030999999999999694)
URSIM_TCP = (-0.14396865671352163, -0.43562006080319216, 0.2020300254283846,
             -0.0012213596815925638, 3.1162765284819756, 0.038891915636886834)


def rotvec(R) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def test_forward_kinematics_gives_what_a_ur5e_controller_reports():
    """URSim computes with alpha = +-1.570796327 (pi/2 to 9 decimals, as its kinematics package reports it): with
    that, forward kinematics is its TCP pose to 1e-15; with the published pi/2, to 1e-9."""
    T = ur.forward(URSIM_Q)
    assert T[:3, 3] == pytest.approx(URSIM_TCP[:3], abs=1e-10)
    assert rotvec(T[:3, :3]) == pytest.approx(URSIM_TCP[3:], abs=1e-9)
    T = ur.forward(URSIM_Q, [(a, d, round(alpha, 9)) for a, d, alpha in ur.UR5E_DH])
    assert T[:3, 3] == pytest.approx(URSIM_TCP[:3], abs=1e-15)
    assert rotvec(T[:3, :3]) == pytest.approx(URSIM_TCP[3:], abs=1e-14)
    assert ur.branch_of(URSIM_Q) == BRANCH  # the simulator holds the branch URSim starts in


def test_dh_table_is_ur_s_published_ur5e_row():
    assert ur.UR5E_DH == (
        (0.0, 0.1625, math.pi / 2), (-0.425, 0.0, 0.0), (-0.3922, 0.0, 0.0),
        (0.0, 0.1333, math.pi / 2), (0.0, 0.0997, -math.pi / 2), (0.0, 0.0996, 0.0))


def test_numpy_forward_kinematics_equals_pinocchio_s():
    pin = pytest.importorskip("pinocchio")
    model = ur.pinocchio_model()
    data = model.createData()
    frame = model.getFrameId("tool0")
    rng = np.random.default_rng(3)
    for q in rng.uniform(-2 * math.pi, 2 * math.pi, (200, 6)):
        pin.framesForwardKinematics(model, data, q)
        assert np.abs(data.oMf[frame].homogeneous - ur.forward(q)).max() < 1e-12


def test_every_branch_inverts_forward_kinematics():
    rng = np.random.default_rng(5)
    checked = 0
    for q in rng.uniform(-math.pi, math.pi, (300, 6)):
        T = ur.forward(q)
        branches = 0
        for signs in itertools.product((1, -1), repeat=3):
            try:
                got = ur.inverse(T, ur.Branch(*signs))
            except ur.Unreachable:
                continue
            assert np.abs(ur.forward(got) - T).max() < 1e-9
            branches += 1
        try:
            own = ur.branch_of(q)
        except ur.Unreachable:
            continue  # within 1e-9 of a singular pose
        assert np.abs(ur.inverse(T, own, near=q) - q).max() < 1e-8  # q itself, whole turns included
        checked += branches
    assert checked > 1000


def test_unreachable_poses_say_why():
    far = np.eye(4)
    far[:3, 3] = (2.0, 0.0, 0.0)
    with pytest.raises(ur.Unreachable, match="out of reach"):
        ur.inverse(far)
    near_axis = np.eye(4)
    near_axis[:3, 3] = (0.01, 0.01, 0.3)
    with pytest.raises(ur.Unreachable, match="shoulder offset"):
        ur.inverse(near_axis)


# --- the simulator's UR5e in the micro cell ------------------------------------------------------------------

BOX = {"x": (-0.010, 0.160), "y": (-0.010, 0.110), "z": (-0.005, 0.040)}  # config/sim-microcell.yaml's arm box


def test_micro_cell_poses_have_ur5e_angles_whose_forward_kinematics_is_the_pose():
    k = UrKinematics()
    for x, y, z, alpha_deg in itertools.product(np.linspace(*BOX["x"], 5), np.linspace(*BOX["y"], 5),
                                                np.linspace(*BOX["z"], 3), (-360, -200, -45, 0, 90, 350, 360)):
        flange = Pose(x, y, z, math.radians(alpha_deg))
        q = k.joints(flange)
        T = k.forward(q)
        assert T[:3, 3] == pytest.approx((x, y, z), abs=1e-12)
        assert np.abs(T[:3, :3] - k.flange_matrix(flange)[:3, :3]).max() < 1e-12
        assert q[4] == pytest.approx(math.pi / 2, abs=1e-9)  # tool vertical: wrist 2 square, far from its singularity
        back = k.flange_of_joints(q)  # moveJ to q: the same flange pose, the same turn of alpha
        assert math.dist(back.xyz, flange.xyz) < 1e-12 and back.alpha == pytest.approx(flange.alpha, abs=1e-12)


def test_the_reference_pose_pins_the_mounting():
    """The default mounting, pinned: the flange at the micro cell's (75, 50, 17.5) mm, alpha 0."""
    q = UrKinematics().joints(Pose(0.075, 0.050, 0.0175, 0.0))
    assert np.degrees(q) == pytest.approx(
        (-90.87038845, -127.39658350, -130.19711691, -12.40629959, 90.0, -0.87038845), abs=1e-6)


def test_joint_angles_are_continuous_along_a_move():
    """A straight move (x, y, z and alpha at once, as the world interpolates it) in 2000 steps: no angle jumps,
    and wrist 3 turns against alpha (a turn about the vertical is a turn about the downward tool axis)."""
    k = UrKinematics()
    start, end = np.array([-0.010, 0.110, 0.040, math.radians(-350)]), np.array([0.160, -0.010, -0.005, 6.0])
    path = np.array([k.joints(Pose(*(start + f * (end - start)))) for f in np.linspace(0, 1, 2001)])
    assert np.abs(np.diff(path, axis=0)).max() < 0.01
    q1_turn = path[-1, 0] - path[0, 0]
    assert path[-1, 5] - path[0, 5] == pytest.approx(-(end[3] - start[3]) + q1_turn, abs=1e-9)


def test_joint_targets_the_four_axis_arm_cannot_hold_are_refused():
    k = UrKinematics()
    q = list(k.joints(Pose(0.05, 0.04, 0.01, 0.3)))
    tilted = q[:3] + [q[3] + 0.1] + q[4:]
    with pytest.raises(ValueError, match="tilt the tool"):
        k.flange_of_joints(tilted)
    other_branch = ur.inverse(k.mount_inv @ k.forward(q), ur.Branch(1, -1, 1))
    with pytest.raises(ValueError, match="not on this simulated UR's branch"):
        k.flange_of_joints(other_branch)
    turned = q[:5] + [q[5] + 2 * math.pi]  # wrist 3 one turn further: the same flange, alpha one turn less
    assert k.flange_of_joints(turned).alpha == pytest.approx(0.3 - 2 * math.pi, abs=1e-12)
    with pytest.raises(ur.Unreachable, match="out of the simulated UR5e's reach"):
        k.joints(Pose(1.5, 0.0, 0.0, 0.0))
