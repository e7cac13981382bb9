"""The plant's real servers for the tests, from Debian (tools/ensure-system), on loopback on a free port with a
temporary data directory, stopped afterwards: PostgreSQL (the plant database) and Mosquitto (the event stream).
PostgreSQL refuses to run as root, so as root it runs as the `postgres` user the package made; Mosquitto is told
to stay root (`user root`), which it accepts."""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

from tests.support.ports import free_port
from tests.support.wait import eventually


def _pg_bin(name: str) -> str:
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    if not found:
        raise RuntimeError(f"PostgreSQL's {name} is not installed: run tools/ensure-system")
    return found[-1]


class PostgresExited(RuntimeError):
    pass


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
        for attempt in range(3):  # a port free when picked may be taken before postgres binds it (another run's)
            try:
                self.resume()
                break
            except PostgresExited:
                if attempt == 2:
                    raise
                self.port = free_port()
        self._run(_pg_bin("psql"), "-h", str(self.sockets), "-p", str(self.port), "-U", "postgres", "-q", "-c",
                  f"CREATE ROLE cellctl LOGIN PASSWORD '{self.password}'", "-c", "CREATE DATABASE plant OWNER cellctl")
        return self

    def resume(self, timeout: float = 30.0) -> None:
        """Start the server (again) on the same data and port; back when it accepts connections."""
        self.proc = subprocess.Popen([*self._as, _pg_bin("postgres"), "-D", str(self.data), "-p", str(self.port),
                                      "-k", str(self.sockets), "-c", "listen_addresses=127.0.0.1",
                                      "-c", "fsync=off"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

        def accepting() -> bool:
            if self.proc.poll() is not None:
                raise PostgresExited(f"postgres exited with {self.proc.returncode} (port {self.port})")
            return subprocess.run([_pg_bin("pg_isready"), "-h", "127.0.0.1", "-p", str(self.port)],
                                  capture_output=True).returncode == 0

        eventually(accepting, timeout=timeout, every=0.1, what="postgres accepting connections")

    def stop(self) -> None:
        """Stop the server (a fast shutdown: what a plant's database outage looks like to the cells)."""
        if self.proc is not None and self.proc.poll() is None:
            # pg_ctl signals postgres itself (not runuser) and waits until it is down: SIGTERM alone is a smart
            # shutdown, which waits for every client, and the cells' replicators never leave
            self._run(_pg_bin("pg_ctl"), "stop", "-D", str(self.data), "-m", "fast", "-w", "-t", "60")
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)


class MosquittoServer:
    """mosquitto -c <its own config>: a listener on 127.0.0.1:`port`, a password file (or anonymous access when
    `password` is None), and persistence in its temporary directory, so a graceful restart (stop, resume) keeps
    persistent sessions and the QoS 1 messages queued for them. `tls`: (certificate, key) files to serve TLS
    with instead of plain MQTT; `acl`: the text of an ACL file (mosquitto.conf(5)) limiting who reads and writes
    what."""

    def __init__(self, username: str = "cellctl", password: str | None = "cellctl-test-password",
                 tls: tuple[Path, Path] | None = None, acl: str | None = None):
        self.username, self.password, self.tls, self.acl = username, password, tls, acl
        self.port = free_port()
        self.root = Path(tempfile.mkdtemp(prefix="cellctl-mqtt-"))
        self.config, self.log = self.root / "mosquitto.conf", self.root / "mosquitto.log"
        self.proc: subprocess.Popen | None = None

    def start(self) -> "MosquittoServer":
        lines = [f"listener {self.port} 127.0.0.1",
                 "persistence true", f"persistence_location {self.root}/",
                 f"log_dest file {self.log}", "log_type error", "log_type warning", "log_type notice",
                 "log_type information"]
        if os.geteuid() == 0:
            lines.append("user root")  # otherwise it drops to `mosquitto`, who cannot write our temp dir
        if self.password is None:
            lines.append("allow_anonymous true")
        else:
            passwd = self.root / "passwd"
            subprocess.run(["mosquitto_passwd", "-c", "-b", str(passwd), self.username, self.password], check=True,
                           capture_output=True, timeout=30)
            lines += ["allow_anonymous false", f"password_file {passwd}"]
        if self.tls is not None:
            lines += [f"certfile {self.tls[0]}", f"keyfile {self.tls[1]}"]
        if self.acl is not None:
            (self.root / "acl").write_text(self.acl)
            lines.append(f"acl_file {self.root / 'acl'}")
        self.config.write_text("\n".join(lines) + "\n")
        self.resume()
        return self

    def resume(self, timeout: float = 10.0) -> None:
        """Start the broker (again) on the same port and data; back when it accepts connections."""
        self.proc = subprocess.Popen(["/usr/sbin/mosquitto", "-c", str(self.config)], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE)
        def accepting() -> bool:
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited with {self.proc.returncode}: "
                                   f"{self.proc.stderr.read().decode(errors='replace')} "
                                   f"{self.log.read_text() if self.log.exists() else ''}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
            except OSError:
                return False
            return True

        eventually(accepting, timeout=timeout, what="mosquitto accepting connections")

    def stop(self) -> None:
        """Stop the broker gracefully (SIGTERM: it saves its sessions and queued messages, then exits)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        if self.proc is not None:
            self.proc.stderr.close()
        self.proc = None

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)
