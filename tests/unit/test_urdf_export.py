"""geometry/urdf.py: the URDF of a kinematic table carries its geometry exactly. Pinocchio, reading the URDF alone,
puts the flange (and the tool) where KinematicTable.forward does, to 1e-9 m, for the published UR5e and IRB 120 tables
and for tables with small deviations of every row parameter, a base away from the cell origin and a tool."""

import math
import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from geometry.kinematic_table import ROW_PARAMETERS, KinematicTable, nominal_table
from geometry.urdf import JOINT_RATINGS, rpy_of, tool_transform, urdf_of

TOLERANCE_M = 1e-9
MODELS = ("ur5e", "irb120")


def deviated(model: str, seed: int) -> KinematicTable:
    """The published table with random small deviations of theta, d, a, alpha and beta in every row (up to a few
    mm and mrad), and a base turned and moved away from the cell origin."""
    rng = np.random.default_rng(seed)
    nominal = nominal_table(model)
    scale = np.tile([2e-3 if p in ("theta", "alpha", "beta") else 3e-3 for p in ROW_PARAMETERS], len(nominal.joints))
    table = nominal.with_vector(nominal.vector() + rng.normal(0.0, 1.0, scale.size) * scale)
    base = np.eye(4)
    base[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.5, 3)).as_matrix()
    base[:3, 3] = rng.uniform(-0.8, 0.8, 3)
    return KinematicTable(table.model, table.joints, base)


