"""Hybrid calibration of area1 against the virtual grid, on the same simulated cell."""

import numpy as np
import pytest

from calibration.errors import VisionError
from calibration.vision.centroid import Blob
from calibration.vision.grid import order_grid

from cellctl.cli import main
from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore

from tests.conftest import MICROCELL


@pytest.mark.parametrize("seed", [2])
def test_virtual_grid_beats_hybrid_by_the_physics_of_the_cell(tmp_path, seed):
    """Seed Table II: 2.3x in area1. Here at least 2x, from the grid plane's offset, the pitch
    tolerance and the sphere's centring, not from a tuned knob."""
    config, text = load_cell_file(MICROCELL)
    grid = run_routine("virtual-grid", config, text, tmp_path / "vg", seed=seed)
    hybrid = run_routine("hybrid", config, text, tmp_path / "hy", seed=seed)
    vg_mean, hy_mean = grid["stats"]["verification"]["mean_um"], hybrid["stats"]["verification"]["mean_um"]
    assert hy_mean >= 2.0 * vg_mean
    assert hybrid["stats"]["registration"]["n"] == 4
    assert hybrid["stats"]["calibration"]["n"] >= 42  # most of the 56 dots seen and fitted
    # OpenCV's baseline beats it on the same samples by registering with a free scale (a similarity), which
    # absorbs the grid plane's offset and pitch: the report says so, with the scale it found
    scale = hybrid["stats"]["baseline_opencv"]["registration_scale"]
    assert hybrid["stats"]["baseline_opencv"]["verification"]["mean_um"] < hy_mean and abs(scale - 1) > 3e-4
    assert f"whose scale ({scale:.5f} here) absorbs" in (tmp_path / "hy" / "report.md").read_text()
    # the composite map's own verification agrees with the truth it could not see
    assert hybrid["truth"]["mapping_mean_um"] == pytest.approx(hy_mean, rel=0.5)
    # offline: the same fit from the samples file
    out = tmp_path / "cal.json"
    assert main(["fit", "hybrid", "--samples", str(tmp_path / "hy" / "samples.csv"), "--out", str(out),
                 "--image-size", "2448x2050"]) == 0


def lattice(rows, cols, angle=0.0, pitch=300.0, drop=()):
    c, s = np.cos(angle), np.sin(angle)
    blobs = []
    for j in range(rows):
        for i in range(cols):
            if (i, j) in drop:
                continue
            u, v = 200 + pitch * (c * i - s * j), 150 + pitch * (s * i + c * j)
            blobs.append(Blob(u, v, 1.0, 10.0, 1.0, 1.0))
    return blobs


def test_grid_numbering_full_rotated_and_partial():
    full = order_grid(lattice(7, 8, angle=0.05), 7, 8)
    assert {(i, j) for i, j, _ in full} == {(i, j) for i in range(8) for j in range(7)}
    first = min(full, key=lambda t: t[2].u + t[2].v)
    assert first[:2] == (0, 0)
    partial = order_grid(lattice(7, 8, drop={(0, 0), (1, 0), (7, 6)}), 7, 8)
    assert len(partial) == 53 and min(i for i, _, _ in partial) == 0
    with pytest.raises(VisionError, match="found 20 dots"):
        order_grid(lattice(4, 5), 7, 8)
    with pytest.raises(VisionError, match="regular lattice"):
        rng = np.random.default_rng(1)
        jitter = [Blob(b.u + rng.uniform(-120, 120), b.v, 1, 10, 1, 1) for b in lattice(7, 8)]
        order_grid(jitter, 7, 8)


def test_area2_virtual_grid_beats_hybrid(tmp_path):
    """Seed Table II: 3.2x in area2; the issue asks at least 1.8x. The registration spheres' centres sit one
    radius above the printed grid, a scale error no rototranslation can take out."""
    config, text = load_cell_file(MICROCELL)
    store = CalibrationStore(tmp_path / "store")  # camera 1 checks each sphere's centring on the nozzle
    run_routine("virtual-grid", config, text, tmp_path / "vg1", seed=2, store=store,
                overrides={"rows": 5, "cols": 5, "passes": 1, "n_verify": 5})
    grid = run_routine("virtual-grid-area2", config, text, tmp_path / "vg2", seed=2, store=store)
    hybrid = run_routine("hybrid", config, text, tmp_path / "hy2", seed=2, overrides={"area": "area2"})
    vg_mean, hy_mean = grid["stats"]["verification"]["mean_um"], hybrid["stats"]["verification"]["mean_um"]
    assert hybrid["stats"]["calibration"]["n"] >= 150  # most of the 16 x 12 dots
    assert hy_mean >= 1.8 * vg_mean
    assert hybrid["truth"]["mapping_mean_um"] > 2 * grid["truth"]["mapping_mean_um"]
