"""The real daemon as a subprocess on an ephemeral port, with its own store, on the simulated micro cell.

The cell file is the default micro cell with the store in the test's temp folder and
the simulated clock spent partly as wall time (`realtime_factor`), so a small job
takes a few seconds and can be paused or killed in the middle of a move.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import ssl
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

import httpx
import yaml

from tests.support.wait import eventually

ROOT = Path(__file__).resolve().parents[2]
# 24 steps, 11.5 s of cell time: all of them (a target out of reach keeps the grid from stopping early, issue 31)
SMALL = {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1, "target_um": 0.001}
SEED = 5


def write_cell_file(folder: Path, realtime_factor: float = 0.08, faults: dict | None = None,
                    lock_break_after_idle_s: float | None = None, routines: dict | None = None,
                    manual: dict | None = None) -> Path:
    """The micro cell with its store in `folder`; `routines`: parameters merged into the cell file's sections."""
    data = yaml.safe_load((ROOT / "config" / "sim-microcell.yaml").read_text())
    data["store_dir"] = str(folder / "store")
    data["sim"]["motion"]["realtime_factor"] = realtime_factor
    if faults:
        data["sim"]["faults"] = faults
    if lock_break_after_idle_s is not None:  # tests that break a lock need not wait the default minute
        data["operator_lock"] = {"break_after_idle_s": lock_break_after_idle_s}
    if manual:  # manual-motion settings (a longer heartbeat time-out for tests that heartbeat from a busy machine)
        data["manual"] = manual
    for name, params in (routines or {}).items():
        data.setdefault("routines", {}).setdefault(name, {}).update(params)
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@contextmanager
def running_daemon(folder: Path, store_from: Path | None = None, **cell_options):
    """A daemon process on the micro cell written in `folder` (write_cell_file's options), stopped after;
    `store_from`: a store copied in first (a calibrated cell's)."""
    cell_file = write_cell_file(folder, **cell_options)
    if store_from is not None:
        shutil.copytree(store_from, folder / "store", dirs_exist_ok=True)
    with DaemonProcess(cell_file).start() as daemon:
        yield daemon


class DaemonProcess:
    """`python -m cellctl.startup` started and stopped by a test; `client` talks to it with the token."""

    def __init__(self, cell_file: Path, args: tuple[str, ...] = ()):
        self.cell_file = cell_file
        self.args = list(args)  # more `python -m cellctl.startup` options, e.g. ("--host", "0.0.0.0", "--tls")
        self.store = Path(yaml.safe_load(cell_file.read_text())["store_dir"])
        self.proc: subprocess.Popen | None = None
        self.url = ""
        self.log_path = cell_file.parent / "daemon.log"
        self.extra_env: dict[str, str] = {}

    def start(self, timeout: float = 120.0) -> DaemonProcess:
        """Start the daemon and wait for its URL file (the event), up to `timeout`: generous, since a loaded
        2-core machine can take tens of seconds to bring up the OPC UA server; a healthy start returns at once."""
        url_file = self.store / "daemon.url"
        if url_file.exists():
            url_file.unlink()
        env = dict(os.environ)
        env.pop("CELLCTL_STORE", None)  # the cell file's store_dir is the one to use
        env.pop("NOTIFY_SOCKET", None)
        env.update(self.extra_env)
        self.log = open(self.log_path, "a")
        self.proc = subprocess.Popen([sys.executable, "-m", "cellctl.startup", "--config", str(self.cell_file),
                                      "--port", "0", *self.args], cwd=ROOT, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        def url() -> str | None:
            if self.proc.poll() is not None:
                raise RuntimeError(f"daemon exited with {self.proc.returncode}:\n{self.log_path.read_text()[-3000:]}")
            return url_file.exists() and url_file.read_text().strip()

        try:
            self.url = eventually(url, timeout=timeout, every=0.05, what="the daemon's URL")
        except AssertionError:
            self.proc.kill()  # not left running: no `with` block will stop it
            self.proc.wait()
            raise RuntimeError("daemon did not become ready:\n" + self.log_path.read_text()[-3000:]) from None
        return self

    @property
    def token(self) -> str:
        return (self.store / "daemon.token").read_text().strip()

    @property
    def ca(self) -> Path | None:
        """The certificate a client pins when the daemon serves HTTPS (the one it made in its store)."""
        return self.store / "tls" / "daemon.crt" if self.url.startswith("https:") else None

    def client(self, token: str | None = "default", **headers) -> httpx.Client:
        h = dict(headers)
        if token == "default":
            token = self.token
        if token is not None:
            h["Authorization"] = f"Bearer {token}"
        verify = ssl.create_default_context(cafile=self.ca) if self.ca else True
        return httpx.Client(base_url=self.url, headers=h, timeout=10.0, verify=verify)

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def terminate(self, timeout: float = 15.0) -> int:
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else 0
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
            raise

    def __enter__(self) -> DaemonProcess:
        return self

    def __exit__(self, *exc) -> None:
        """Stopped (SIGTERM) if still running, its log closed."""
        if self.proc is not None and self.proc.poll() is None:
            self.terminate()
        self.log.close()

    def logs(self) -> list[dict]:
        out = []
        for line in self.log_path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                pass
        return out


def wait_for(client: httpx.Client, job_id: int, states: set[str], timeout: float = 90.0) -> dict:
    """The job, once it is in one of `states`."""
    def in_state():
        job = client.get(f"/jobs/{job_id}").json()
        return job if job["state"] in states else None

    def said() -> str:
        job = client.get(f"/jobs/{job_id}").json()
        return f"job {job_id} in {sorted(states)} (it is {job['state']}: {job.get('reason')})"

    return eventually(in_state, timeout=timeout, every=0.05, what=said)


def wait_step(client: httpx.Client, job_id: int, step: int, timeout: float = 60.0) -> dict:
    """The job, once it has done at least `step` steps (it must still be queued or running until then)."""
    def stepped():
        job = client.get(f"/jobs/{job_id}").json()
        if (job.get("progress") or {}).get("step", 0) >= step:
            return job
        assert job["state"] in ("queued", "running"), job
        return None

    return eventually(stepped, timeout=timeout, what=f"job {job_id} at step {step}")
