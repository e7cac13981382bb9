"""Benchmark of the VR matching (seed 000): one line-based simultaneous solve (20 variables) with about 100
segments, the line detection feeding it, and a full vr-experiments run if asked.

    .venv/bin/python tools/bench_vr.py [--segments 100] [--repeat 30] [--experiments]

Target (issue 7): the solve in <= 50 ms.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.models.model_matching import (
    CameraState,
    Observations,
    increment,
    solve,
)
from calibration.routines.vr_common import (
    CAM,
    Estimate,
    VrParams,
    _cams,
    line_observations,
    line_update,
    load_models,
)
from cellctl.cell import Cell
from cellctl.config import load_cell_file

CELL = Path(__file__).resolve().parents[1] / "config" / "sim-vr.yaml"


def timed(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--segments", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--experiments", action="store_true", help="also time the full default vr-experiments run")
    args = ap.parse_args()

    config, text = load_cell_file(CELL)
    params = VrParams()
    models = load_models(params)
    with Cell(config, text) as cell:
        world = cell.sim_world
        cell.begin_step(0)
        frames = [cell.cameras[n].capture() for n in CAM]
        rng = np.random.default_rng(0)
        # a start near the truth, as after coarse matching: cameras and receptacle a little off
        cams = [CameraState.centred(increment(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.002, 3)]) @ world.cameras[n].V,
                                    world.cameras[n].f * 1.01, 640, 480) for n in CAM]
        est = Estimate(cams, world.oru_pose(), world.receptacle @ increment(np.r_[rng.normal(0, 0.005, 3), 0, 0, 0.01]))
        obs, t_detect = timed(lambda: Observations.concat([line_observations(params, frames[i], i, est, models)
                                                            for i in range(2)]), 5)
        keep = np.zeros(obs.n_lines, bool)
        keep[rng.choice(obs.n_lines, min(args.segments, obs.n_lines), replace=False)] = True
        sub = obs.select_lines(keep)
        start = (_cams(est, (True, True), True, False), est.objects(True))
        result, t_solve = timed(lambda: solve(*start, sub), args.repeat)
        _, t_update = timed(lambda: line_update(params, frames, est, models, (True, True), True), 3)
    print(f"line detection, both views: {obs.n_lines} segments, median {1e3 * statistics.median(t_detect):.1f} ms")
    print(f"simultaneous solve (20 variables, {sub.n_lines} segments, {result.iterations} iterations, "
          f"rms {result.rms_px:.2f} px): median {1e3 * statistics.median(t_solve):.1f} ms, "
          f"min {1e3 * min(t_solve):.1f} ms, max {1e3 * max(t_solve):.1f} ms  (target <= 50 ms)")
    print(f"full line-based update ({params.rounds} detect-and-solve rounds with gating): "
          f"median {1e3 * statistics.median(t_update):.0f} ms")
    if args.experiments:
        import tempfile

        from cellctl.runs import run_routine

        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            res = run_routine("vr-experiments", config, text, Path(tmp) / "run")
            print(f"vr-experiments (default parameters): {time.perf_counter() - t0:.0f} s wall, "
                  f"{res['cell_time_s'] / 60:.0f} min of simulated cell time, {res['n_samples']} samples")


if __name__ == "__main__":
    main()
