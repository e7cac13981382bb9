"""`cellctl fit` on sample files made here, not by cellctl's simulated cell: each file has its own
ground truth (a camera map, a grid's placement, a tool offset, a rotation axis) that the fit must recover."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from calibration.models.planar import PlanarMap
from calibration.models.tool_offset import rot

from cellctl.cli import main


def camera(um_per_px: float, centre_m, size=(1280, 1024), k2=0.004, turn_deg=3.0) -> PlanarMap:
    """A true camera: pixels -> plane (m), with a little perspective and barrel distortion."""
    s, c = um_per_px * 1e-6, math.cos(math.radians(turn_deg))
    n = math.sin(math.radians(turn_deg))
    w, h = size
    H = np.array([[s * c, -s * n, 0.0], [s * n, s * c, 0.0], [2e-6, -1.5e-6, 1.0]])
    mid = H @ [(w - 1) / 2, (h - 1) / 2, 1.0]  # the translation that puts the image centre on centre_m
    H[:2, 2] = np.asarray(centre_m) * mid[2] - mid[:2]
    return PlanarMap(size, H / H[2, 2], ((w - 1) / 2, (h - 1) / 2), max(size) / 2, (k2,), (0.0, 0.0))


def write(path, rows):
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def fit(tmp_path, routine, rows, *extra) -> dict:
    samples, out = tmp_path / f"{routine}.csv", tmp_path / f"{routine}.json"
    write(samples, rows)
    assert main(["fit", routine, "--samples", str(samples), "--out", str(out), *extra]) == 0
    return json.loads(out.read_text())


def test_rotation_sweep_recovers_the_tool_offset(tmp_path):
    rng = np.random.default_rng(7)
    d = np.array([40.0, -90.0]) * 1e-6
    rows = []
    for k, centre in enumerate(rng.uniform(0.03, 0.05, (6, 2))):
        for alpha in range(0, 360, 20):
            m = centre + (rot(math.radians(alpha)) - np.eye(2)) @ d + rng.normal(0, 0.3e-6, 2)
            rows.append({"pos_id": k, "alpha_deg": alpha, "x_mm": m[0] * 1e3, "y_mm": m[1] * 1e3})
    model = fit(tmp_path, "rotation-sweep", rows)["model"]
    assert model["dx_um"] == pytest.approx(40.0, abs=0.2) and model["dy_um"] == pytest.approx(-90.0, abs=0.2)


def test_hybrid_recovers_the_camera_and_the_grids_placement(tmp_path):
    rng = np.random.default_rng(3)
    true = camera(6.6, (0.040, 0.030), size=(2448, 2050))
    turn, shift = rot(math.radians(1.2)), np.array([0.0331, 0.0238])  # robot <- grid frame
    rows = []
    for i in range(8):
        for j in range(7):
            g = np.array([i, j]) * 2e-3
            uv = true.plane_to_pixel(turn @ g + shift)[0] + rng.normal(0, 0.02, 2)
            rows.append({"set": "grid", "gx_mm": g[0] * 1e3, "gy_mm": g[1] * 1e3, "x_mm": "", "y_mm": "",
                         "u_px": uv[0], "v_px": uv[1]})
    robot = rng.uniform([0.034, 0.024], [0.046, 0.036], (24, 2))
    for k, xy in enumerate(robot):
        uv = true.plane_to_pixel(xy)[0] + rng.normal(0, 0.02, 2)
        rows.append({"set": "reg" if k < 4 else "ver", "gx_mm": "", "gy_mm": "", "x_mm": xy[0] * 1e3,
                     "y_mm": xy[1] * 1e3, "u_px": uv[0], "v_px": uv[1]})
    result = fit(tmp_path, "hybrid", rows, "--image-size", "2448x2050")
    assert result["stats"]["verification"]["n"] == 20
    assert result["stats"]["verification"]["mean_um"] < 0.5
    fitted = PlanarMap.from_dict(result["model"]["map"])
    test = rng.uniform([200, 200], [2200, 1800], (50, 2))
    assert np.abs(fitted.pixel_to_plane(test) - true.pixel_to_plane(test)).max() < 1e-6


def test_onboard_camera_recovers_the_rotation_axis(tmp_path):
    rng = np.random.default_rng(5)
    true = camera(6.2, (0.0, 0.0), size=(2592, 1944))  # pixels -> position relative to the gripper
    D = np.array([65.0, -137.0]) * 1e-6
    centre, mount = np.array([0.100, 0.085]), np.array([0.025, 0.005])
    spheres = [centre + [(i - 2) * 3e-3, (j - 1.5) * 2.5e-3] for j in range(4) for i in range(5)]
    rows = [{"set": "place", "pose": "", "sphere": s, "alpha_deg": "", "x_mm": X[0] * 1e3, "y_mm": X[1] * 1e3,
             "u_px": "", "v_px": ""} for s, X in enumerate(spheres)]
    for k, alpha in enumerate((0.0, 15.0, 30.0, -15.0, -30.0, 45.0), start=1):
        R = rot(math.radians(alpha))
        P = centre - R @ mount + rng.normal(0, 0.5e-6, 2)  # the arm's reported pose over the grid
        for s, X in enumerate(spheres):
            b = R.T @ (X - P - (np.eye(2) - R) @ D)  # eq. (5) solved for what the camera sees
            uv = true.plane_to_pixel(b)[0] + rng.normal(0, 0.02, 2)
            rows.append({"set": "pose", "pose": k, "sphere": s, "alpha_deg": alpha, "x_mm": P[0] * 1e3,
                         "y_mm": P[1] * 1e3, "u_px": uv[0], "v_px": uv[1]})
    model = fit(tmp_path, "onboard-camera", rows, "--image-size", "2592x1944")["model"]
    assert model["d_x_um"] == pytest.approx(65.0, abs=1.0) and model["d_y_um"] == pytest.approx(-137.0, abs=1.0)
    # the seed's procedure alone (pose 1's map, c* by eq. 4) recovers it too
    seed = fit(tmp_path, "onboard-camera", rows, "--image-size", "2592x1944", "--param", "joint_adjustment=false")
    assert seed["model"]["d_x_um"] == pytest.approx(65.0, abs=1.5)
