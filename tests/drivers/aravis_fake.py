"""Aravis's fake GigE Vision camera (`arv-fake-gv-camera-0.8`, Debian aravis-tools) for the tests.

It speaks the real GVCP/GVSP protocol over UDP. It serves on one interface address: here
127.0.0.1 (`-i 127.0.0.1`, the `lo` interface), on the fixed GigE Vision control port 3956, so
one runs at a time on this address. `kill()` is a camera losing power, `start()` one coming back.

Its image is a diagonal ramp that the camera computes from its own registers, so a frame shows
what the camera applied: pixel (x, y) = clamp(((x + y + block_id) % 255) * scale) for Mono8 and
clamp(((256 (x + y + block_id)) % 65535) * scale) for Mono16, with
scale = 1 + GainRaw + log10(exposure_us / 10000) (aravis src/arvfakecamera.c).
"""

from __future__ import annotations

import ctypes
import errno
import importlib
import shutil
import signal
import socket
import subprocess
from pathlib import Path

import numpy as np

from tests.support.wait import eventually

BINARY = "arv-fake-gv-camera-0.8"
GVCP_PORT = 3956


def available() -> str | None:
    """Why the fake camera or the Aravis binding cannot run here, or None when both can."""
    if shutil.which(BINARY) is None:
        return f"{BINARY} is not installed (Debian aravis-tools: tools/ensure-system)"
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        importlib.import_module("gi.repository.Aravis")
    except (ImportError, ValueError) as exc:
        return f"the Aravis binding is not importable ({exc}): tools/ensure-system, then tools/ensure-venv"
    return None


def port_taken(host: str = "127.0.0.1", port: int = GVCP_PORT) -> bool:
    """Whether something holds the GVCP port on `host` (a running camera); sends nothing."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, port))
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            return True
        raise
    finally:
        probe.close()
    return False


class FakeGvCamera:
    """One fake camera process on `host`, started and stopped by the tests."""

    def __init__(self, log_dir: Path, serial: str = "CELL1", host: str = "127.0.0.1"):
        self.serial = serial
        self.host = host
        self.log = Path(log_dir) / "arv-fake-gv-camera.log"
        self.process: subprocess.Popen | None = None

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def start(self, timeout_s: float = 10.0) -> None:
        if self.running:
            return
        if port_taken(self.host):
            raise RuntimeError(f"UDP {self.host}:{GVCP_PORT} is taken: another GigE Vision camera (fake) runs here")
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen([BINARY, "-i", self.host, "-s", self.serial], stdin=subprocess.DEVNULL,
                                            stdout=log, stderr=log, preexec_fn=_die_with_parent)
        def bound() -> bool:  # bound: it answers GVCP from then on
            assert self.process.poll() is None, f"{BINARY} exited"
            return port_taken(self.host)

        try:
            eventually(bound, timeout=timeout_s, what=f"{BINARY} bound on {self.host}")
        except AssertionError:
            self.stop()
            raise RuntimeError(f"{BINARY} did not start on {self.host}; see {self.log}:\n{self.log.read_text()}") from None

    def kill(self) -> None:
        """The camera loses power: no goodbye on the wire."""
        if self.process is not None:
            self.process.kill()
            self.process.wait(10)
            self.process = None

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)
            self.process = None


def _die_with_parent() -> None:
    """In the child: end with the test process, even when that one is killed (no camera left on the port)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def next_block_id(block_id: int) -> int:
    """The fake's frame counter: 16 bits, 0 skipped (it starts at 65401 to show wrap-around bugs early)."""
    return 1 if block_id == 65535 else block_id + 1


def ramp(width: int, height: int, block_id: int, exposure_us: float, gain_raw: int, bits: int = 8) -> np.ndarray:
    """The image the fake camera sends for frame `block_id` with these register values."""
    scale = 1.0 + gain_raw + np.log10(exposure_us / 10000.0)
    x, y = np.meshgrid(np.arange(width), np.arange(height))
    if bits == 8:
        values = ((x + block_id + y) % 255) * scale
        return np.clip(values, 0, 255).astype(np.uint8)
    values = ((256 * x + 256 * block_id + 256 * y) % 65535) * scale
    return np.clip(values, 0, 65535).astype(np.uint16)
