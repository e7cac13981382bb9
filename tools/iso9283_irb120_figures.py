"""ISO 9283 on the IRB 120 cell measured by its fixed cameras, for a range of seeds, against the hidden truth (issue
28: "AP and RP measured by the cameras against the truth: both within 15 % (or 5 µm)").

Per seed: `arm-kinematics` (fixed cameras), then `iso9283` twice (30 cycles by default): the arm as its controller
moves it (`moves=controller`, before) and through the arm calibration (after). Printed per seed and test: the worst
pose's AP and RP, measured and true (µm), the largest |measured - true| over the five poses (µm), and how many of the
ten figures (AP and RP of P1-P5) meet the goal; then the totals.

    .venv/bin/python tools/iso9283_irb120_figures.py [--seeds 0 10] [--cycles 30] [--frames N] [--out DIR]
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore

ROOT = Path(__file__).resolve().parents[1]
CELL = ROOT / "config" / "sim-irb120-csm.yaml"
POSES = ("P1", "P2", "P3", "P4", "P5")


def within(measured: float, truth: float) -> bool:
    return abs(measured - truth) <= max(0.15 * truth, 0.005)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs=2, default=(0, 10), metavar=("FIRST", "STOP"))
    ap.add_argument("--cycles", type=int, default=30)
    ap.add_argument("--frames", type=int, default=None, help="frames per camera per visit (default: the cell file's)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/iso9283-irb120-figures"))
    args = ap.parse_args()
    config, text = load_cell_file(CELL)
    print(f"{'seed':>4} {'test':>10} {'AP meas':>8} {'AP true':>8} {'|dAP|':>6} {'RP meas':>8} {'RP true':>8} "
          f"{'|dRP|':>6} {'met':>5} {'cell s':>6}   (µm; worst pose; met: of AP and RP of P1-P5)")
    met = {(moves, f): 0 for moves in ("controller", "calibrated") for f in ("ap_mm", "rp_mm")}
    seeds = range(*args.seeds)
    for seed in seeds:
        out = args.out / f"seed{seed}"
        shutil.rmtree(out, ignore_errors=True)
        store = CalibrationStore(out / "store")
        run_routine("arm-kinematics", config, text, out / "arm", seed=seed, store=store)
        for moves in ("controller", "calibrated"):
            r = run_routine("iso9283", config, text, out / moves, seed=seed, store=store,
                            overrides={"cycles": args.cycles, "moves": moves,
                                       **({"frames": args.frames} if args.frames else {})})
            s, t = r["stats"], r["truth"]
            for f in ("ap_mm", "rp_mm"):
                met[moves, f] += sum(within(s[f][p], t[f][p]) for p in POSES)
            ok = sum(within(s[f][p], t[f][p]) for f in ("ap_mm", "rp_mm") for p in POSES)
            gap = {f: max(abs(s[f][p] - t[f][p]) for p in POSES) * 1e3 for f in ("ap_mm", "rp_mm")}
            print(f"{seed:>4} {moves:>10} {s['ap_mm']['worst'] * 1e3:>8.1f} {t['ap_mm']['worst'] * 1e3:>8.1f} "
                  f"{gap['ap_mm']:>6.1f} {s['rp_mm']['worst'] * 1e3:>8.1f} {t['rp_mm']['worst'] * 1e3:>8.1f} "
                  f"{gap['rp_mm']:>6.1f} {ok:>3}/10 {r['cell_time_s']:>6.0f}", flush=True)
        store.close()
    for (moves, f), ok in met.items():
        print(f"{moves} {f[:2].upper()}: {ok} of {5 * len(seeds)} poses within 15 % (or 5 µm) of the truth")


if __name__ == "__main__":
    main()