def random_tool(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.uniform(-0.1, 0.1, 3)
    return T


def pose_dict(T: np.ndarray) -> dict:
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    return {"x_mm": T[0, 3] * 1e3, "y_mm": T[1, 3] * 1e3, "z_mm": T[2, 3] * 1e3, "qw": w, "qx": x, "qy": y, "qz": z}


def frame_poses(text: str, frames: tuple[str, ...], Q: np.ndarray) -> dict[str, np.ndarray]:
    """Each frame's pose in the URDF's root (base_link) for every row of joints Q, by pinocchio."""
    model = pin.buildModelFromXML(text)
    data = model.createData()
    ids = {name: model.getFrameId(name) for name in frames}
    assert all(i < model.nframes for i in ids.values()), ids
    out = {name: np.empty((len(Q), 4, 4)) for name in frames}
    for k, q in enumerate(Q):
        pin.framesForwardKinematics(model, data, q)
        for name, i in ids.items():
            out[name][k] = data.oMf[i].homogeneous
    return out


def random_joints(table: KinematicTable, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = np.array([j.limits for j in table.joints]).T
    return rng.uniform(lo, hi, (n, len(table.joints)))


@pytest.mark.parametrize("model", MODELS)
def test_the_published_table_as_urdf_moves_as_the_table(model):
    table = nominal_table(model)
    Q = random_joints(table, 200, 1)
    got = frame_poses(urdf_of(table, model), ("flange", "tool0"), Q)
    want = table.forward_batch(Q)
    assert np.abs(got["flange"] - want).max() < TOLERANCE_M
    assert np.abs(got["tool0"] - want).max() < TOLERANCE_M  # tool0: ROS-Industrial's name of the same frame


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("seed", [3, 4, 5])
def test_a_calibrated_table_with_its_base_and_tool_as_urdf_moves_as_the_table(model, seed):
    table = deviated(model, seed)
    T_flange_tool = random_tool(seed)
    Q = random_joints(table, 200, seed)
    want = table.forward_batch(Q)
    for tool in (T_flange_tool, pose_dict(T_flange_tool)):  # a matrix, or a stored pose (x_mm, ..., qz)
        got = frame_poses(urdf_of(table, f"{model}_calibrated", tool), ("flange", "tool"), Q)
        assert np.abs(got["flange"] - want).max() < TOLERANCE_M
        assert np.abs(got["tool"] - want @ T_flange_tool).max() < TOLERANCE_M
    # the deviations are what moves the flange: the published table is millimetres away
    assert np.abs(nominal_table(model).forward_batch(Q)[:, :3, 3] - want[:, :3, 3]).max() > 1e-3


def test_micrometre_deviations_survive_the_text():
    """Numbers are written with every digit: a deviation of 1 µm or 1 µrad in any one parameter moves the URDF's
    flange as it moves the table's."""
    nominal = nominal_table("ur5e")
    Q = random_joints(nominal, 20, 9)
    for k in range(nominal.vector().size):
        step = np.zeros(nominal.vector().size)
        step[k] = 1e-6
        table = nominal.with_vector(nominal.vector() + step)
        got = frame_poses(urdf_of(table, "ur5e"), ("flange",), Q)["flange"]
        assert np.abs(got - table.forward_batch(Q)).max() < 1e-12, nominal.parameter_names()[k]


def test_the_document_parses_and_names_its_links_joints_and_limits():
    table = deviated("irb120", 7)
    text = urdf_of(table, "irb120_cell_v3", random_tool(7), comment="calibration 3 -- of cell x")
    root = ET.fromstring(text)  # the stdlib's parser reads it
    assert root.tag == "robot" and root.get("name") == "irb120_cell_v3"
    assert [link.get("name") for link in root.iter("link")] == [
        "base_link", "link_1", "link_2", "link_3", "link_4", "link_5", "link_6", "flange", "tool0", "tool"]
    joints = {j.get("name"): j for j in root.iter("joint")}
    assert list(joints) == ["joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6",
                            "link_6-flange", "flange-tool0", "flange-tool"]
    chain = ["base_link", "link_1", "link_2", "link_3", "link_4", "link_5", "link_6"]
    for i, row in enumerate(table.joints):
        j = joints[row.name]
        assert j.get("type") == "revolute" and j.find("axis").get("xyz") == "0 0 1"
        assert (j.find("parent").get("link"), j.find("child").get("link")) == (chain[i], chain[i + 1])
        limit = j.find("limit")
        assert (float(limit.get("lower")), float(limit.get("upper"))) == row.limits  # exact: repr round-trips
        assert (float(limit.get("velocity")), float(limit.get("effort"))) == JOINT_RATINGS["irb120"][i]
    assert math.isclose(float(joints["joint_6"].find("limit").get("upper")), math.radians(400))
    assert joints["link_6-flange"].get("type") == "fixed"
    assert (joints["flange-tool"].find("parent").get("link"), joints["flange-tool"].find("child").get("link")) == \
        ("flange", "tool")
    # pinocchio reads the same joints and limits
    model = pin.buildModelFromXML(text)
    assert list(model.names)[1:] == [j.name for j in table.joints]
    assert np.array_equal(model.lowerPositionLimit, [j.limits[0] for j in table.joints])
    assert np.array_equal(model.upperPositionLimit, [j.limits[1] for j in table.joints])


def test_no_tool_no_tool_link_and_ur_joint_names():
    root = ET.fromstring(urdf_of(nominal_table("ur5e"), "ur5e"))
    assert "tool" not in {link.get("name") for link in root.iter("link")}
    revolute = [j for j in root.iter("joint") if j.get("type") == "revolute"]
    assert [j.get("name") for j in revolute] == ["base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3"]
    assert {float(j.find("limit").get("upper")) for j in revolute} == {2 * math.pi}


def test_rpy_is_fixed_axis_roll_pitch_yaw_also_at_gimbal_lock():
    rng = np.random.default_rng(11)
    for _ in range(200):
        R = Rotation.random(random_state=rng).as_matrix()
        roll, pitch, yaw = rpy_of(R)
        assert np.abs(pin.rpy.rpyToMatrix(roll, pitch, yaw) - R).max() < 1e-14
    for pitch in (math.pi / 2, -math.pi / 2):
        R = pin.rpy.rpyToMatrix(0.3, pitch, -1.1)
        assert np.abs(pin.rpy.rpyToMatrix(*rpy_of(R)) - R).max() < 1e-14


def test_bad_tools_and_tables_are_refused_naming_what_is_wrong():
    table = nominal_table("ur5e")
    with pytest.raises(ValueError, match="tool: qz missing"):
        urdf_of(table, "x", {"x_mm": 0, "y_mm": 0, "z_mm": 0, "qw": 1, "qx": 0, "qy": 0})
    with pytest.raises(ValueError, match="not of unit length"):
        tool_transform({"x_mm": 0, "y_mm": 0, "z_mm": 0, "qw": 1, "qx": 1, "qy": 0, "qz": 0})
    with pytest.raises(ValueError, match="finite"):
        tool_transform({"x_mm": float("nan"), "y_mm": 0, "z_mm": 0, "qw": 1, "qx": 0, "qy": 0, "qz": 0})
    with pytest.raises(ValueError, match="not a rigid transform"):
        urdf_of(table, "x", np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="needs 6 joints"):
        urdf_of(KinematicTable("ur5e", table.joints[:5]), "x")
