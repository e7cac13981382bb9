"""A long soak with faults: the daemons of the micro cell on its fakes and through the UR and ABB protocol
simulators run many small jobs while faults fall on a seeded schedule, and each job is acknowledged and resumed
until it is done. Prints what was lost or duplicated (locally and in the plant database), any motion without an
acknowledgement, the daemons' memory, files, threads and children over time, and the API's read latency.

    .venv/bin/python tools/soak.py [--jobs 500] [--seed 0] [--kinds fake,ur,abb] [--readers 4] [--long-lived abb]
                                [--keep DIR]

Starts its own PostgreSQL and Mosquitto (Debian's, tools/ensure-system), mounts a tmpfs for the stores (root;
without it the disk-full episodes are left out, saying so) and a wall clock it can step (a C compiler).
The engine is tests/support/soak.py, which the suite's short soak (tests/fleet/test_soak.py) shares.
Exit status 1 when anything was lost, duplicated, moved unasked, or a job never finished.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the tests' helpers: tests.support
# the simulators' and plant servers' ports from a block of its own (tests/support/ports.py): the suite's workers
# take gw0-gw5's, so the soak can run beside it
os.environ.setdefault("PYTEST_XDIST_WORKER", "gw6")

from tests.support.servers import MosquittoServer, PostgresServer  # noqa: E402
from tests.support.soak import KINDS, Soak, SoakSettings  # noqa: E402


def kinds(text: str) -> tuple[str, ...]:
    got = tuple(k.strip() for k in text.split(",") if k.strip())
    bad = [k for k in got if k not in KINDS]
    if bad or not got:
        raise argparse.ArgumentTypeError(f"{text!r}: allowed cell kinds are {', '.join(KINDS)} (comma-separated)")
    return got


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=500, help="jobs in all, taken in turn by the cells")
    parser.add_argument("--seed", type=int, default=0, help="draws the faults")
    parser.add_argument("--kinds", type=kinds, default=KINDS, help="cells: fake, ur, abb (comma-separated)")
    parser.add_argument("--readers", type=int, default=4, help="background clients reading the status")
    parser.add_argument("--long-lived", type=kinds, default=("abb",), help="cells whose daemon is never killed, so "
                        "that one process lives through the soak (its growth is the figure); default abb")
    parser.add_argument("--warm-up", type=int, default=10, help="jobs per daemon before growth is measured")
    parser.add_argument("--keep", type=Path, help="keep the stores and logs in this folder")
    args = parser.parse_args()
    if args.jobs < 1:
        parser.error("--jobs: at least 1")
    # stopped (Ctrl-C, kill): through the finally blocks, so the daemons, servers and the tmpfs go too
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    folder = args.keep or Path(tempfile.mkdtemp(prefix="cellctl-soak-"))
    folder.mkdir(parents=True, exist_ok=True)
    postgres, mosquitto = PostgresServer().start(), MosquittoServer().start()
    t0 = time.monotonic()
    try:
        settings = SoakSettings(jobs=args.jobs, seed=args.seed, kinds=args.kinds, readers=args.readers,
                                long_lived=args.long_lived, ur_host="127.0.0.48",  # not the suite's soak's
                                keep_stores=args.keep is not None)
        report = Soak(folder, settings, postgres, mosquitto,
                      log=lambda line: print(f"[{time.monotonic() - t0:7.1f} s] {line}", flush=True)).run()
    finally:
        postgres.close()
        mosquitto.close()
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)
    print()
    for line in report.lines(warm_up=args.warm_up):
        print(line)
    problems = report.problems()
    for p in problems:
        print("PROBLEM:", p)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
