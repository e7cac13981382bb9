"""Load test of the cell daemon on loopback: N clients poll the status and follow the event stream
while a job runs; prints the latencies and shows the job's cell time and result unchanged.

    .venv/bin/python tools/load_daemon.py [--clients 50] [--poll-interval 0.1] [--realtime 0.1]

Starts its own daemon (simulated micro cell, temporary store, ephemeral port), runs the
same small virtual-grid job twice with the same seed, once alone and once under load,
and compares the two (every sample, the fit, the cell time).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the tests' helpers: tests.support

from tests.support.daemon import DaemonProcess, write_cell_file
from tests.support.daemon_load import compare_under_load, percentiles  # the load, shared with the test


async def main_async(args) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        daemon = DaemonProcess(write_cell_file(Path(tmp), realtime_factor=args.realtime)).start()
        try:
            rep = await compare_under_load(daemon.url, daemon.token, clients=args.clients,
                                           poll_interval=args.poll_interval)
        finally:
            daemon.terminate()
            daemon.log.close()
    print(f"job alone: {rep.wall_alone:.2f} s wall, cell time {rep.alone['result']['cell_time_s']:.3f} s")
    if args.debug:
        for t, lat in sorted(rep.slow, key=lambda x: -x[1])[:10]:
            print(f"slow GET /cell at {t - rep.t_job:+.2f} s of the job: {lat * 1e3:.0f} ms")
    print(f"job under load ({args.clients} clients polling /cell every {args.poll_interval} s and "
          f"{args.clients} following /events): {rep.wall_loaded:.2f} s wall, "
          f"cell time {rep.loaded['result']['cell_time_s']:.3f} s")
    print(f"GET /cell latency       {percentiles(rep.status_latencies)}")
    print(f"event delivery latency  {percentiles(rep.event_delays)}")
    counts = rep.events_per_stream
    print(f"events per stream: min {min(counts, default=0)}  max {max(counts, default=0)}; errors {len(rep.errors)}")
    for e in rep.errors[:5]:
        print("  ", e)
    for what, ok in rep.same.items():
        print(f"{what:22s} {'unchanged' if ok else 'CHANGED'}")
    return 0 if all(rep.same.values()) and not rep.errors else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--poll-interval", type=float, default=0.1, help="seconds between a client's status polls")
    parser.add_argument("--debug", action="store_true", help="print when the slowest status polls happened")
    parser.add_argument("--realtime", type=float, default=0.1, help="the sim's realtime_factor (wall s per cell s)")
    return asyncio.run(main_async(parser.parse_args()))


if __name__ == "__main__":
    sys.exit(main())
