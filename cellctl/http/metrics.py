"""`/metrics`: the cell in Prometheus's text format, for the plant's monitoring.

What the stores already know (jobs, their times, the live job's progress, devices, calibrations and their
health) is read from them at scrape time by one Collector, so nothing is counted twice and a restart of the
daemon loses nothing the job store kept. What only passes through (requests, by front end and outcome) is a
counter of this process, reset at restart as Prometheus expects of counters; every front end counts its
requests with `count_request` (HTTP here, by a middleware; OPC UA in cellctl.opcua).

No token is needed, as for every GET of the API: a Prometheus scraper usually has none, and the bearer
token must not be handed to the monitoring system, which would then command the cell. So nothing here is
secret: routine, state, device and target names, counts and times; never a token, lock id, job parameter or
error text (a device's error may quote anything). Beyond loopback it is HTTPS like the rest (tls.py);
Prometheus pins the daemon's certificate with `tls_config: {ca_file: daemon.crt}`.
"""

from __future__ import annotations

import time
from datetime import datetime

from fastapi import FastAPI, Request
from fastapi.responses import Response
from prometheus_client import CollectorRegistry, Counter, PlatformCollector, ProcessCollector
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4, choose_encoder, generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector

from cellctl.http.contract import body
from cellctl.stores.disk_space import MB, space
from cellctl.stores.jobs import STATES

__all__ = ["FRONT_ENDS", "CellCollector", "count_request", "http_outcome", "install", "registry_of"]

FRONT_ENDS = ("http", "opcua")
VERDICTS = ("ok", "drift", "unchecked")
# seconds: a simulated job takes a few, a full calibration on a real cell an hour or more
BUCKETS_S = (1, 5, 10, 30, 60, 120, 300, 600, 1200, 1800, 3600, 7200, 14400, float("inf"))

REQUESTS = Counter("cellctl_requests", "requests served, by front end and outcome (ok, refused <status>, error)",
                   ["front_end", "outcome"], registry=None)  # registered with each daemon's registry


def count_request(front_end: str, outcome: str) -> None:
    """Count one request a front end answered: `front_end` "http" or "opcua"; `outcome` "ok", "refused <code>"
    (e.g. "refused 401", "refused BadUserAccessDenied") or "error" (the front end failed)."""
    if front_end not in FRONT_ENDS:
        raise ValueError(f"front_end: {front_end!r}; allowed: {', '.join(FRONT_ENDS)}")
    if not isinstance(outcome, str) or not 0 < len(outcome) <= 64:
        raise ValueError(f"outcome: {outcome!r}; allowed: a short text such as 'ok', 'refused 401', 'error'")
    REQUESTS.labels(front_end, outcome).inc()


def http_outcome(status: int) -> str:
    return "ok" if status < 400 else f"refused {status}" if status < 500 else "error"


