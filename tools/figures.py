#!/usr/bin/env python3
"""The figures a refactoring must leave unchanged: run them, or compare two runs of them.

    .venv/bin/python tools/figures.py run OUT        # virtual-grid seed 3, calibrate-cell seed 5,
                                                     # csm-positioning seed 4, vr-experiments seed 2
    .venv/bin/python tools/figures.py compare A B    # every result.json's stats, model and cell time,
                                                     # equal to 6 significant digits; exit 1 if not

Each run uses its own calibration store under OUT, so nothing of the user's is touched.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RUNS = {  # name -> (routine or sequence, cell file, seed)
    "vg3": ("virtual-grid", "config/sim-microcell.yaml", 3),
    "cc5": ("calibrate-cell", "config/sim-microcell.yaml", 5),
    "csm4": ("csm-positioning", "config/sim-irb120-csm.yaml", 4),
    "vr2": ("vr-experiments", "config/sim-vr.yaml", 2),
}
KEYS = ("stats", "model", "cell_time_s")


def run(out: Path) -> int:
    out.mkdir(parents=True, exist_ok=True)
    def one(name: str) -> tuple[str, int]:
        routine, config, seed = RUNS[name]
        # -m from this checkout's root: the code measured is this tree's, whatever the venv's install points at
        cmd = [sys.executable, "-m", "cellctl.cli", "run", routine, "--config", str(ROOT / config), "--seed", str(seed), "--out",
               str(out / name), "--store", str(out / f"store-{name}"), "--quiet"]
        with open(out / f"{name}.log", "w") as log:
            return name, subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)

    with ThreadPoolExecutor(2) as pool:
        codes = dict(pool.map(one, RUNS))
    for name, code in codes.items():
        print(f"{name}: {'ok' if code == 0 else f'exit {code}, see {out / name}.log'}")
    return 0 if all(c == 0 for c in codes.values()) else 1


def differences(a, b, where: str = "") -> list[str]:
    """Where two JSON values differ (floats compared to 6 significant digits)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{where}.{k}: only in {'A' if k in a else 'B'}" for k in sorted(set(a) ^ set(b))]
        for k in sorted(set(a) & set(b)):
            out += differences(a[k], b[k], f"{where}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items vs {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{where}[{i}]")]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        if math.isnan(a) and math.isnan(b) or a == b:
            return []
        return [] if f"{a:.6g}" == f"{b:.6g}" else [f"{where}: {a!r} vs {b!r}"]
    return [] if a == b else [f"{where}: {a!r} vs {b!r}"]


def compare(a: Path, b: Path) -> int:
    found = 0
    files = sorted(p.relative_to(a) for p in a.glob("**/result.json") if "store-" not in str(p))
    if not files:
        print(f"{a}: no result.json")
        return 1
    for rel in files:
        if not (b / rel).is_file():
            print(f"{rel}: missing in {b}")
            found += 1
            continue
        ra, rb = (json.loads((d / rel).read_text()) for d in (a, b))
        diffs = [d for k in KEYS for d in differences(ra.get(k), rb.get(k), k)]
        print(f"{rel}: {'equal' if not diffs else f'{len(diffs)} differences'}")
        for d in diffs[:20]:
            print(f"    {d}")
        found += bool(diffs)
    return 1 if found else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    sub.add_parser("run").add_argument("out", type=Path)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = parser.parse_args(argv)
    return run(args.out) if args.cmd == "run" else compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
