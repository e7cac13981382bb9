"""Calibration downtime (issue 31): cell time and figure of each routine of a sequence, today's plan against the
accuracy-targeted one, and the floor.

    .venv/bin/python tools/bench_downtime.py [--seeds 0-9] [--sequence calibrate-cell] [--out DIR]

Per routine, over the seeds (simulated cell, the cell file's defaults; cell time is the simulated clock's:
motion at the cell file's speeds, settling, exposure and read-out):

- today: the routine's whole budget (a targeted routine run with a target it cannot meet: today's fixed plan,
  its points in the targeted plan's order);
- targeted: its defaults (a targeted routine stops once its predicted accuracy meets today's figure);
- floor: the fewest samples the target needs times the least time a sample takes. The fewest calibration
  samples come from the run's own covariance: its calibration share of the predicted error scales as
  1/sqrt(samples), so n_min = n * model^2 / (goal^2 - floor^2) at the stop (`targeted.py`); the other steps
  (verification, placing) count as many as the plan has. The least time per sample is the quickest step of
  that kind the run took (exposure + read-out + the shortest move at full speed + settling);
- ratios of each to the floor.

The figure is the verification mean radial error (µm). Timings are printed, never asserted.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from collections import defaultdict
from pathlib import Path

from calibration.routines import routine_class, sequence
from calibration.routines.base import Step, TargetsAccuracy

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.run_folder import RunFolder

ROOT = Path(__file__).resolve().parents[1]
UNREACHABLE_UM = 1e-3  # a target no cell meets: the whole budget, today's plan


def seeds_of(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def step_times(folder: Path) -> dict[str, list[float]]:
    """Seconds each step took, by its kind (its `set`, else its action's rows' set), the first step left out
    (it starts wherever the arm was)."""
    rows = RunFolder(folder).samples()
    ends: dict[int, tuple[float, str]] = {}
    for r in rows:
        ends[int(r["step"])] = (float(r["cell_time_s"]), str(r.get("set") or "step"))
    times: dict[str, list[float]] = defaultdict(list)
    last = None
    for step in sorted(ends):
        t, kind = ends[step]
        if last is not None:
            times[kind].append(t - last)
        last = t
    return times


def budget_kind(routine, folder: Path) -> str | None:
    """The `set` of the rows of a targeted routine's budget steps (its calibration samples: "cal", "reg", "pose")."""
    run = RunFolder(folder)
    budget = {s["index"] for s in run.manifest()["plan"] if routine.budget(Step.from_dict(s))}
    kinds = {str(r.get("set")) for r in run.samples() if int(r["step"]) in budget}
    return kinds.pop() if len(kinds) == 1 else None


def floor_of(result: dict, times: dict[str, list[float]], budget_kind: str | None) -> tuple[float, int | None]:
    """(floor seconds, fewest calibration samples) of one run."""
    target = result["stats"].get("target")
    n_min = None
    if target and budget_kind and target.get("floor_um") is not None:
        n, floor, model, goal = target["samples"], target["floor_um"], target["model_um"], target["goal_um"]
        room = goal**2 - floor**2
        n_min = math.ceil(n * model**2 / room) if room > 0 else None
    total = 0.0
    for kind, ts in times.items():
        count = len(ts) + (1 if kind == next(iter(times)) else 0)  # the first step, left out of the times
        if kind == budget_kind and n_min is not None:
            count = n_min
        total += count * min(ts)
    return total, n_min


def run(config, text, seq: str, seed: int, out: Path, today: bool) -> dict[str, dict]:
    store = CalibrationStore(out / "store")
    results = {}
    try:
        for k, item in enumerate(sequence(seq).items):
            routine = routine_class(item.routine)()
            overrides = dict(item.params)
            targeted = isinstance(routine, TargetsAccuracy)
            if today and targeted:
                overrides["target_um"] = UNREACHABLE_UM
            folder = out / f"{k + 1:02d}-{item.name}"
            result = run_routine(item.routine, config, text, folder, seed=seed, store=store, overrides=overrides)
            times = step_times(folder)
            floor, n_min = floor_of(result, times, budget_kind(routine, folder) if targeted else None)
            results[item.name] = {"time": result["cell_time_s"], "n": len(times) and sum(map(len, times.values())) + 1,
                                  "figure": result["stats"].get("verification", {}).get("mean_um"),
                                  "n_cal": result["stats"].get("target", {}).get("samples"), "n_min": n_min,
                                  "floor": floor, "model": result["model"]}
    finally:
        store.close()
    return results


def mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.fmean(values) if values else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0-9", help="simulation seeds, e.g. 0-9 or 1,3,5")
    parser.add_argument("--sequence", default="calibrate-cell")
    parser.add_argument("--config", default=str(ROOT / "config" / "sim-microcell.yaml"))
    parser.add_argument("--out", default=None, help="where the runs go (default: a temporary folder)")
    parser.add_argument("--targeted-only", action="store_true", help="skip today's plans (their columns show -)")
    args = parser.parse_args()
    config, text = load_cell_file(args.config)
    out = Path(args.out or tempfile.mkdtemp(prefix="bench-downtime-"))
    seeds = seeds_of(args.seeds)
    modes = ("targeted",) if args.targeted_only else ("today", "targeted")
    runs = {mode: {s: run(config, text, args.sequence, s, out / mode / f"seed{s}", mode == "today") for s in seeds}
            for mode in modes}
    items = sequence(args.sequence).names
    print(f"{args.sequence} on {Path(args.config).name}, seeds {args.seeds} (means over the seeds; runs in {out})")
    head = (f"{'routine':<20}{'today s':>9}{'fig µm':>8}{'target s':>9}{'fig µm':>8}{'Δfig %':>8}{'n cal':>8}"
            f"{'n min':>7}{'floor s':>9}{'today/fl':>9}{'targ/fl':>8}")
    print(head)
    print("-" * len(head))
    total = {"today": 0.0, "targeted": 0.0, "floor": 0.0}

    def cell(v, width, fmt):
        return f"{'-' if v is None else format(v, fmt):>{width}}"

    def ratio(a, b):
        return None if a is None or not b else a / b

    for item in items:
        t = {m: mean(runs[m][s][item]["time"] for s in seeds) if m in runs else None for m in ("today", "targeted")}
        f = {m: mean(runs[m][s][item]["figure"] for s in seeds) if m in runs else None for m in ("today", "targeted")}
        floor = mean(runs["targeted"][s][item]["floor"] for s in seeds)
        n_cal = mean(runs["targeted"][s][item]["n_cal"] for s in seeds)
        n_min = mean(runs["targeted"][s][item]["n_min"] for s in seeds)
        change = 100 * (f["targeted"] / f["today"] - 1) if f["today"] and f["targeted"] else None
        total = {"today": total["today"] + (t["today"] or 0.0), "targeted": total["targeted"] + t["targeted"],
                 "floor": total["floor"] + floor}
        print(f"{item:<20}{cell(t['today'], 9, '.1f')}{cell(f['today'], 8, '.2f')}{cell(t['targeted'], 9, '.1f')}"
              f"{cell(f['targeted'], 8, '.2f')}{cell(change, 8, '+.1f')}{cell(n_cal, 8, '.1f')}{cell(n_min, 7, '.1f')}"
              f"{cell(floor, 9, '.1f')}{cell(ratio(t['today'], floor), 9, '.2f')}"
              f"{cell(ratio(t['targeted'], floor), 8, '.2f')}")
    print("-" * len(head))
    today = total["today"] if "today" in runs else None
    worst = max(sum(runs["targeted"][s][i]["time"] for i in items) for s in seeds)
    print(f"{args.sequence:<20}{cell(today, 9, '.1f')}{'':>8}{total['targeted']:>9.1f}{'':>8}{'':>8}{'':>8}{'':>7}"
          f"{total['floor']:>9.1f}{cell(ratio(today, total['floor']), 9, '.2f')}"
          f"{cell(ratio(total['targeted'], total['floor']), 8, '.2f')}   (targeted, worst seed: {worst:.1f} s)")
    if "today" in runs:
        offsets = [(runs["targeted"][s][i]["model"], runs["today"][s][i]["model"]) for s in seeds for i in items
                   if runs["targeted"][s][i]["model"].get("kind") == "tool-offset"]
        if offsets:
            delta = [math.hypot(a["dx_um"] - b["dx_um"], a["dy_um"] - b["dy_um"]) for a, b in offsets]
            print(f"tool offset, targeted against today's plan: |Δ| mean {statistics.fmean(delta):.2f} µm, "
                  f"max {max(delta):.2f} µm")

if __name__ == "__main__":
    main()
