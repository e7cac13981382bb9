"""Rotation-sweep calibration of the nozzle offset, after virtual-grid calibration of camera 1."""

import numpy as np
import pytest

from calibration.errors import CalibrationInputError
from calibration.models.tool_offset import fit_tool_offset

from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore


def test_offset_recovered_and_compensation_works(calibrated_cell):
    """The full-size sweep of calibrate-cell (cell file defaults: 5 x 6 positions every 20 degrees, 30 checks)."""
    sweep = calibrated_cell.done["results"]["rotation-sweep"]
    truth, model, stats = sweep["truth"], sweep["model"], sweep["stats"]
    assert abs(model["dx_um"] - truth["dx_um"]) <= 1.0
    assert abs(model["dy_um"] - truth["dy_um"]) <= 1.0
    assert stats["verification"]["n"] == 30
    assert stats["uncompensated"]["mean_um"] >= 40 * stats["verification"]["mean_um"]
    assert sweep["calibration"]["target"] == "nozzle" and sweep["calibration"]["active"]


def test_refuses_without_a_camera_calibration(microcell, tmp_path):
    config, text = microcell
    with pytest.raises(CalibrationInputError, match="needs an active calibration of 'cam1'"):
        run_routine("rotation-sweep", config, text, tmp_path / "rs", store=CalibrationStore(tmp_path / "empty"))
    assert not (tmp_path / "rs").exists()  # refused before any motion or file


def test_tool_offset_fit_exact_and_degenerate():
    rng = np.random.default_rng(0)
    d = np.array([-68.7e-6, 137.2e-6])
    ids, alphas, xy = [], [], []
    for k in range(4):
        centre = rng.uniform(-5e-3, 5e-3, 2)
        for a in np.radians(np.arange(0, 360, 20)):
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            ids.append(k), alphas.append(a), xy.append(centre + (R - np.eye(2)) @ d)
    fit = fit_tool_offset(ids, alphas, np.array(xy))
    assert (fit.dx, fit.dy) == pytest.approx(tuple(d), abs=1e-12)
    with pytest.raises(CalibrationInputError, match="less than 10 degrees"):
        fit_tool_offset([0, 0, 0], np.radians([0, 2, 4]), np.zeros((3, 2)))