class CellCollector(Collector):
    """The daemon's state as metric families, read from its stores on each scrape."""

    def __init__(self, daemon):
        self.daemon = daemon
        self._done: dict[int, tuple[str, float | None, float]] = {}  # done is final: read each job once

    def collect(self):
        yield from self._jobs()
        yield from self._live_job()
        yield from self._devices()
        yield from self._calibrations()
        yield from self._fleet()
        yield from self._disk()

    def _disk(self):
        """The store's filesystem: its free and total bytes, and the floor below which jobs are refused."""
        store_dir = getattr(self.daemon, "store_dir", None)
        if store_dir is None:  # a collector over stores alone
            return
        found = space(store_dir)
        free = GaugeMetricFamily("cellctl_store_free_bytes", "free bytes on the store's filesystem (what the daemon "
                                 "may still write)", labels=["filesystem"])
        free.add_metric([found.filesystem], found.free)
        size = GaugeMetricFamily("cellctl_store_size_bytes", "size of the store's filesystem", labels=["filesystem"])
        size.add_metric([found.filesystem], found.total)
        floor = GaugeMetricFamily("cellctl_store_min_free_bytes", "free space the cell file asks to keep "
                                  "(store.min_free_mb): below it new jobs, resumptions and saved images are refused",
                                  value=self.daemon.config.store.min_free_mb * MB)
        yield from (free, size, floor)

    def _fleet(self):
        """Replication to the plant, per sink: up, records not yet delivered, delivered since start."""
        replicator = getattr(self.daemon, "replicator", None)
        if replicator is None:
            return
        up = GaugeMetricFamily("cellctl_fleet_sink_up", "1 if the plant's sink (postgres, mqtt) is connected",
                               labels=["sink"])
        backlog = GaugeMetricFamily("cellctl_fleet_backlog_records", "records kept for the sink, not yet "
                                    "delivered", labels=["sink"])
        delivered = CounterMetricFamily("cellctl_fleet_delivered_records", "records delivered to the sink since "
                                        "the daemon started", labels=["sink"])
        pending = replicator.backlog()
        for sink in replicator.names:
            up.add_metric([sink], int(replicator.up[sink]))
            backlog.add_metric([sink], pending[sink])
            delivered.add_metric([sink], replicator.delivered[sink])
        yield from (up, backlog, delivered)

    def _jobs(self):
        jobs = self.daemon.jobs
        counts = jobs.counts()
        family = GaugeMetricFamily("cellctl_jobs", "jobs in the job store, by routine and state (done and aborted "
                                                   "are final: those only grow)", labels=["routine", "state"])
        for routine in sorted({r for r, _ in counts}):
            for state in STATES:
                family.add_metric([routine, state], counts.get((routine, state), 0))
        yield family
        self._done.update(jobs.done_times(self._done.keys()))
        yield _histogram("cellctl_job_cell_time_seconds", "cell time of the jobs done (the cell's clock: motion, "
                                                          "settling, exposure), by routine",
                         [(routine, cell_s) for routine, cell_s, _ in self._done.values() if cell_s is not None])
        yield _histogram("cellctl_job_wall_time_seconds", "wall-clock time the jobs done spent running (pauses "
                                                          "left out), by routine",
                         [(routine, wall_s) for routine, _, wall_s in self._done.values()])

    def _live_job(self):
        live = self.daemon.worker.live_job
        yield GaugeMetricFamily("cellctl_live_job_id", "the job the worker runs now (0: none)", value=live or 0)
        step = GaugeMetricFamily("cellctl_live_job_step", "steps the live job has done", labels=["routine"])
        steps = GaugeMetricFamily("cellctl_live_job_steps", "steps the live job has in all (of its current item, "
                                                            "for a sequence)", labels=["routine"])
        if live is not None:
            job = self.daemon.jobs.get(live)
            progress = job.progress or {}
            if progress.get("total"):
                step.add_metric([job.routine], progress.get("step", 0))
                steps.add_metric([job.routine], progress["total"])
        yield step
        yield steps

    def _devices(self):
        family = GaugeMetricFamily("cellctl_device_up", "1 if the device is connected and ready, else 0",
                                   labels=["device", "kind", "backend"])
        for device in self.daemon.cells.status():
            family.add_metric([device["name"], device["kind"], device["backend"]], int(device["state"] == "ready"))
        yield family

    def _calibrations(self):
        labels = ["target", "routine"]
        version = GaugeMetricFamily("cellctl_calibration_active_version", "version of the active calibration",
                                    labels=labels)
        mean = GaugeMetricFamily("cellctl_calibration_verification_mean_meters", "mean error of the active "
                                 "calibration on its verification points (points the fit never saw)", labels=labels)
        verdict = GaugeMetricFamily("cellctl_calibration_health", "1 for the active calibration's health verdict "
                                    "(ok, drift, unchecked: no check of this version yet), 0 for the others",
                                    labels=["target", "verdict"])
        age = GaugeMetricFamily("cellctl_calibration_last_check_age_seconds", "seconds since the target's last "
                                "check (targets never checked: absent)", labels=["target"])
        calstore, now = self.daemon.calstore, time.time()
        for target, health in calstore.health().items():
            active = health["active"]
            version.add_metric([target, active["routine"]], active["version"])
            stats = (calstore.get(active["id"]).result.get("stats") or {}).get("verification") or {}
            if isinstance(stats.get("mean_um"), (int, float)):
                mean.add_metric([target, active["routine"]], stats["mean_um"] * 1e-6)
            for name in VERDICTS:
                verdict.add_metric([target, name], int(health["verdict"] == name))
            if health["last_check"] is not None:
                checked = datetime.strptime(health["last_check"]["created"], "%Y-%m-%dT%H:%M:%S%z").timestamp()
                age.add_metric([target], max(now - checked, 0.0))
        yield from (version, mean, verdict, age)


def _histogram(name: str, documentation: str, values: list[tuple[str, float]]) -> HistogramMetricFamily:
    family = HistogramMetricFamily(name, documentation, labels=["routine"])
    by_routine: dict[str, list[float]] = {}
    for routine, value in values:
        by_routine.setdefault(routine, []).append(value)
    for routine, seconds in sorted(by_routine.items()):
        buckets = [(_le(b), sum(1 for s in seconds if s <= b)) for b in BUCKETS_S]
        family.add_metric([routine], buckets, sum_value=sum(seconds))
    return family


def _le(bound: float) -> str:
    return "+Inf" if bound == float("inf") else str(float(bound))


def registry_of(daemon) -> CollectorRegistry:
    """A registry of the daemon's metrics, the request counter, and the process's own (memory, CPU, open files)."""
    registry = CollectorRegistry()
    registry.register(CellCollector(daemon))
    registry.register(REQUESTS)
    ProcessCollector(registry=registry)
    PlatformCollector(registry=registry)
    return registry


class _CountRequests:
    """ASGI middleware: each HTTP request counted once its answer starts (a stream too), or as an error when the
    app raised before answering."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = False

        async def sending(message):
            nonlocal started
            if message["type"] == "http.response.start" and not started:
                started = True
                count_request("http", http_outcome(message["status"]))
            await send(message)

        try:
            await self.app(scope, receive, sending)
        except Exception:
            if not started:
                count_request("http", "error")
            raise


def install(app: FastAPI, daemon) -> None:
    """Serve /metrics and count every HTTP request. Call it after the API's own middleware, so that what that
    refuses (401, 403, 405) is counted too."""
    registry = registry_of(daemon)
    app.add_middleware(_CountRequests)

    @app.get("/metrics", summary="the cell's metrics for Prometheus (text format; no token needed, nothing secret)",
             response_class=Response, responses=body("text/plain", "Prometheus text format (OpenMetrics when the "
                                                                   "Accept header asks for it)", {"type": "string"}))
    def metrics(request: Request):
        try:
            encode, media_type = choose_encoder(request.headers.get("accept", ""))
        except (ValueError, TypeError):  # an Accept header it cannot read (a version "abc"): the classic text format
            encode, media_type = generate_latest, CONTENT_TYPE_PLAIN_0_0_4
        return Response(encode(registry), media_type=media_type)

