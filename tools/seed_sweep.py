"""Run everything seed 001 compares (the `seed-001` sequence) for a range of simulation seeds and print,
per seed, the figures the issues judge, against the hidden truth.

    .venv/bin/python tools/seed_sweep.py [--seeds 0 10] [--out /tmp/seed-sweep]

Columns: VG virtual grid area1 (verification mean µm, fitted-vs-true map mean/max µm, centroid RMS px);
HY1/HY2 hybrid verification mean and its ratio to the virtual grid, area1 / area2; RS rotation sweep
(offset error µm per axis, uncompensated / compensated ratio); A2 virtual grid area2 verification mean;
OB on-board camera (D error µm per axis, worst c* RMS over the poses); PT place-test (measured mean, true mean).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from cellctl.config import load_cell_file
from cellctl.core.runs import run_sequence
from cellctl.stores.calibrations import CalibrationStore

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs=2, default=(0, 10), metavar=("FIRST", "END"))
    parser.add_argument("--out", default="/tmp/seed-sweep")
    args = parser.parse_args()
    config, text = load_cell_file(ROOT / "config" / "sim-microcell.yaml")
    for seed in range(*args.seeds):
        out = Path(args.out) / str(seed)
        shutil.rmtree(out, ignore_errors=True)
        r = run_sequence("seed-001", config, text, out, seed=seed, store=CalibrationStore(out / "calibrations"))["results"]
        vg, rs, ob, pt = (r[k] for k in ("virtual-grid", "rotation-sweep", "onboard-camera", "place-test"))
        ver = {k: v["stats"]["verification"]["mean_um"] for k, v in r.items()}
        worst_c = max(row["c*"] for row in ob["stats"]["cross_reference"]["rms_um"].values())
        print(f"seed {seed}: VG {ver['virtual-grid']:.2f} map {vg['truth']['mapping_mean_um']:.2f}/"
              f"{vg['truth']['mapping_max_um']:.2f} cen {vg['truth']['centroid_rms_px']:.4f} | "
              f"HY1 {ver['hybrid']:.2f} x{ver['hybrid'] / ver['virtual-grid']:.2f} | "
              f"HY2 {ver['hybrid.area2']:.2f} x{ver['hybrid.area2'] / ver['virtual-grid-area2']:.2f} | "
              f"RS {rs['truth']['dx_error_um']:+.2f} {rs['truth']['dy_error_um']:+.2f} "
              f"x{rs['stats']['uncompensated']['mean_um'] / ver['rotation-sweep']:.0f} | A2 {ver['virtual-grid-area2']:.2f} | "
              f"OB {ob['truth']['d_x_error_um']:+.1f} {ob['truth']['d_y_error_um']:+.1f} c* {worst_c:.1f} | "
              f"PT {ver['place-test']:.2f} (true {pt['truth']['placement_mean_um']:.2f})", flush=True)


if __name__ == "__main__":
    main()
