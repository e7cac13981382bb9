"""Benchmark of the VR matching (seed 000): the line detection of both views, one line-based simultaneous solve
(20 variables) with about 100 segments, a full line-based update, how detection and update grow with the
number of segments, and a full vr-experiments run if asked.

    .venv/bin/python tools/bench_vr.py [--segments 100] [--repeat 30] [--experiments]

Targets: the solve <= 50 ms (issue 7); line detection of both views <= 15 ms and a full line-based update
<= 40 ms (issue 17). Timings are medians (and minima) of repeated runs: the machine may be shared.

Scaling, printed as growth = (t / t_first) / (segments / segments_first), t the best of the repeats: 1 for linear
growth, above 1 for worse than linear.
- detection (both views) against the number of segments: the models' edges are cut to a subset (the first edges
  of one random order, faces kept, so the z-buffer and what hides what are unchanged) giving at least 25, 50
  and 100 segments (edges come whole: a few more), and all of them (245);
- the full update against the number of segments: all edges, cut into segments of 40, 20 (the default) and
  10 px (about 125, 245 and 460 segments). Fewer than about 100 segments cannot be timed as an update: with 20
  unknowns the gate and the divergence check stop it, or it takes many more iterations, so its time would not
  say how the cost grows.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.models.model_matching import (
    CameraState,
    Observations,
    increment,
    solve,
)
from calibration.routines.vr._common import (
    CAM,
    Estimate,
    VrParams,
    _cams,
    line_observations,
    line_update,
    load_models,
)

from cellctl.config import load_cell_file
from cellctl.core.cell import Cell

CELL = Path(__file__).resolve().parents[1] / "config" / "sim-vr.yaml"
TARGET_DETECT_MS, TARGET_SOLVE_MS, TARGET_UPDATE_MS = 15.0, 50.0, 40.0


def timed(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, times


def ms(times) -> str:
    return f"median {1e3 * statistics.median(times):.1f} ms, min {1e3 * min(times):.1f} ms"


def detect_both(params, frames, est, models) -> Observations:
    return Observations.concat([line_observations(params, frames[i], i, est, models) for i in range(2)])


def edge_subsets(params, frames, est, models, rng):
    """(segments, models) for the fewest edges, in one random order over both objects, that give at least 25, 50
    and 100 segments, and for all edges."""
    order = [(obj, k) for obj in models for k in range(len(models[obj].edges))]
    order = [order[i] for i in rng.permutation(len(order))]

    def cut(n_edges):
        chosen = order[:n_edges]
        return {obj: replace(m, edges=m.edges[sorted(k for o, k in chosen if o == obj)]) for obj, m in models.items()}

    out = []
    for size in (25, 50, 100):
        n_edges = next((n for n in range(1, len(order)) if detect_both(params, frames, est, cut(n)).n_lines >= size),
                       len(order))
        out.append(cut(n_edges))
    return [(detect_both(params, frames, est, m).n_lines, m) for m in out + [models]]


def growth_table(title, rows) -> None:
    """rows: (segments, times); growth from the best times (the least disturbed by other work on the machine)."""
    print(f"\n{title}\n  {'segments':>8}  {'median':>9}  {'min':>9}  {'growth':>6}")
    n0, t0 = rows[0][0], min(rows[0][1])
    for n, times in rows:
        print(f"  {n:8d}  {1e3 * statistics.median(times):6.1f} ms  {1e3 * min(times):6.1f} ms  "
              f"{(min(times) / t0) / (n / n0):6.2f}")


def scaling(params, frames, est, models, rng, repeat) -> None:
    rows = []
    for n, sub in edge_subsets(params, frames, est, models, rng):
        rows.append((n, timed(lambda s=sub: detect_both(params, frames, est, s), repeat)[1]))
    growth_table("line detection, both views, against segments (edge subsets of the models):", rows)
    rows = []
    for segment_px in (40.0, 20.0, 10.0):
        p = params.model_copy(update={"segment_px": segment_px})
        n = detect_both(p, frames, est, models).n_lines
        rows.append((n, timed(lambda p=p: line_update(p, frames, est, models, (True, True), True), repeat)[1]))
    growth_table("full line-based update against segments (all edges in segments of 40, 20, 10 px):", rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--segments", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--experiments", action="store_true", help="also time the full default vr-experiments run")
    ap.add_argument("--no-scaling", action="store_true", help="skip the scaling table")
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
    obs, t_detect = timed(lambda: detect_both(params, frames, est, models), args.repeat)
    keep = np.zeros(obs.n_lines, bool)
    keep[rng.choice(obs.n_lines, min(args.segments, obs.n_lines), replace=False)] = True
    sub = obs.select_lines(keep)
    start = (_cams(est, (True, True), True, False), est.objects(True))
    result, t_solve = timed(lambda: solve(*start, sub), args.repeat)
    _, t_update = timed(lambda: line_update(params, frames, est, models, (True, True), True), max(3, args.repeat // 3))
    print(f"line detection, both views: {obs.n_lines} segments, {ms(t_detect)}  (target <= {TARGET_DETECT_MS:.0f} ms)")
    print(f"simultaneous solve (20 variables, {sub.n_lines} segments, {result.iterations} iterations, "
          f"rms {result.rms_px:.2f} px): {ms(t_solve)}, max {1e3 * max(t_solve):.1f} ms  "
          f"(target <= {TARGET_SOLVE_MS:.0f} ms)")
    print(f"full line-based update ({params.rounds} detect-and-solve rounds with gating): {ms(t_update)}  "
          f"(target <= {TARGET_UPDATE_MS:.0f} ms)")
    if not args.no_scaling:
        scaling(params, frames, est, models, np.random.default_rng(1), max(5, args.repeat // 3))
    if args.experiments:
        import tempfile

        from cellctl.core.runs import run_routine

        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            res = run_routine("vr-experiments", config, text, Path(tmp) / "run")
            print(f"vr-experiments (default parameters): {time.perf_counter() - t0:.0f} s wall, "
                  f"{res['cell_time_s'] / 60:.0f} min of simulated cell time, {res['n_samples']} samples")


if __name__ == "__main__":
    main()
