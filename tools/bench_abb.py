"""Command round trip of the ABB driver on loopback: ping and get-cartesian against the protocol simulator.

The original public client (open_abb abb.py) takes at least 80 ms per call; the
target here is a median of 2 ms or less per command, in either reply dialect
(`--dialect open_abb`: no terminator, framed by field count; `cellctl`: ended by '#').
Prints pass/fail per command and exits 1 if a median misses the target. By default
the simulator runs in its own process (no GIL shared with the client); --in-process
runs it in a thread.

    .venv/bin/python tools/bench_abb.py [--calls 2000] [--dialect open_abb|cellctl] [--in-process]
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import yaml

from drivers.arms.abb import AbbArm
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.servers import connect_when_up, free_ports
from drivers.sim.servers.abb import serve

ORIGINAL_CLIENT_MS = 80.0
TARGET_MEDIAN_MS = 2.0


def _serve_process(cell: dict, ports: list[int], stop, dialect: str) -> None:
    serve(SimWorldConfig(**cell["sim"]), "127.0.0.1", ports[0], ports[1], stop=stop, limits=cell["arm"]["limits"],
          options={"reply_dialect": dialect})


def _measure(call, n: int) -> list[float]:
    for _ in range(min(100, n)):  # warm up
        call()
    times = []
    for _ in range(n):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return times


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--in-process", action="store_true", help="run the simulator in a thread of this process")
    parser.add_argument("--cell", default=str(ROOT / "config" / "sim-microcell.yaml"))
    parser.add_argument("--dialect", choices=("open_abb", "cellctl"), default="open_abb",
                        help="the simulator's reply format (default: the public server's)")
    args = parser.parse_args()

    cell = yaml.safe_load(Path(args.cell).read_text())
    ports = free_ports(2)
    if args.in_process:
        stop = threading.Event()
        runner = threading.Thread(target=_serve_process, args=(cell, ports, stop, args.dialect), daemon=True)
    else:
        stop = multiprocessing.Event()
        runner = multiprocessing.Process(target=_serve_process, args=(cell, ports, stop, args.dialect), daemon=True)
    runner.start()
    arm = AbbArm.create("abb", {"host": "127.0.0.1", "motion_port": ports[0], "logger_port": ports[1],
                                "limits": cell["arm"]["limits"], "linear_axes": [1, 2, 3]})
    try:
        connect_when_up(arm, timeout_s=10.0)
        where = "thread" if args.in_process else "process"
        print(f"ABB driver <-> simulator ({where}, {args.dialect} replies) on loopback, {args.calls} calls each")
        print(f"{'command':<16}{'median ms':>10}{'p99 ms':>10}{'calls/s':>10}{'vs 80 ms':>10}  "
              f"median <= {TARGET_MEDIAN_MS:g} ms")
        failed = []
        for name, call in (("ping (00)", arm.ping), ("cartesian (03)", arm.pose), ("joints (04)", arm.joints)):
            times = sorted(_measure(call, args.calls))
            median = statistics.median(times) * 1e3
            p99 = times[int(0.99 * (len(times) - 1))] * 1e3
            rate = len(times) / sum(times)
            verdict = "pass" if median <= TARGET_MEDIAN_MS else "FAIL"
            if verdict == "FAIL":
                failed.append(name)
            print(f"{name:<16}{median:>10.3f}{p99:>10.3f}{rate:>10.0f}{ORIGINAL_CLIENT_MS / median:>9.0f}x  {verdict}")
        print(f"the original client sleeps/waits >= {ORIGINAL_CLIENT_MS:.0f} ms per call")
        print(f"FAIL: median above {TARGET_MEDIAN_MS:g} ms for {', '.join(failed)}" if failed
              else f"PASS: every median <= {TARGET_MEDIAN_MS:g} ms")
        return 1 if failed else 0
    finally:
        arm.close()
        stop.set()
        runner.join(timeout=5.0)


if __name__ == "__main__":
    sys.exit(main())
