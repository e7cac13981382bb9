"""The computer's own time per step (issue 31): wall time per step with and without the overlap of a step's
measurement with the next step's move (`collect(pipeline=...)`), and the processing time that overlaps.

    .venv/bin/python tools/bench_overlap.py [--seed 0] [--realtime 1.0] [--out DIR]

The simulated cell spends its cell time as wall time (`sim.motion.realtime_factor`, 1: moves, settling, exposure and
read-out take their real time), so the wall time of a step is what a real cell's would be: its cell time plus
whatever the computer adds. Per routine (virtual-grid, then rotation-sweep with the camera it calibrated; small
plans, the whole budget):

- wall s/step: the wall time from one step's capture to the next's, mean, with and without the overlap;
- cell s/step: the simulated clock's time per step (the same in both: the samples are the same);
- measure ms and refit ms: the wall time per step of the routine's processing (`measure`: finding the feature)
  and of the accuracy target's refit (`enough`), which the overlap runs beside the next move;
- added ms: wall minus cell time per step, what the computer still adds.

Timings are printed, never asserted; the machine's load shows in them.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

from calibration.routines import routine_class

from cellctl.config import load_cell_file
from cellctl.core import orchestrator, runs
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore

ROOT = Path(__file__).resolve().parents[1]
UNREACHABLE_UM = 1e-3  # the whole budget: every step of the plan taken, the same steps in both modes
PLANS = {"virtual-grid": {"rows": 4, "cols": 4, "passes": 1, "n_verify": 8, "target_um": UNREACHABLE_UM},
         "rotation-sweep": {"rows": 1, "cols": 3, "step_deg": 60.0, "n_verify": 4, "target_um": UNREACHABLE_UM}}


class Timed:
    """Wall time spent in a routine class's methods (any thread), per method name, while in force."""

    def __init__(self, cls, names):
        self.cls, self.names = cls, names
        self.spent: dict[str, list[float]] = defaultdict(list)
        self.ends: dict[str, list[float]] = defaultdict(list)  # when each call returned
        self._lock = threading.Lock()

    def __enter__(self):
        self.saved = {n: self.cls.__dict__[n] for n in self.names}
        for name, method in self.saved.items():
            setattr(self.cls, name, self._timed(name, method))
        return self

    def _timed(self, name, method):
        @functools.wraps(method)
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                end = time.perf_counter()
                with self._lock:
                    self.spent[name].append(end - start)
                    self.ends[name].append(end)
        return timed

    def __exit__(self, *exc):
        for name, method in self.saved.items():
            setattr(self.cls, name, method)

    def per_step_ms(self, name: str, steps: int) -> float:
        return 1e3 * sum(self.spent.get(name, ())) / steps


def run(config, text, name: str, out: Path, store: CalibrationStore, pipeline: bool) -> dict:
    cells: list[float] = []

    def progress(p):
        if p.step is not None:
            cells.append(p.cell_time_s)

    runs.collect = functools.partial(orchestrator.collect, pipeline=pipeline)
    try:
        with Timed(routine_class(name), ("capture", "measure", "enough")) as timed:
            run_routine(name, config, text, out, seed=0, store=store, overrides=PLANS[name], on_progress=progress)
    finally:
        runs.collect = orchestrator.collect
    # from one capture to the next, in both modes the point where the step's cell time is stamped; the first step
    # left out (it starts wherever the arm was)
    walls = timed.ends["capture"]
    steps = len(walls) - 1
    return {"wall": (walls[-1] - walls[0]) / steps, "cell": (cells[-1] - cells[0]) / steps,
            "measure": timed.per_step_ms("measure", steps + 1), "refit": timed.per_step_ms("enough", steps + 1),
            "steps": steps + 1}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--realtime", type=float, default=1.0, help="wall seconds per second of cell time")
    parser.add_argument("--config", default=str(ROOT / "config" / "sim-microcell.yaml"))
    parser.add_argument("--out", default=None, help="where the runs go (default: a temporary folder)")
    args = parser.parse_args()
    config, text = load_cell_file(args.config)
    sim = config.sim.model_copy(update={"seed": args.seed, "motion": config.sim.motion.model_copy(
        update={"realtime_factor": args.realtime})})
    config = config.model_copy(update={"sim": sim})
    out = Path(args.out or tempfile.mkdtemp(prefix="bench-overlap-"))
    results = {}
    for mode, pipeline in (("plain", False), ("overlap", True)):
        store = CalibrationStore(out / mode / "store")  # rotation-sweep measures with the map virtual-grid made
        try:
            results[mode] = {name: run(config, text, name, out / mode / name, store, pipeline) for name in PLANS}
        finally:
            store.close()
    print(f"wall time per step, realtime factor {args.realtime} (runs in {out})")
    head = (f"{'routine':<16}{'steps':>6}{'cell s':>8}{'plain s':>9}{'overlap s':>10}{'measure ms':>11}"
            f"{'refit ms':>9}{'added plain ms':>15}{'added overlap ms':>17}{'saved %':>8}")
    print(head)
    print("-" * len(head))
    for name in PLANS:
        plain, overlap = results["plain"][name], results["overlap"][name]
        print(f"{name:<16}{plain['steps']:>6}{plain['cell']:>8.3f}{plain['wall']:>9.3f}{overlap['wall']:>10.3f}"
              f"{statistics.fmean([plain['measure'], overlap['measure']]):>11.1f}"
              f"{statistics.fmean([plain['refit'], overlap['refit']]):>9.1f}"
              f"{1e3 * (plain['wall'] - plain['cell']):>15.1f}{1e3 * (overlap['wall'] - overlap['cell']):>17.1f}"
              f"{100 * (1 - overlap['wall'] / plain['wall']):>8.1f}")


if __name__ == "__main__":
    main()
