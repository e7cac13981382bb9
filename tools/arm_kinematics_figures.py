"""Run `arm-kinematics` on the uncalibrated UR5e cell for a range of seeds and print the figures issue 28 judges,
against the hidden truth: the tool's position and orientation error over 50 unseen configurations of the working
volume before (nominal arm + hand-eye) and after, the usual chain's (cameras first, then the arm), the error over
sigma of the identified deviations, and the cell time.

    .venv/bin/python tools/arm_kinematics_figures.py [--seeds 0 10] [--measured-board] [--poses N] [--out DIR]
    .venv/bin/python tools/arm_kinematics_figures.py --irb120 [--seeds 0 10]

--irb120 runs the IRB 120 cell instead (config/sim-irb120-csm.yaml, observe: fixed-cameras) and prints its figures
in camera 1's frame (the issue's keys), in the frame the calibration's own cameras measure (`measured_`: what a
camera-guided move misses by) and in the arm's own frame (`arm_frame_`).

The board's print is the calibration's length reference (a camera measures angles only). By default the run takes
the drawing's size (the print within 0.05 %, the cell file's budget). --measured-board gives each run the size an
engineer measures with a caliper across the board's 240 mm (read to 0.01 mm, off by up to 0.02 mm): the simulation
reads the true print to make that measurement, as the engineer's caliper reads the real one.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
from pathlib import Path

import numpy as np

from drivers.sim.kinds import build_world

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine

ROOT = Path(__file__).resolve().parents[1]
CELL = ROOT / "config" / "sim-ur5e-uncalibrated.yaml"
CALIPER_LENGTH_MM = 240.0
CALIPER_SIGMA_PCT = 100 * float(np.hypot(0.02 / np.sqrt(3), 0.01 / np.sqrt(12))) / CALIPER_LENGTH_MM  # 0.005 %


def caliper_scale(config, seed: int) -> float:
    """The board's scale as a caliper across its width reads it: to 0.01 mm, within +/-0.02 mm."""
    world = build_world(config.sim.model_copy(update={"seed": seed}))
    board = next(b for b in world.boards.values() if b.config.mount == "table")
    rng = np.random.default_rng([seed, 28])
    reading = round(CALIPER_LENGTH_MM * board.scale + rng.uniform(-0.02, 0.02), 2)
    return reading / CALIPER_LENGTH_MM


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs=2, default=(0, 10), metavar=("FIRST", "STOP"))
    ap.add_argument("--measured-board", action="store_true")
    ap.add_argument("--poses", type=int, default=None)
    ap.add_argument("--out", type=Path, default=Path("/tmp/arm-kinematics-figures"))
    ap.add_argument("--irb120", action="store_true", help="the IRB 120 cell with its two fixed cameras")
    args = ap.parse_args()
    if args.irb120:
        return irb120(args)
    config, text = load_cell_file(CELL)
    rows = []
    print(f"{'seed':>4} {'before mm':>9} {'after mm':>8} {'max mm':>7} {'after deg':>9} {'seq mm':>7} {'seq/ours':>8} {'he-seq/ours':>11} "
          f"{'err/sigma':>9} {'print %':>8} {'cell s':>6}")
    for seed in range(*args.seeds):
        overrides = {}
        if args.measured_board:  # and its uncertainty: +/-0.02 mm uniform and the 0.01 mm reading over 240 mm
            overrides.update(board_scale=caliper_scale(config, seed), board_scale_sigma_pct=CALIPER_SIGMA_PCT)
        if args.poses:
            overrides["poses"] = args.poses
        out = args.out / f"seed{seed}"
        shutil.rmtree(out, ignore_errors=True)
        r = run_routine("arm-kinematics", config, text, out, seed=seed, overrides=overrides)
        t = r["truth"]
        rows.append(t | {"cell_time_s": r["cell_time_s"]})
        print(f"{seed:>4} {t['position_error_before_mean_mm']:>9.3f} {t['position_error_after_mean_mm']:>8.3f} "
              f"{t['position_error_after_max_mm']:>7.3f} {t['orientation_error_after_mean_deg']:>9.4f} "
              f"{t['position_error_sequential_mean_mm']:>7.3f} {t['sequential_over_simultaneous']:>8.2f} "
              f"{t['sequential_hand_eye_over_simultaneous']:>11.2f} "
              f"{t['error_over_sigma_median']:>9.2f} {t['board_scale_error_pct']:>8.4f} {r['cell_time_s']:>6.0f}",
              flush=True)
    med = lambda k: statistics.median(r[k] for r in rows)  # noqa: E731
    print(f"median: before {med('position_error_before_mean_mm'):.3f} mm, after {med('position_error_after_mean_mm'):.3f}"
          f" mm (worst seed {max(r['position_error_after_mean_mm'] for r in rows):.3f}), orientation "
          f"{med('orientation_error_after_mean_deg'):.4f} deg, OpenCV chain/ours {med('sequential_over_simultaneous'):.2f}, "
          f"hand-eye chain/ours {med('sequential_hand_eye_over_simultaneous'):.2f}, "
          f"error/sigma {med('error_over_sigma_median'):.2f}, cell time {med('cell_time_s'):.0f} s")


def irb120(args) -> None:
    config, text = load_cell_file(ROOT / "config" / "sim-irb120-csm.yaml")
    columns = [("before mm", "position_error_before_mean_mm"), ("cam1 mm", "position_error_after_mean_mm"),
               ("cam1 max", "position_error_after_max_mm"), ("deg", "orientation_error_after_mean_deg"),
               ("measured", "measured_position_error_after_mean_mm"),
               ("meas max", "measured_position_error_after_max_mm"), ("meas x", "measured_improvement"),
               ("seq/ours", "measured_simultaneous_over_sequential"), ("arm mm", "arm_frame_position_error_after_mean_mm"),
               ("err/sigma", "error_over_sigma_median")]
    print(f"{'seed':>4} " + " ".join(f"{name:>9}" for name, _ in columns) + f" {'cell s':>6}")
    rows = []
    for seed in range(*args.seeds):
        out = args.out / f"irb120-seed{seed}"
        shutil.rmtree(out, ignore_errors=True)
        r = run_routine("arm-kinematics", config, text, out, seed=seed,
                        overrides={"poses": args.poses} if args.poses else {})
        rows.append(r["truth"])
        print(f"{seed:>4} " + " ".join(f"{r['truth'][key]:>9.4f}" for _, key in columns) + f" {r['cell_time_s']:>6.0f}",
              flush=True)
    print("median: " + ", ".join(f"{name} {statistics.median(r[key] for r in rows):.4f}" for name, key in columns))


if __name__ == "__main__":
    main()
