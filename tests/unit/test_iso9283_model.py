"""ISO 9283 math (calibration/models/iso9283.py) against small examples computed by hand: the cube's five poses
(§6.8), pose accuracy (§7.2.1) and pose repeatability (§7.2.2), with cases whose RP is known in closed form."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.errors import CalibrationInputError
from calibration.models.iso9283 import PLANES, cube_poses, pose_accuracy, pose_repeatability

DOWN = Rotation.from_euler("xyz", (180, 0, 90), degrees=True).as_matrix()  # a tool pointing straight down


def _T(position, R=None) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = position
    return T


def _rot(axis: str, angle: float) -> np.ndarray:
    return Rotation.from_euler(axis, angle).as_matrix()


# -- §6.8: the cube's poses ----------------------------------------------------------------------------------------
def test_the_five_poses_of_a_100_mm_cube_on_its_x_plus_plane():
    """Edge 100 mm: the plane through the bottom edge along x at -y and the top one at +y is 100 by 141.4 mm, its
    diagonals 173.2 mm; 10 % in from a corner is 0.8 of the way from the centre: 40 mm along each axis."""
    centre = np.array([-0.55, -0.13, 0.415])
    poses = cube_poses(centre, 0.1, "x+", DOWN)
    assert list(poses) == ["P1", "P2", "P3", "P4", "P5"]
    offsets = {k: np.round((T[:3, 3] - centre) * 1e3, 9) for k, T in poses.items()}
    assert offsets["P1"].tolist() == [0, 0, 0]
    assert offsets["P2"].tolist() == [-40, -40, -40]
    assert offsets["P3"].tolist() == [40, -40, -40]
    assert offsets["P4"].tolist() == [40, 40, 40]
    assert offsets["P5"].tolist() == [-40, 40, 40]
    for T in poses.values():  # one orientation for all
        assert np.allclose(T[:3, :3], DOWN) and np.allclose(T[3], [0, 0, 0, 1])


def test_each_outer_pose_is_a_tenth_of_the_diagonal_in_from_its_corner_on_the_plane():
    centre, edge = np.array([0.1, 0.2, 0.3]), 0.2
    diagonal = edge * math.sqrt(3)
    corners = {  # the x- plane: edges along x, the bottom one at +y, the top one at -y
        "P2": centre + [-0.1, 0.1, -0.1], "P3": centre + [0.1, 0.1, -0.1],
        "P4": centre + [0.1, -0.1, 0.1], "P5": centre + [-0.1, -0.1, 0.1]}
    poses = cube_poses(centre, edge, "x-")
    for name, corner in corners.items():
        p = poses[name][:3, 3]
        assert np.linalg.norm(p - corner) == pytest.approx(0.1 * diagonal)
        assert np.linalg.norm(p - centre) == pytest.approx(0.4 * diagonal)
        normal = np.cross([1.0, 0.0, 0.0], [0.0, -1.0, 1.0])  # the plane holds x and its rising diagonal
        assert (p - centre) @ normal == pytest.approx(0.0, abs=1e-15)
    # P2, P1, P4 on one diagonal, P3, P1, P5 on the other
    for a, b in (("P2", "P4"), ("P3", "P5")):
        assert poses[a][:3, 3] + poses[b][:3, 3] == pytest.approx(2 * centre)


@pytest.mark.parametrize("plane", sorted(PLANES))
def test_every_plane_is_a_diagonal_plane_of_the_cube(plane):
    poses = cube_poses(np.zeros(3), 1.0, plane)
    offsets = np.array([T[:3, 3] for T in poses.values()])[1:]
    assert np.allclose(np.abs(offsets), 0.4)  # 0.8 of the way to a cube corner (+/-0.5 on each axis)
    assert np.linalg.matrix_rank(offsets) == 2  # coplanar, with the centre


def test_the_cube_refuses_what_it_cannot_build():
    with pytest.raises(CalibrationInputError, match="plane 'xy': allowed: x\\+, x-"):
        cube_poses(np.zeros(3), 0.1, "xy")
    with pytest.raises(CalibrationInputError, match="cube edge -0.1: allowed: a positive length"):
        cube_poses(np.zeros(3), -0.1)
    with pytest.raises(CalibrationInputError, match="orientation"):
        cube_poses(np.zeros(3), 0.1, orientation=2 * np.eye(3))


# -- §7.2.1: pose accuracy -----------------------------------------------------------------------------------------
def test_accuracy_is_the_barycentre_against_the_commanded_position():
    """Attained 1, 3 mm along x and 2 mm +/- 3 mm along y: the barycentre is (2, 0, 0) mm, APp = 2 mm."""
    commanded = _T([0.0, 0.0, 0.0])
    attained = [_T(np.array(p) * 1e-3) for p in ([1, 0, 0], [3, 0, 0], [2, 3, 0], [2, -3, 0])]
    ap = pose_accuracy(commanded, attained)
    assert ap.n == 4
    assert ap.barycentre * 1e3 == pytest.approx([2, 0, 0])
    assert ap.ap_p * 1e3 == pytest.approx(2.0)
    assert ap.ap_xyz * 1e3 == pytest.approx([2, 0, 0], abs=1e-12)
    assert ap.ap_abc == pytest.approx([0, 0, 0], abs=1e-15)


def test_accuracy_in_three_axes_and_the_angles_about_x_y_z():
    """Every attained pose 0.3, 0.4, 1.2 mm off: APp = 1.3 mm. Turned 0.01 and 0.03 rad about z from a commanded
    tool-down orientation: APc = 0.02 rad; about x by +/-0.002 and 0.004: APa = 0.003 rad."""
    commanded = _T([0.5, -0.2, 0.4], DOWN)
    off = np.array([0.3, 0.4, 1.2]) * 1e-3
    attained = [_T(commanded[:3, 3] + off, _rot("z", 0.01) @ DOWN), _T(commanded[:3, 3] + off, _rot("z", 0.03) @ DOWN),
                _T(commanded[:3, 3] + off, _rot("x", 0.002) @ DOWN), _T(commanded[:3, 3] + off, _rot("x", 0.004) @ DOWN)]
    ap = pose_accuracy(commanded, attained)
    assert ap.ap_p * 1e3 == pytest.approx(1.3)
    assert ap.ap_xyz * 1e3 == pytest.approx([0.3, 0.4, 1.2])
    assert ap.ap_abc == pytest.approx([0.0015, 0.0, 0.01], abs=1e-12)  # (0.002 + 0.004) / 4 about x, 0.04 / 4 about z


def test_accuracy_with_one_commanded_pose_per_cycle_and_of_positions_alone():
    attained = np.array([_T([0.001, 0, 0]), _T([0.003, 0, 0])])
    assert pose_accuracy(np.array([_T([0, 0, 0])] * 2), attained).ap_p == pytest.approx(0.002)
    xy = np.array([[1.0, 2.0], [3.0, 2.0]]) * 1e-3
    ap = pose_accuracy(np.array([0.0, 2e-3]), xy)
    assert ap.ap_p == pytest.approx(2e-3) and ap.ap_abc is None


def test_accuracy_refuses_shapes_and_matrices_it_cannot_use():
    with pytest.raises(CalibrationInputError, match="attained of shape"):
        pose_accuracy(_T([0, 0, 0]), np.zeros((3, 4)))
    with pytest.raises(CalibrationInputError, match="commanded of shape"):
        pose_accuracy(np.eye(3), [_T([0, 0, 0])])
    bad = _T([0, 0, 0])
    bad[0, 0] = 2.0
    with pytest.raises(CalibrationInputError, match="no rotation matrix"):
        pose_accuracy(_T([0, 0, 0]), [bad])
    with pytest.raises(CalibrationInputError, match="not finite"):
        pose_accuracy(_T([0, 0, 0]), [_T([np.nan, 0, 0])])


# -- §7.2.2: pose repeatability ------------------------------------------------------------------------------------
def test_points_on_a_sphere_about_their_barycentre_repeat_to_its_radius():
    """The 8 corners of a cube around c all lie at r from it (their barycentre): every l_j = r, S_l = 0, RPl = r."""
    c, r = np.array([-0.5, -0.1, 0.4]), 25e-6
    points = c + r / math.sqrt(3) * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    rp = pose_repeatability([_T(p, DOWN) for p in points])
    assert rp.barycentre == pytest.approx(c)
    assert rp.distances == pytest.approx([r] * 8)
    assert rp.s_l == pytest.approx(0.0, abs=1e-15)  # rounding of positions 0.4 m from the origin
    assert rp.rp_l == pytest.approx(r)
    assert rp.rp_abc == pytest.approx([0, 0, 0], abs=1e-12)  # one orientation: no spread


def test_repeatability_of_two_radii():
    """+/-1 mm along x and +/-3 mm along y: l = 1, 1, 3, 3 mm, mean 2, S_l = sqrt(4 / 3), RPl = 2 + 2 sqrt(3) mm."""
    points = np.array([[1, 0, 0], [-1, 0, 0], [0, 3, 0], [0, -3, 0]]) * 1e-3
    rp = pose_repeatability(points)
    assert rp.l_mean * 1e3 == pytest.approx(2.0)
    assert rp.s_l * 1e3 == pytest.approx(math.sqrt(4 / 3))
    assert rp.rp_l * 1e3 == pytest.approx(2 + 2 * math.sqrt(3))
    assert rp.rp_abc is None  # positions alone
    assert pose_repeatability(points[:, :2]).rp_l * 1e3 == pytest.approx(2 + 2 * math.sqrt(3))  # in a plane alike


def test_orientation_repeatability_is_three_sample_sds_of_each_angle():
    """About x by +1, -1, +1, -1 mrad (mean 0): S_a = sqrt(4e-6 / 3) rad, RPa = 3 S_a; b and c do not move."""
    attained = [_T([0, 0, 0], _rot("x", s * 1e-3) @ DOWN) for s in (1, -1, 1, -1)]
    rp = pose_repeatability(attained)
    assert rp.s_abc == pytest.approx([math.sqrt(4e-6 / 3), 0, 0], abs=1e-12)
    assert rp.rp_abc == pytest.approx([3 * math.sqrt(4e-6 / 3), 0, 0], abs=1e-12)


def test_repeatability_does_not_depend_on_the_frame_it_is_measured_in():
    rng = np.random.default_rng(1)
    attained = [_T(rng.normal(0, 1e-5, 3), Rotation.from_rotvec(rng.normal(0, 1e-4, 3)).as_matrix() @ DOWN)
                for _ in range(10)]
    moved = [_T([0.3, -0.2, 0.1], _rot("z", 0.7)) @ T for T in attained]
    a, b = pose_repeatability(attained), pose_repeatability(moved)
    assert b.rp_l == pytest.approx(a.rp_l, rel=1e-9)
    assert np.linalg.norm(b.rp_abc) == pytest.approx(np.linalg.norm(a.rp_abc), rel=1e-6)  # the axes turn, not the size


def test_rp_of_3d_gaussian_noise_is_the_maxwell_figure():
    """Many cycles of isotropic noise of sigma per axis: l follows Maxwell's law, mean 2 sqrt(2/pi) sigma and SD
    sqrt(3 - 8/pi) sigma, so RPl = 3.62 sigma."""
    sigma = 10e-6
    points = np.random.default_rng(0).normal(0, sigma, (40000, 3))
    expected = (2 * math.sqrt(2 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi)) * sigma
    assert pose_repeatability(points).rp_l == pytest.approx(expected, rel=0.01)


def test_repeatability_needs_two_visits():
    with pytest.raises(CalibrationInputError, match="1 attained pose: repeatability needs at least 2"):
        pose_repeatability([_T([0, 0, 0])])
