"""The calibrated region a planar map keeps (the convex hull of the pixels its fit used), the image it was fitted
for, and `cellctl map` on both: a pixel off the image is refused naming its row, one outside the region is marked
and warned about, with its sigma grown (issue 25)."""

import csv
import json
from dataclasses import replace

import numpy as np
import pytest

from calibration.errors import CalibrationInputError
from calibration.models.planar import PlanarMap, fit_planar_map, hull, inside_hull
from calibration.usage import CellCalibration, map_sigma

from cellctl.cli import main


def grid_fit(noise=1e-6, seed=1):
    """A fit on a 7 x 5 grid of pixels between (300, 200) and (900, 600) of a 1280 x 1024 image."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(300, 900, 7), np.linspace(200, 600, 5))
    uv = np.column_stack([u.ravel(), v.ravel()])
    xy = uv * 20e-6 + 1e-9 * (uv - 640) ** 2 + rng.normal(0, noise, uv.shape)
    return fit_planar_map(uv, xy, (1280, 1024))


def test_hull_is_the_convex_outline_counter_clockwise():
    pts = np.array([[0, 0], [2, 0], [2, 2], [0, 2], [1, 1], [1, 0], [2, 1]], dtype=float)
    h = hull(pts)
    assert {tuple(p) for p in h} == {(0, 0), (2, 0), (2, 2), (0, 2)}  # no inner or collinear points
    area = 0.5 * np.sum(h[:, 0] * np.roll(h[:, 1], -1) - np.roll(h[:, 0], -1) * h[:, 1])
    assert area == pytest.approx(4.0)  # positive: counter-clockwise
    inside = inside_hull(h, np.array([[1, 1], [0, 0], [2, 1], [2.01, 1], [-0.5, 1]]))
    assert inside.tolist() == [True, True, True, False, False]  # the edge and its corners count as inside


def test_a_fit_keeps_its_region_and_a_map_reads_back_with_or_without_one():
    fit = grid_fit()
    m = fit.map
    assert {tuple(p) for p in m.region} == {(300, 200), (900, 200), (900, 600), (300, 600)}
    again = PlanarMap.from_dict(json.loads(json.dumps(m.to_dict())))
    assert again.region == m.region
    assert again.in_region([[600, 400], [900, 600], [950, 400]]).tolist() == [True, True, False]
    older = {k: v for k, v in m.to_dict().items() if k != "region_px"}  # a map made before the region was kept
    assert PlanarMap.from_dict(older).in_region([[600, 400]]) is None
    with pytest.raises(CalibrationInputError, match="region_px"):
        PlanarMap.from_dict(dict(m.to_dict(), region_px=[[0, 0], [1, 1]]))
    assert fit.map_with(fit.theta).region == m.region  # a refined map keeps the region of its samples,
    wider = fit.map_with(fit.theta, [[100, 100], [1000, 100], [500, 900], [600, 400]])  # or of those refining it
    assert {tuple(p) for p in wider.region} == {(100, 100), (1000, 100), (500, 900)}


def test_the_image_edges_and_what_is_said_off_it():
    m = grid_fit().map
    assert m.on_image([[-0.5, -0.5], [1279.5, 1023.5], [640, 512]]).all()
    assert not m.on_image([[-0.6, 10], [10, 1023.6], [99999, -5]]).any()
    assert m.off_image(99999, -5, "cam1's") == ("pixel (99999, -5) is outside cam1's 1280 x 1024 image: allowed u_px "
                                                "-0.5 to 1279.5, v_px -0.5 to 1023.5")
    cal = CellCalibration({"cam1": {"map": m.to_dict()}, "nozzle": {"dx_um": 1.0, "dy_um": 2.0}})
    with pytest.raises(CalibrationInputError, match=r"pixel \(99999, -5\) is outside cam1's 1280 x 1024 image"):
        cal.check_on_image("cam1", [(640, 512), (99999, -5)])
    with pytest.raises(CalibrationInputError, match="'nozzle' .* maps no pixels"):
        cal.locate("nozzle", [(1, 2)])


def test_the_maps_sigma_grows_outside_the_region():
    fit = grid_fit(noise=2e-6)
    model = {"map": fit.map.to_dict(), "uncertainty": fit.uncertainty().to_dict()}
    sigma = map_sigma(model, [[600, 400], [900, 600], [1000, 700], [1200, 900]])
    assert sigma[0] < sigma[1] < sigma[2] < sigma[3]
    assert np.isnan(map_sigma({"map": fit.map.to_dict()}, [[600, 400]])).all()  # no covariance kept


def test_cellctl_map_marks_pixels_outside_the_region_and_refuses_one_off_the_image(tmp_path, capsys):
    fit = grid_fit(noise=2e-6)
    cal = tmp_path / "cal.json"
    model = {"kind": "virtual-grid", "plane_unit": "m", "map": fit.map.to_dict(),
             "uncertainty": fit.uncertainty().to_dict()}
    cal.write_text(json.dumps({"model": model}))
    pixels, out = tmp_path / "px.csv", tmp_path / "xy.csv"
    pixels.write_text("u_px,v_px\n600,400\n1100,900\n")
    assert main(["map", str(cal), "--pixels", str(pixels), "--out", str(out)]) == 0
    rows = list(csv.DictReader(open(out)))
    assert [r["outside_calibrated_region"] for r in rows] == ["0", "1"]
    assert 0 < float(rows[0]["sigma_um"]) < float(rows[1]["sigma_um"])
    err = capsys.readouterr().err
    assert "1 of 2 pixels (rows 3) are outside the calibrated region" in err

    pixels.write_text("u_px,v_px\n600,400\n99999,-5\n")
    out.unlink()
    assert main(["map", str(cal), "--pixels", str(pixels), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "row 3: pixel (99999, -5) is outside the calibration's 1280 x 1024 image" in err
    assert not out.exists()  # nothing half-written

    # a calibration made before the region was kept: the column is empty, nothing is claimed
    model["map"] = {k: v for k, v in model["map"].items() if k != "region_px"}
    cal.write_text(json.dumps({"model": model}))
    pixels.write_text("u_px,v_px\n1100,900\n")
    assert main(["map", str(cal), "--pixels", str(pixels), "--out", str(out)]) == 0
    assert [r["outside_calibrated_region"] for r in csv.DictReader(open(out))] == [""]
    assert "warning" not in capsys.readouterr().err


def test_a_map_without_a_region_is_still_a_map():
    m = replace(grid_fit().map, region=None)
    assert "region_px" not in m.to_dict() and PlanarMap.from_dict(m.to_dict()).region is None
