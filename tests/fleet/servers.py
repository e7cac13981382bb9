"""The plant's real servers for the tests, from Debian (tools/ensure-system), on loopback on a free port with a
temporary data directory, stopped afterwards: PostgreSQL (so far; Mosquitto joins it with the event stream).
PostgreSQL refuses to run as root, so as root it runs as the `postgres` user the package made."""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pg_bin(name: str) -> str:
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    if not found:
        raise RuntimeError(f"PostgreSQL's {name} is not installed: run tools/ensure-system")
    return found[-1]


class PostgresServer:
    """initdb, postgres -D, a database `plant` owned by `cellctl` with a password: `dsn` to reach it."""

    def __init__(self, password: str = "cellctl-test-password"):
        self.password = password
        self.port = free_port()
        self.root = Path(tempfile.mkdtemp(prefix="cellctl-pg-"))
        self.data, self.sockets = self.root / "data", self.root / "run"
        self.proc: subprocess.Popen | None = None
        self._as = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []

    @property
    def dsn(self) -> str:
        return f"postgresql://cellctl:{self.password}@127.0.0.1:{self.port}/plant"

    def _run(self, *args: str) -> None:
        subprocess.run([*self._as, *args], check=True, capture_output=True, text=True, timeout=120)

    def start(self) -> "PostgresServer":
        self.sockets.mkdir(parents=True)
        if self._as:
            user = pwd.getpwnam("postgres")
            os.chown(self.root, user.pw_uid, user.pw_gid)
            os.chown(self.sockets, user.pw_uid, user.pw_gid)
        if not self.data.exists():
            pwfile = self.root / "superuser-password"
            pwfile.write_text("postgres-test\n")
            if self._as:
                os.chown(pwfile, pwd.getpwnam("postgres").pw_uid, -1)
            self._run(_pg_bin("initdb"), "-D", str(self.data), "-U", "postgres", f"--pwfile={pwfile}",
                      "--auth-local=trust", "--auth-host=scram-sha-256", "-E", "UTF8", "--no-sync")
        self.resume()
        self._run(_pg_bin("psql"), "-h", str(self.sockets), "-p", str(self.port), "-U", "postgres", "-q", "-c",
                  f"CREATE ROLE cellctl LOGIN PASSWORD '{self.password}'", "-c", "CREATE DATABASE plant OWNER cellctl")
        return self

    def resume(self, timeout: float = 30.0) -> None:
        """Start the server (again) on the same data and port; back when it accepts connections."""
        self.proc = subprocess.Popen([*self._as, _pg_bin("postgres"), "-D", str(self.data), "-p", str(self.port),
                                      "-k", str(self.sockets), "-c", "listen_addresses=127.0.0.1",
                                      "-c", "fsync=off"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ready = subprocess.run([_pg_bin("pg_isready"), "-h", "127.0.0.1", "-p", str(self.port)],
                                   capture_output=True)
            if ready.returncode == 0:
                return
            if self.proc.poll() is not None:
                raise RuntimeError(f"postgres exited with {self.proc.returncode}")
            time.sleep(0.1)
        raise RuntimeError("postgres did not accept connections")

    def stop(self) -> None:
        """Stop the server (a fast shutdown: what a plant's database outage looks like to the cells)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)
