"""The path of a manual move (cellctl/core/manual_path.py): steps in the cell and tool frames of four- and six-axis
arms, the held jog's end at the box edge, and the segments a move is sent in."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz, tool_down

from drivers.interfaces import Pose
from drivers.limits import WorkspaceBox

from cellctl.core.manual_path import PathError, check_in_box, rotation_of, segments, stepped, to_box_edge

BOX = WorkspaceBox(x_mm=(-10, 160), y_mm=(-10, 110), z_mm=(-5, 40))


def six_axis(alpha: float, tilt_deg: float = 0.0) -> Pose:
    r = Rotation.from_euler("y", tilt_deg, degrees=True) * tool_down(alpha)
    return Pose(0.4, 0.1, 0.3, alpha, quaternion_wxyz(r))


def test_a_four_axis_tool_frame_is_turned_by_alpha():
    p = Pose(0.04, 0.03, 0.02, math.radians(90))
    assert np.allclose(stepped(p, "x", 0.001, "tool").xyz, [0.04, 0.031, 0.02])
    assert np.allclose(stepped(p, "x", 0.001, "cell").xyz, [0.041, 0.03, 0.02])
    assert stepped(p, "rz", 0.1, "tool").alpha == pytest.approx(p.alpha + 0.1)
    with pytest.raises(PathError, match="vertical only"):
        stepped(p, "rx", 0.1, "cell")


def test_six_axis_turns_in_the_cell_frame_and_in_the_tool_frame():
    p = six_axis(0.3, tilt_deg=20)
    cell = stepped(p, "rz", 0.2, "cell")
    tool = stepped(p, "rz", 0.2, "tool")
    assert np.allclose(cell.xyz, p.xyz) and np.allclose(tool.xyz, p.xyz)  # turns about the tool point
    expected_cell = Rotation.from_euler("z", 0.2) * rotation_of(p)
    expected_tool = rotation_of(p) * Rotation.from_euler("z", 0.2)
    assert (rotation_of(cell) * expected_cell.inv()).magnitude() < 1e-9
    assert (rotation_of(tool) * expected_tool.inv()).magnitude() < 1e-9
    # a tool-frame step goes along the tool's own axis
    down = stepped(p, "z", 0.01, "tool")
    assert np.allclose(down.xyz - p.xyz, rotation_of(p).as_matrix()[:, 2] * 0.01)


def test_a_held_jog_ends_at_the_box_edge():
    p = Pose(0.04, 0.03, 0.02, 0.0)
    assert np.allclose(to_box_edge(p, "y", 1, "cell", BOX).xyz, [0.04, 0.110, 0.02])
    assert np.allclose(to_box_edge(p, "z", -1, "cell", BOX).xyz, [0.04, 0.03, -0.005])
    turned = Pose(0.04, 0.03, 0.02, math.radians(90))  # tool x is the cell's y
    assert np.allclose(to_box_edge(turned, "x", 1, "tool", BOX).xyz, [0.04, 0.110, 0.02])
    check_in_box(to_box_edge(p, "x", 1, "cell", BOX), BOX)
    with pytest.raises(PathError, match="outside the workspace box"):
        check_in_box(Pose(0.04, 0.03, 0.041), BOX)


def test_segments_split_the_straight_path_at_the_manual_speed():
    start, end = Pose(0.0, 0.0, 0.0, 0.0), Pose(0.003, 0.004, 0.0, 0.0)  # 5 mm
    path = segments(start, end, 0.01, 0.05)  # 10 mm/s: 0.5 s in 10 pieces of 50 ms
    assert len(path) == 10 and all(s.seconds == pytest.approx(0.05) for s in path)
    assert np.allclose(path[-1].target.xyz, end.xyz) and np.allclose(path[4].target.xyz, [0.0015, 0.002, 0.0])
    turn = segments(six_axis(0.0), six_axis(0.5), 0.01, 0.05)  # a turn at the speed of a point 0.1 m away
    assert len(turn) == 100 and (rotation_of(turn[-1].target) * rotation_of(six_axis(0.5)).inv()).magnitude() < 1e-9
    assert segments(start, start, 0.01, 0.05) == []
