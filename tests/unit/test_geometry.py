"""The shared math below drivers/ and calibration/ (geometry/): round trips and known values."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from geometry.irb120 import IRB120_DH, Chain
from geometry.orientation import alpha_of, quaternion_wxyz, rotation_from_wxyz, tilt_of, tool_down
from geometry.projection import OVERHEAD, camera_direction, face_footprint, pinhole, unit_direction
from geometry.transforms import inverse, look_at, matrix_of, pose_matrix, rotation, view_matrix

from drivers.interfaces import Pose

RNG = np.random.default_rng(12)


def test_pose_matrix_known_turn_and_inverse_round_trip():
    T = pose_matrix([0.0, 0.0, math.pi / 2], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(T @ [1.0, 0.0, 0.0, 1.0], [1.0, 3.0, 3.0, 1.0], atol=1e-15)  # x turns to y
    for _ in range(20):
        T = pose_matrix(RNG.uniform(-2, 2, 3), RNG.uniform(-1, 1, 3))
        np.testing.assert_allclose(inverse(T) @ T, np.eye(4), atol=1e-14)
        np.testing.assert_allclose(T @ inverse(T), np.eye(4), atol=1e-14)


def test_rotation_about_an_axis_is_the_rotation_vector():
    for _ in range(20):
        axis, angle = RNG.normal(size=3), RNG.uniform(-3, 3)
        expected = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
        np.testing.assert_allclose(rotation(axis * 7.0, angle), expected, atol=1e-14)  # any axis length


def test_tool_pose_to_matrix_and_back():
    down = Pose(0.1, -0.2, 0.3, alpha=0.4, orientation=quaternion_wxyz(tool_down(0.4)))
    T = matrix_of(down)
    np.testing.assert_allclose(T[:3, 3], [0.1, -0.2, 0.3])
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, -1.0], atol=1e-15)  # the tool points down
    R = Rotation.from_matrix(T[:3, :3])
    assert alpha_of(R) == pytest.approx(0.4) and tilt_of(R) == pytest.approx(0.0, abs=1e-7)
    assert np.allclose(np.abs(quaternion_wxyz(R)), np.abs(down.orientation))
    # without an orientation: a turn by alpha about the vertical
    np.testing.assert_allclose(matrix_of(Pose(0.0, 0.0, 0.0, alpha=math.pi / 2))[:3, 0], [0.0, 1.0, 0.0], atol=1e-15)
    with pytest.raises(ValueError, match="unit length"):
        rotation_from_wxyz((1.0, 1.0, 0.0, 0.0))


def test_look_at_puts_the_target_on_the_optical_axis():
    position, target = np.array([0.5, -0.3, 0.8]), np.array([0.0, 0.25, 0.0])
    V = look_at(position, target)
    p = V @ np.r_[target, 1.0]
    np.testing.assert_allclose(p[:3], [0.0, 0.0, np.linalg.norm(target - position)], atol=1e-15)
    np.testing.assert_allclose(V[:3, :3] @ V[:3, :3].T, np.eye(3), atol=1e-15)
    assert np.linalg.det(V[:3, :3]) == pytest.approx(1.0)
    z = (target - position) / np.linalg.norm(target - position)
    assert V[0, :3] @ [0.0, 1.0, 0.0] == pytest.approx(math.sqrt(1 - z[1] ** 2))  # image x as near `right` as can be
    # looking straight along `right`: still a proper view matrix
    V = look_at([0.0, -1.0, 0.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose((V @ [0.0, 0.0, 0.0, 1.0])[:3], [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(view_matrix(V[:3, :3], [0.0, -1.0, 0.0]), V)


def test_directions():
    np.testing.assert_allclose(unit_direction(0, 0), [1, 0, 0], atol=1e-16)
    np.testing.assert_allclose(unit_direction(90, 0), [0, 1, 0], atol=1e-16)
    np.testing.assert_allclose(unit_direction(33, 90), [0, 0, 1], atol=1e-16)
    side = camera_direction(30.0, 15.0)
    np.testing.assert_array_equal(side, unit_direction(30.0, 15.0))
    for turn in (10.0, 45.0, 90.0):
        top = camera_direction(30.0, 15.0, turn)
        assert np.linalg.norm(top) == pytest.approx(1.0)
        assert math.degrees(math.acos(side @ top)) == pytest.approx(turn)  # the inter-camera angle
    # turned all the way: in the plane of the side camera and OVERHEAD, perpendicular to the side camera
    top = camera_direction(30.0, 15.0, 90.0)
    assert np.cross(side, OVERHEAD) @ top == pytest.approx(0.0, abs=1e-15) and top @ OVERHEAD > 0


def test_pinhole_known_pixels():
    uv = pinhole(np.array([[0.1, -0.2, 2.0], [0.0, 0.0, 5.0]]), 1000.0, 320.0, 240.0)
    np.testing.assert_allclose(uv, [[370.0, 140.0], [320.0, 240.0]])


def test_face_footprint():
    square = np.array([[-0.1, -0.1, 1.0], [-0.1, 0.1, 1.0], [0.1, 0.1, 1.0], [0.1, -0.1, 1.0]])
    assert np.cross(square[1] - square[0], square[2] - square[0]) @ square[0] < 0  # faces the camera
    uv, box = face_footprint(square, 100.0, 50.0, 40.0, 100, 80)
    np.testing.assert_allclose(uv, [[40, 30], [40, 50], [60, 50], [60, 30]])
    assert box == (40, 30, 61, 51)
    assert face_footprint(square[::-1], 100.0, 50.0, 40.0, 100, 80) is None  # its back
    assert face_footprint(square - [0, 0, 1.0], 100.0, 50.0, 40.0, 100, 80) is None  # behind the camera
    assert face_footprint(square + [5.0, 0, 0], 100.0, 50.0, 40.0, 100, 80) is None  # outside the image
    _, box = face_footprint(square * [10, 10, 1], 100.0, 50.0, 40.0, 100, 80)
    assert box == (0, 0, 100, 80)  # clipped to the image


def _dh_numpy(dh, q, tool):
    """Standard DH with plain 4x4 products: the independent check of the pinocchio chain."""
    def rz(t):
        return pose_matrix([0, 0, t])

    def rx(t):
        return pose_matrix([t, 0, 0])

    T = np.eye(4)
    for (d, a, alpha, offset), qi in zip(dh, q):
        T = T @ rz(qi + offset) @ pose_matrix(translation=(a, 0, d)) @ rx(alpha)
    return T @ pose_matrix(translation=(tool[1], 0.0, tool[0]))


def test_irb120_chain_is_standard_dh_and_reaches_poses():
    tool = (0.04, 0.01)
    chain = Chain(IRB120_DH, tool, {"mark": (0.01, -0.02, 0.003)})
    for _ in range(10):
        q = RNG.uniform(-1, 1, 6)
        T = _dh_numpy(IRB120_DH, q, tool)
        m = chain.placement(q)
        np.testing.assert_allclose(m.rotation, T[:3, :3], atol=1e-12)
        np.testing.assert_allclose(m.translation, T[:3, 3], atol=1e-12)
        np.testing.assert_allclose(chain.point(q, "mark"), (T @ [0.01, -0.02, 0.003, 1.0])[:3], atol=1e-12)
    # the catalogue arm at zero: wrist centre 0.302 + 0.070 m ahead at the height of 0.290 + 0.270 m
    wrist = _dh_numpy(IRB120_DH[:5], np.zeros(5), (0.0, 0.0))[:3, 3]
    np.testing.assert_allclose(wrist, [0.302, 0.0, 0.290 + 0.270 + 0.070], atol=1e-12)
    q0 = np.radians([0, 10, 10, 0, 60, 0])
    goal = chain.placement(q0 + 0.1)
    q, reached = chain.reach_pose(goal, q0)
    assert reached and chain.within_limits(q)
    assert np.linalg.norm(pin.log6(chain.placement(q).actInv(goal)).vector) < 1e-10
    far = pin.SE3(goal.rotation, goal.translation + [2.0, 0.0, 0.0])
    q, reached = chain.reach_pose(far, q0)
    assert not reached and chain.within_limits(q)
