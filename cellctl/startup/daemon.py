"""Start-up and shutdown of the daemon: stores, token, cell, worker, HTTP server; systemd; JSON logs.

Start: open the job database and the calibration store (under the cell file's
`store_path()`), make the token if there is none, connect the cell's devices,
mark a job that was running when the daemon died as faulted, start the worker,
serve HTTP (HTTPS beyond loopback: tls.py), then tell systemd READY=1 (and keep its watchdog fed from the event
loop, so a stuck loop gets the service restarted).
Stop (SIGTERM/SIGINT): the arm is stopped, the running job paused and recorded,
the devices closed.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import socket
import sys
import time
from pathlib import Path

from cellctl.config import load_cell_file
from cellctl.core.events import EventHub
from cellctl.core.worker import CellHolder, Worker
from cellctl.errors import ServiceError
from cellctl.fleet import link
from cellctl.service.auth import OperatorLock, load_or_create_token, token_path
from cellctl.service.local import LocalService
from cellctl.service.schedule import CheckSchedule
from cellctl.startup.ownership import check_port_free, listening_socket, own_cell
from cellctl.startup.tls import tls_for, url_of
from cellctl.stores.backup import BackupSchedule, StoreCorrupt, check_store
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.disk_space import keep_reserve
from cellctl.stores.jobs import DB_FILE, JobStore, folder_records

DEFAULT_PORT = 8470
log = logging.getLogger("cellctl.startup")


# -- structured logs ---------------------------------------------------------------------

_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message", "asctime"}


class JsonLines(logging.Formatter):
    """One JSON object per line: time, level, logger, message and any `extra=` fields."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {"t": round(record.created, 3), "level": record.levelname.lower(), "logger": record.name,
                 "msg": record.getMessage()}
        entry.update({k: v for k, v in vars(record).items() if k not in _STANDARD and k != "color_message"})
        if record.exc_info:
            entry["trace"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


def setup_logging(level: str = "INFO") -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLines())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        logging.getLogger(name).handlers[:] = []
        logging.getLogger(name).propagate = True
    logging.getLogger("uvicorn.access").setLevel("WARNING")  # 50 pollers would drown the journal


# -- systemd ---------------------------------------------------------------------------------


def sd_notify(message: str) -> bool:
    """Send one sd_notify datagram ("READY=1", "WATCHDOG=1", ...); False when not under systemd."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]  # abstract namespace socket
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
        try:
            s.connect(address)
            s.sendall(message.encode())
        except OSError:
            return False
    return True


def watchdog_interval() -> float | None:
    """Half the WATCHDOG_USEC systemd gave us (when it is meant for this process)."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    return int(usec) / 2e6


# -- the daemon ------------------------------------------------------------------------------


class Daemon:
    """The cell's process: its stores, token, lock, event hub, devices and worker, and the service over them."""

    def __init__(self, config_path: str | Path, loaded: tuple | None = None):
        self.config_path = Path(config_path)
        self.config, self.cell_text = loaded or load_cell_file(config_path)  # loaded: serve() read it already
        self.store_dir = self.config.store_path()
        self.store_dir.mkdir(parents=True, exist_ok=True)
        backups = self.config.store.backup
        try:  # before anything reads or writes the store: a store that fails its integrity check is never served
            check_store(self.store_dir, backups.folder(self.store_dir) if backups else None,
                        f" --config {self.config_path}")
        except StoreCorrupt as exc:
            log.error("store refused", extra={"store": str(self.store_dir), "error": str(exc)})
            raise
        keep_reserve(self.store_dir)  # freed when a write runs out of space, so the fault can be recorded
        self.token = load_or_create_token(self.store_dir)
        in_fleet = self.config.fleet is not None
        # the fleet's credentials are read first: a bad one stops the start before any device is touched
        self.replicator = link.replicator(self.config, self.config_path.parent,
                                          {"jobs": self.store_dir / DB_FILE,
                                           "calibrations": self.store_dir / CalibrationStore.FILE})
        self.jobs = JobStore(self.store_dir / DB_FILE, replicate=in_fleet)
        self.calstore = CalibrationStore(self.store_dir, replicate=in_fleet)
        if self.replicator is not None:
            self.jobs.outbox.on_commit = self.calstore.outbox.on_commit = self.replicator.wake
        self.hub = EventHub()
        self.lock = OperatorLock(break_after_idle_s=self.config.operator_lock.break_after_idle_s)
        self.started = time.monotonic()  # for the uptime: a wall-clock step must not change it
        for job in self.jobs.recover():
            log.warning("job recovered after restart", extra={"job": job.id, "state": job.state, "reason": job.reason})
            if job.state == "faulted":  # it died running: what its folders hold may not have been recorded yet
                self.jobs.resend(job.id, *folder_records(job))
        self.jobs.record_cell("idle", None)
        self.cells = CellHolder(self.config, self.cell_text)
        self.worker = Worker(self.jobs, self.cells, self.calstore, self.hub)
        self.service = LocalService.of_daemon(self)  # what every front end calls
        self.schedule = None
        self.opcua = None  # the OPC UA front end, started in the event loop (start_opcua)
        self.backups = (BackupSchedule(backups, self.store_dir, self.config.cell.name, self.config.store.min_free_mb)
                        if backups else None)
        if self.config.health is not None:
            self.schedule = CheckSchedule(self.config.health, self.service, self.worker, self.calstore, self.lock)
            self.service.schedule = self.schedule  # status shows the next check

    def start(self) -> None:
        self.worker.start()
        if self.schedule is not None:
            self.schedule.start()
        if self.backups is not None:
            self.backups.start()

    def start_fleet(self, url: str) -> None:
        """Replication to the plant, once the daemon knows its own URL (the plant shows it)."""
        if self.replicator is None:
            return
        for sink in self.replicator.sinks:
            sink.info["api_url"] = self.config.fleet.api_url or url
        self.replicator.start()

    def stop(self, reason: str) -> None:
        sd_notify("STOPPING=1")
        log.info("stopping", extra={"reason": reason})
        if self.schedule is not None:
            self.schedule.stop()
        if self.backups is not None:
            self.backups.stop()
        self.cells.stop()
        self.worker.shutdown(reason)
        self.cells.close()
        if self.replicator is not None:  # the last state changes go out (briefly), then the cell says offline
            self.replicator.stop()
        self.jobs.close()
        self.calstore.close()


