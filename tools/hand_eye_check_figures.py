"""Judge `calibration-check targets=hand-eye:<camera>` on the simulated UR5e cell against the hidden truth.

For each seed: calibrate the wrist camera (hand-eye at the cell file's defaults, stored), then check it twice on the
same cell: as it is (a drift verdict is a false alarm) and with the camera bumped on its mount (the world's
`sim.drift` knob) by --bump-mm in a direction and --bump-deg about an axis drawn per seed. A bump is found when the
verdict is drift and attributed when the camera, and only the camera, is named; its drift estimate is set against
the true bump (both: the camera's shift along the flange frame's axes and its turn about its own centre).
--board moves the table's board instead (then attributed means the board alone).

    .venv/bin/python tools/hand_eye_check_figures.py [--seeds 0 20] [--bump-mm 0.5] [--bump-deg 0.1] [--poses 6]
                                                     [--board] [--out DIR]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import time
from pathlib import Path

import numpy as np

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore

ROOT = Path(__file__).resolve().parents[1]
TARGET = "hand-eye:wrist"


def bump_of(seed: int, mm: float, deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The bump of a seed: `mm` along a random direction, `deg` about a random axis (flange frame)."""
    rng = np.random.default_rng([seed, 2027])
    t, r = rng.normal(size=3), rng.normal(size=3)
    return t / np.linalg.norm(t) * mm, r / np.linalg.norm(r) * deg


def with_drift(config, drift: dict):
    sim = config.sim.model_validate(dict(config.sim.model_dump(), drift=drift))
    return config.model_copy(update={"sim": sim})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs=2, default=(0, 20), metavar=("FIRST", "END"))
    parser.add_argument("--bump-mm", type=float, default=0.5)
    parser.add_argument("--bump-deg", type=float, default=0.1)
    parser.add_argument("--poses", type=int, default=None, help="hand_eye_poses of the check (default: its own)")
    parser.add_argument("--board", action="store_true", help="move the table's board instead of the camera")
    parser.add_argument("--out", default="/tmp/hand-eye-check-figures")
    args = parser.parse_args()
    config, text = load_cell_file(ROOT / "config" / "sim-ur5e-handeye.yaml")
    moved, part = ("table", "board") if args.board else ("wrist", "camera")
    overrides = {"targets": TARGET, **({"hand_eye_poses": args.poses} if args.poses else {})}
    found, attributed, alarms, t_err, r_err, t_z, r_z, quiet_t, quiet_r, wall, cell = ([] for _ in range(11))
    for seed in range(*args.seeds):
        out = Path(args.out) / str(seed)
        shutil.rmtree(out, ignore_errors=True)
        store = CalibrationStore(out / "store")
        try:
            cal = run_routine("hand-eye", config, text, out / "hand-eye", seed=seed, store=store)
            t0 = time.perf_counter()
            quiet = run_routine("calibration-check", config, text, out / "check-as-is", seed=seed, store=store,
                                overrides=overrides)
            wall.append(time.perf_counter() - t0)
            t_true, r_true = bump_of(seed, args.bump_mm, args.bump_deg)
            drift = {moved: {"translation_mm": t_true.tolist(), "rotation_deg": r_true.tolist()}}
            bumped = run_routine("calibration-check", with_drift(config, drift), text, out / "check-bumped",
                                 seed=seed, store=store, overrides=overrides)
        finally:
            store.close()
        cell.append(bumped["cell_time_s"])
        alarms.append(quiet["verdict"] == "drift")
        q = quiet["stats"]["drift"][TARGET][part]
        quiet_t.append(q["shift_mm"])
        quiet_r.append(q["turn_deg"])
        d = bumped["stats"]["drift"][TARGET]
        est = d[part]
        found.append(bumped["verdict"] == "drift")
        attributed.append(bumped["drifted"] == [TARGET] and d["attributed_to"] == [part])
        dt = np.asarray(est["translation_mm"]) - t_true
        dr = np.asarray(est["rotation_deg"]) - r_true
        t_err.append(float(np.linalg.norm(dt)))
        r_err.append(float(np.linalg.norm(dr)))
        t_z.append(float(np.sqrt(np.mean((dt / np.asarray(est["translation_std_mm"])) ** 2))))
        r_z.append(float(np.sqrt(np.mean((dr / np.asarray(est["rotation_std_deg"])) ** 2))))
        truth = cal.get("truth", {})
        print(f"seed {seed}: calibration X off by {truth.get('hand_eye_translation_error_mm', float('nan')):.3f} mm"
              f" | as is: {quiet['verdict']} (p {quiet['stats']['test'][TARGET]['p_value']:.3g}, {part} reads "
              f"{q['shift_mm']:.3f} mm {q['turn_deg']:.4f} deg) | bumped {np.round(t_true, 3).tolist()} mm "
              f"{np.round(r_true, 4).tolist()} deg: {bumped['verdict']} {d['attributed_to']} (p "
              f"{bumped['stats']['test'][TARGET]['p_value']:.2g}), estimate {np.round(est['translation_mm'], 3).tolist()}"
              f" mm {np.round(est['rotation_deg'], 4).tolist()} deg, off by {t_err[-1]:.3f} mm {r_err[-1]:.4f} deg",
              flush=True)
    n = len(found)
    print()
    print(f"{part} moved {args.bump_mm:g} mm / {args.bump_deg:g} deg (random direction per seed), seeds "
          f"{args.seeds[0]}-{args.seeds[1] - 1}, check at {overrides.get('hand_eye_poses', 'its default')} poses:")
    print(f"  found {sum(found)} of {n}; attributed to the {part} alone {sum(attributed)} of {n}")
    print(f"  drift estimate against the true move: shift off by median {statistics.median(t_err):.3f} mm, worst "
          f"{max(t_err):.3f} mm; turn off by median {statistics.median(r_err):.4f} deg, worst {max(r_err):.4f} deg")
    print(f"  error over the reported 1-sigma (RMS over the axes), median: shift {statistics.median(t_z):.2f}, "
          f"turn {statistics.median(r_z):.2f}")
    print(f"nothing moved: {sum(alarms)} false alarm(s) in {n}; the {part} read as moved by median "
          f"{statistics.median(quiet_t):.3f} mm (worst {max(quiet_t):.3f}), {statistics.median(quiet_r):.4f} deg "
          f"(worst {max(quiet_r):.4f})")
    print(f"a check: {statistics.median(cell):.1f} s of cell time, {statistics.median(wall):.1f} s of wall time "
          "(median)")


if __name__ == "__main__":
    main()
