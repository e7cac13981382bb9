"""Benchmark of the CLI's start-up: each command in a fresh process, as a user types it, against the 0.3 s target.

    .venv/bin/python tools/bench_startup.py [--rounds N] [--url URL]

- `cellctl --help`;
- `cellctl status --url URL`: by default a URL where nothing listens (the refusal comes at once, so this times
  the import path and the request); give a running daemon's URL (and $CELLCTL_TOKEN) to time a real answer;
- for comparison: a bare `python -c pass` (the interpreter's own start-up); `status` finding its token through
  `--config` (the cell file is read and validated for its store: pydantic, the sim world's configs); `cellctl
  check` (the cell file with the routines it names).

Best of N rounds (the machine may be shared; the best round is the least disturbed one), printed, never asserted.
What a command imports is tested instead (tests/cli/test_cli_edges.py: no numpy, scipy, cv2, pydantic, fastapi).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from bench_timing import best_of  # tools/bench_timing.py

ROOT = Path(__file__).resolve().parent.parent
MICROCELL = ROOT / "config" / "sim-microcell.yaml"
TARGET_S = 0.3
CELLCTL = [sys.executable, "-m", "cellctl.cli"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--url", default="http://127.0.0.1:1", help="the daemon for `status` (default: none "
                                                                      "listening)")
    args = parser.parse_args()
    env = {k: v for k, v in os.environ.items() if k not in ("CELLCTL_URL", "CELLCTL_STORE")}
    commands = [("python -c pass (the interpreter alone)", [sys.executable, "-c", "pass"], False),
                ("cellctl --help", [*CELLCTL, "--help"], True),
                (f"cellctl status --url {args.url}", [*CELLCTL, "status", "--url", args.url], True),
                ("  the same, the token found through --config (no $CELLCTL_STORE)",
                 [*CELLCTL, "status", "--url", args.url, "--config", str(MICROCELL)], False),
                ("cellctl check --config config/sim-microcell.yaml",
                 [*CELLCTL, "check", "--config", str(MICROCELL)], False)]
    print(f"start-up, best of {args.rounds} fresh processes (target for the marked ones: {TARGET_S} s)")
    for name, argv, targeted in commands:
        seconds = best_of(lambda argv=argv: subprocess.run(argv, env=env, capture_output=True, cwd=ROOT),
                          args.rounds)
        verdict = ("within" if seconds <= TARGET_S else "OVER") + f" the {TARGET_S} s target" if targeted else ""
        print(f"  {name:66s} {seconds:6.3f} s  {verdict}")


if __name__ == "__main__":
    main()