def serve(config_path: str | Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT, log_level: str = "INFO",
          tls: bool = False) -> int:
    """Run the daemon until SIGTERM/SIGINT; returns the exit status. `tls`: HTTPS even where the cell file does
    not ask for it; beyond loopback plain HTTP is refused (PlainHttpRefused) unless the cell file allows it.
    Refused (exit 2 from the command line) before any device is touched: a cell another process owns
    (CellOwned), a port in use (PortInUse)."""
    setup_logging(log_level)
    loaded = load_cell_file(config_path)
    # the cell is this process's before anything is written or touched; a second owner is refused here
    ownership = own_cell(loaded[0], loaded[0].store_path(), f"cellctl serve --config {config_path}")
    try:
        return _serve(config_path, loaded, ownership, host, port, tls)
    finally:
        ownership.release()


def _serve(config_path, loaded, ownership, host, port, tls) -> int:
    import uvicorn

    from cellctl.http.api import create_app

    listener = listening_socket(host, port, "the HTTP API", "pick another with --port PORT (0: any free one)")
    try:
        opcua = loaded[0].opcua
        if opcua.enabled:  # its port in use: refused now, while nothing has moved
            check_port_free(opcua.host, opcua.port, "the OPC UA server",
                            "set another opcua.port in the cell file (0: any free one)")
        served = tls_for(loaded[0], Path(config_path), host, force=tls)  # refused before any device is touched
        daemon = Daemon(config_path, loaded)
    except BaseException:
        listener.close()
        raise
    app = create_app(daemon)

    class Server(uvicorn.Server):
        def handle_exit(self, sig, frame):
            # first make the cell safe (arm stopped, job paused), then let uvicorn close the connections
            if not self.should_exit:
                daemon.cells.stop()
                daemon.worker.shutdown(f"daemon stopped by signal {sig}", timeout=0)
            super().handle_exit(sig, frame)
            self._captured_signals.clear()  # a clean stop, not death by the signal: daemon.stop() still runs

    config = uvicorn.Config(app, host=host, port=port, log_config=None, access_log=False,
                            timeout_graceful_shutdown=2, lifespan="on", **(served.uvicorn_options() if served else {}))
    server = Server(config)

    async def main():
        daemon.hub.attach(asyncio.get_running_loop())
        daemon.start()
        try:
            daemon.opcua = await start_opcua(daemon)
        except (ServiceError, OSError) as exc:  # a bad opcua: section or a port in use: one line, serve nothing
            print(f"cellctl serve: OPC UA server cannot start: {exc}", file=sys.stderr)
            return 2
        serving = asyncio.create_task(server.serve(sockets=[listener]))  # bound above: uvicorn binds nothing
        while not server.started:
            if serving.done():
                return await serving
            await asyncio.sleep(0.02)
        url = url_of("https" if served else "http", server.servers[0].sockets[0].getsockname())
        daemon.start_fleet(url)
        (daemon.store_dir / "daemon.url").write_text(url + "\n")
        ownership.serving(url)  # a refused second owner is told to go through it
        log.info("ready", extra={"url": url, "store": str(daemon.store_dir), "token_file": str(token_path(daemon.store_dir)),
                                 "cell": daemon.config.cell.name, "tls": served.describe() if served else None})
        sd_notify(f"READY=1\nSTATUS=serving {daemon.config.cell.name} on {url}")
        interval = watchdog_interval()
        while not serving.done():
            if interval and daemon.worker.alive:  # a dead worker starves the watchdog: systemd restarts us
                sd_notify("WATCHDOG=1")
            await asyncio.wait([serving], timeout=interval or 1.0)
        if daemon.opcua is not None:
            await daemon.opcua.stop()
        return await serving

    try:
        status = asyncio.run(main())
    finally:
        daemon.stop("server ended")
    return status if isinstance(status, int) else 0


async def start_opcua(daemon: Daemon):
    """The OPC UA server, when the cell file enables it (its URL beside daemon.url); else None."""
    if not daemon.config.opcua.enabled:
        return None
    from cellctl.http.metrics import count_request
    from cellctl.opcua.server import OpcuaServer

    opcua = OpcuaServer(daemon.config, daemon.service, daemon.hub, daemon.store_dir, daemon.token,
                        count=lambda outcome: count_request("opcua", outcome))
    url = await opcua.start()
    (daemon.store_dir / "opcua.url").write_text(url + "\n")
    return opcua
