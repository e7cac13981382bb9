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
import json
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "daemon"))

from daemon_helpers import SMALL, DaemonProcess, write_cell_file

SLOW: list = []
SSL = __import__("ssl").create_default_context()  # one for all clients: making 100 costs seconds of CPU
MEASURING = asyncio.Event()
JOB = {"routine": "virtual-grid", "params": SMALL, "seed": 7}


def percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    v = sorted(values)
    pick = lambda q: v[min(int(q * len(v)), len(v) - 1)] * 1e3
    return (f"n {len(v):6d}  p50 {pick(0.5):7.1f} ms  p95 {pick(0.95):7.1f} ms  p99 {pick(0.99):7.1f} ms  "
            f"max {v[-1] * 1e3:7.1f} ms")


async def run_job(client: httpx.AsyncClient) -> tuple[dict, float]:
    t0 = time.monotonic()
    job = (await client.post("/jobs", json=JOB)).json()
    while True:
        j = (await client.get(f"/jobs/{job['id']}")).json()
        if j["state"] in ("done", "faulted", "aborted"):
            break
        await asyncio.sleep(0.1)
    assert j["state"] == "done", j
    samples = (await client.get(f"/jobs/{job['id']}/samples")).text
    return {"result": j["result"], "samples": samples}, time.monotonic() - t0


async def poller(url: str, stop: asyncio.Event, interval: float, latencies: list[float], errors: list[str]) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=30, verify=SSL) as c:
        while not stop.is_set():
            t = time.monotonic()
            measured = MEASURING.is_set()
            try:
                r = await c.get("/cell")
                r.raise_for_status()
                if measured:  # the clients' own start-up (100 connections at once) is not measured
                    latencies.append(time.monotonic() - t)
                    SLOW.append((t, latencies[-1]))
            except httpx.HTTPError as exc:
                errors.append(f"status: {exc!r}")
            await asyncio.sleep(interval)


async def follower(url: str, stop: asyncio.Event, delays: list[float], counts: list[int], errors: list[str]) -> None:
    me = len(counts)
    counts.append(0)
    async with httpx.AsyncClient(base_url=url, timeout=httpx.Timeout(30, read=None), verify=SSL) as c:
        try:
            async with c.stream("GET", "/events") as stream:
                async for line in stream.aiter_lines():
                    if line.startswith("data: "):
                        data = json.loads(line[6:])
                        if MEASURING.is_set():
                            delays.append(time.time() - data["at"])  # publish -> received, same host clock
                        counts[me] += 1
                    if stop.is_set():
                        break
        except httpx.HTTPError as exc:
            errors.append(f"events: {exc!r}")


async def main_async(args) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        daemon = DaemonProcess(write_cell_file(Path(tmp), realtime_factor=args.realtime)).start()
        try:
            headers = {"Authorization": f"Bearer {daemon.token}"}
            async with httpx.AsyncClient(base_url=daemon.url, headers=headers, timeout=30) as c:
                alone, wall_alone = await run_job(c)
                print(f"job alone: {wall_alone:.2f} s wall, cell time {alone['result']['cell_time_s']:.3f} s")

                stop = asyncio.Event()
                status_lat, event_delay, counts, errors = [], [], [], []
                tasks = [asyncio.create_task(poller(daemon.url, stop, args.poll_interval, status_lat, errors))
                         for _ in range(args.clients)]
                tasks += [asyncio.create_task(follower(daemon.url, stop, event_delay, counts, errors))
                          for _ in range(args.clients)]
                await asyncio.sleep(1.0)  # let every client connect
                MEASURING.set()
                t_job = time.monotonic()
                loaded, wall_loaded = await run_job(c)
                if args.debug:
                    for t, lat in sorted(SLOW, key=lambda x: -x[1])[:10]:
                        print(f"slow GET /cell at {t - t_job:+.2f} s of the job: {lat * 1e3:.0f} ms")
                stop.set()
                await asyncio.sleep(0.3)
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
            print(f"job under load ({args.clients} clients polling /cell every {args.poll_interval} s and "
                  f"{args.clients} following /events): {wall_loaded:.2f} s wall, "
                  f"cell time {loaded['result']['cell_time_s']:.3f} s")
            print(f"GET /cell latency       {percentiles(status_lat)}")
            print(f"event delivery latency  {percentiles(event_delay)}")
            print(f"events per stream: min {min(counts, default=0)}  max {max(counts, default=0)}; errors {len(errors)}")
            for e in errors[:5]:
                print("  ", e)
            same = {
                "cell time": alone["result"]["cell_time_s"] == loaded["result"]["cell_time_s"],
                "stats": alone["result"]["stats"] == loaded["result"]["stats"],
                "model": alone["result"]["model"] == loaded["result"]["model"],
                "samples (all columns)": alone["samples"] == loaded["samples"],
            }
            for what, ok in same.items():
                print(f"{what:22s} {'unchanged' if ok else 'CHANGED'}")
            return 0 if all(same.values()) and not errors else 1
        finally:
            daemon.terminate()
            daemon.log.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--poll-interval", type=float, default=0.1, help="seconds between a client's status polls")
    parser.add_argument("--debug", action="store_true", help="print when the slowest status polls happened")
    parser.add_argument("--realtime", type=float, default=0.1, help="the sim's realtime_factor (wall s per cell s)")
    return asyncio.run(main_async(parser.parse_args()))


if __name__ == "__main__":
    sys.exit(main())
