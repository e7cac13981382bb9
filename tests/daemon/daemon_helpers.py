"""The real daemon as a subprocess on an ephemeral port, with its own store, on the simulated micro cell.

The cell file is the default micro cell with the store in the test's temp folder and
the simulated clock spent partly as wall time (`realtime_factor`), so a small job
takes a few seconds and can be paused or killed in the middle of a move.
"""

from __future__ import annotations

import json
import os
import signal
import ssl
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
SMALL = {"rows": 4, "cols": 4, "n_verify": 8, "passes": 1}  # 24 steps, 11.5 s of cell time
SEED = 5


def write_cell_file(folder: Path, realtime_factor: float = 0.08, faults: dict | None = None,
                    lock_break_after_idle_s: float | None = None) -> Path:
    data = yaml.safe_load((ROOT / "config" / "sim-microcell.yaml").read_text())
    data["store_dir"] = str(folder / "store")
    data["sim"]["motion"]["realtime_factor"] = realtime_factor
    if faults:
        data["sim"]["faults"] = faults
    if lock_break_after_idle_s is not None:  # tests that break a lock need not wait the default minute
        data["operator_lock"] = {"break_after_idle_s": lock_break_after_idle_s}
    path = folder / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


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

    def start(self, timeout: float = 20.0) -> DaemonProcess:
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
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"daemon exited with {self.proc.returncode}:\n{self.log_path.read_text()[-3000:]}")
            if url_file.exists() and url_file.read_text().strip():
                self.url = url_file.read_text().strip()
                return self
            time.sleep(0.05)
        raise RuntimeError("daemon did not become ready:\n" + self.log_path.read_text()[-3000:])

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


@pytest.fixture
def start_daemon(tmp_path):
    """Factory: start a daemon on a cell file; every one started is stopped at the end."""
    started: list[DaemonProcess] = []

    def start(cell_file: Path | None = None, **cell_options) -> DaemonProcess:
        d = DaemonProcess(cell_file or write_cell_file(tmp_path, **cell_options)).start()
        started.append(d)
        return d

    yield start
    for d in started:
        if d.proc and d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait(5)
        if getattr(d, "log", None):
            d.log.close()


def wait_for(client: httpx.Client, job_id: int, states: set[str], timeout: float = 90.0) -> dict:
    """Poll until the job is in one of `states`."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] in states:
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} not in {states} after {timeout} s: {job['state']} {job.get('reason')}")


def wait_step(client: httpx.Client, job_id: int, step: int, timeout: float = 60.0) -> dict:
    """Poll until the running job has done at least `step` steps."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if (job.get("progress") or {}).get("step", 0) >= step:
            return job
        assert job["state"] in ("queued", "running"), job
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} did not reach step {step} in {timeout} s")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted in-process run (`cellctl run` semantics) of SMALL with SEED, and its samples."""
    from cellctl.config import load_cell_file
    from cellctl.core.runs import run_routine
    from cellctl.stores.run_folder import RunFolder

    folder = tmp_path_factory.mktemp("reference")
    config, text = load_cell_file(write_cell_file(folder, realtime_factor=0.0))
    result = run_routine("virtual-grid", config, text, folder / "run", seed=SEED, overrides=SMALL)
    return result, RunFolder(folder / "run").samples()
