"""Load on a running daemon: N clients poll the status (GET /cell, what `cellctl status` reads) and N follow
the event stream while a job runs; the same job alone first, so the two can be compared.

Shared by tools/load_daemon.py (which prints the figures) and tests/daemon/test_load.py (which asserts the
job's cell time and result unchanged). Loopback only: the URL is the daemon's own (tests start it on
127.0.0.1); every request loop is bounded in time (`time_limit_s`) and ends with the job.
"""

from __future__ import annotations

import asyncio
import json
import ssl
import time
from dataclasses import dataclass, field

import httpx

from tests.support.daemon import SMALL

JOB = {"routine": "virtual-grid", "params": SMALL, "seed": 7}
TERMINAL = ("done", "faulted", "aborted")


def percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    v = sorted(values)

    def pick(q):
        return v[min(int(q * len(v)), len(v) - 1)] * 1e3

    return (f"n {len(v):6d}  p50 {pick(0.5):7.1f} ms  p95 {pick(0.95):7.1f} ms  p99 {pick(0.99):7.1f} ms  "
            f"max {v[-1] * 1e3:7.1f} ms")


@dataclass
class LoadReport:
    clients: int
    poll_interval: float
    alone: dict = field(default_factory=dict)  # {"result": ..., "samples": CSV text}
    loaded: dict = field(default_factory=dict)
    wall_alone: float = 0.0
    wall_loaded: float = 0.0
    status_latencies: list = field(default_factory=list)  # s, GET /cell while the loaded job ran
    event_delays: list = field(default_factory=list)  # s, publish -> received
    events_per_stream: list = field(default_factory=list)
    slow: list = field(default_factory=list)  # (t, latency) of every measured poll
    errors: list = field(default_factory=list)
    t_job: float = 0.0

    @property
    def same(self) -> dict[str, bool]:
        a, b = self.alone["result"], self.loaded["result"]
        return {"cell time": a["cell_time_s"] == b["cell_time_s"], "stats": a["stats"] == b["stats"],
                "model": a["model"] == b["model"], "samples (all columns)": self.alone["samples"] == self.loaded["samples"]}


async def run_job(client: httpx.AsyncClient, job: dict, time_limit_s: float) -> tuple[dict, float]:
    t0 = time.monotonic()
    r = await client.post("/jobs", json=job)
    r.raise_for_status()
    job_id = r.json()["id"]
    while True:
        j = (await client.get(f"/jobs/{job_id}")).json()
        if j["state"] in TERMINAL:
            break
        if time.monotonic() - t0 > time_limit_s:
            raise TimeoutError(f"job {job_id} still {j['state']} after {time_limit_s} s")
        await asyncio.sleep(0.1)
    assert j["state"] == "done", j
    samples = (await client.get(f"/jobs/{job_id}/samples")).text
    return {"id": job_id, "result": j["result"], "samples": samples}, time.monotonic() - t0


class _Load:
    def __init__(self, url: str, report: LoadReport, deadline: float):
        self.url, self.report, self.deadline = url, report, deadline
        self.stop = asyncio.Event()
        self.measuring = asyncio.Event()
        self.ssl = ssl.create_default_context()  # one for all clients: making 100 costs seconds of CPU

    def over(self) -> bool:
        return self.stop.is_set() or time.monotonic() > self.deadline

    async def poller(self) -> None:
        rep = self.report
        async with httpx.AsyncClient(base_url=self.url, timeout=30, verify=self.ssl) as c:
            while not self.over():
                t = time.monotonic()
                measured = self.measuring.is_set()
                try:
                    r = await c.get("/cell")
                    r.raise_for_status()
                    if measured:  # the clients' own start-up (100 connections at once) is not measured
                        rep.status_latencies.append(time.monotonic() - t)
                        rep.slow.append((t, rep.status_latencies[-1]))
                except httpx.HTTPError as exc:
                    rep.errors.append(f"status: {exc!r}")
                await asyncio.sleep(rep.poll_interval)

    async def follower(self) -> None:
        rep = self.report
        me = len(rep.events_per_stream)
        rep.events_per_stream.append(0)
        async with httpx.AsyncClient(base_url=self.url, timeout=httpx.Timeout(30, read=None), verify=self.ssl) as c:
            try:
                async with c.stream("GET", "/events") as stream:
                    async for line in stream.aiter_lines():
                        if line.startswith("data: "):
                            data = json.loads(line[6:])
                            if self.measuring.is_set():
                                rep.event_delays.append(time.time() - data["at"])  # same host clock
                            rep.events_per_stream[me] += 1
                        if self.over():
                            break
            except httpx.HTTPError as exc:
                rep.errors.append(f"events: {exc!r}")


async def compare_under_load(url: str, token: str, *, clients: int = 50, poll_interval: float = 0.1,
                             job: dict | None = None, time_limit_s: float = 120.0,
                             connect_s: float = 1.0) -> LoadReport:
    """Run `job` alone, then again with `clients` pollers and `clients` event followers; both runs reported."""
    job = job or JOB
    report = LoadReport(clients, poll_interval)
    headers = {"Authorization": f"Bearer {token}"}
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=30) as c:
        report.alone, report.wall_alone = await run_job(c, job, time_limit_s)
        load = _Load(url, report, time.monotonic() + time_limit_s)
        tasks = [asyncio.create_task(load.poller()) for _ in range(clients)]
        tasks += [asyncio.create_task(load.follower()) for _ in range(clients)]
        try:
            await asyncio.sleep(connect_s)  # let every client connect
            load.measuring.set()
            report.t_job = time.monotonic()
            report.loaded, report.wall_loaded = await run_job(c, job, time_limit_s)
            load.stop.set()
            await asyncio.sleep(0.3)
        finally:
            load.stop.set()
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
    return report
