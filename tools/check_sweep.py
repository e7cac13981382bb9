"""The check's figures over many simulated cells: per seed, calibrate (calibrate-cell's routines at the cell
file's defaults), then check in later runs of the same seed, with no drift and
with each drift scenario of the issue, judged against the drift the world applied.

    .venv/bin/python tools/check_sweep.py [--seeds 0 50] [--jobs 2] [--scenarios none cam1 nozzle cam2 touch-up]

Prints one line per seed and scenario, then per scenario: how many seeds gave a drift verdict, how many named
exactly the drifted target, how many estimated it within 1 µm (cam2: 5 µm, cam3: 3 µm), and for the touch-up the
verification mean against the virtual grid's and the cell time against 10 % of the virtual grid's.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = {  # name: (drift, check parameters, the target that drifted, estimate bound µm)
    "none": ({}, {}, None, None),
    "cam1": ({"cam1": {"map_shift_um": [3.0, 0.0]}}, {"targets": "cam1,nozzle"}, "cam1", 1.0),
    "nozzle": ({"nozzle": {"offset_change_um": [5.0, 0.0]}}, {"targets": "cam1,nozzle"}, "nozzle", 1.0),
    "cam2": ({"cam2": {"map_shift_um": [0.0, 15.0]}}, {}, "cam2", 5.0),
    "cam3": ({"cam3": {"map_shift_um": [10.0, 0.0]}}, {}, "cam3", 3.0),
    "touch-up": ({"cam1": {"map_shift_um": [10.0, 0.0]}}, {"targets": "cam1", "update": True}, "cam1", 1.0),
}


def one_seed(seed: int, out: Path, scenarios: list[str]) -> list[dict]:
    from cellctl.config import load_cell_file
    from cellctl.core.runs import run_routine
    from cellctl.stores.calibrations import CalibrationStore

    config, text = load_cell_file(ROOT / "config" / "sim-microcell.yaml")
    folder = out / str(seed)
    shutil.rmtree(folder, ignore_errors=True)
    store = CalibrationStore(folder / "store")
    calibrations = {r: run_routine(r, config, text, folder / r, seed=seed, store=store)
                    for r in ("virtual-grid", "rotation-sweep", "virtual-grid-area2", "onboard-camera")}
    store.close()
    lines = []
    for name in scenarios:
        drift, params, target, bound = SCENARIOS[name]
        sim = config.sim.model_validate(dict(config.sim.model_dump(), drift=drift))
        shutil.copytree(folder / "store", folder / f"store-{name}")
        result = run_routine("calibration-check", config.model_copy(update={"sim": sim}), text, folder / f"check-{name}",
                             seed=seed, store=CalibrationStore(folder / f"store-{name}"), overrides=params)
        line = {"seed": seed, "scenario": name, "verdict": result["verdict"], "drifted": result["drifted"],
                "cell_time_s": result["cell_time_s"]}
        if target:
            est, true = result["stats"]["drift"][target], result["truth"][target]
            line["error_um"] = math.hypot(est["dx_um"] - true["dx_um"], est["dy_um"] - true["dy_um"])
            line["bound_um"] = bound
        if name == "touch-up":
            grid = calibrations["virtual-grid"]
            line["verification_ratio"] = (result["stats"]["touch_up"].get(target, {}).get("mean_um", math.inf)
                                          / grid["stats"]["verification"]["mean_um"])
            line["time_ratio"] = result["cell_time_s"] / grid["cell_time_s"]
        lines.append(line)
        print(json.dumps(line), flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs=2, default=(0, 20), metavar=("FIRST", "END"))
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    parser.add_argument("--out", default="/tmp/check-sweep")
    args = parser.parse_args()
    out = Path(args.out)
    with ProcessPoolExecutor(args.jobs) as pool:
        lines = [line for lines in pool.map(one_seed, range(*args.seeds), [out] * (args.seeds[1] - args.seeds[0]),
                                            [args.scenarios] * (args.seeds[1] - args.seeds[0])) for line in lines]
    print()
    for name in args.scenarios:
        runs = [r for r in lines if r["scenario"] == name]
        target = SCENARIOS[name][2]
        drift = sum(r["verdict"] == "drift" for r in runs)
        text = f"{name:9s} {len(runs)} seeds: drift verdict in {drift}"
        if target:
            exact = sum(r["drifted"] == [target] for r in runs)
            close = sum(r["error_um"] <= r["bound_um"] for r in runs)
            text += f", exactly {target} in {exact}, estimate within {SCENARIOS[name][3]:g} µm in {close}"
        if name == "touch-up":
            ok = sum(r["verification_ratio"] <= 1.2 for r in runs)
            worst = max(r["time_ratio"] for r in runs)
            text += f", verification <= 1.2 x virtual grid's in {ok}, cell time <= {worst:.3f} x virtual grid's"
        print(text)


if __name__ == "__main__":
    main()
