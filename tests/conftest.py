import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
MICROCELL = ROOT / "config" / "sim-microcell.yaml"


def microcell_data() -> dict:
    return yaml.safe_load(MICROCELL.read_text())


@pytest.fixture
def microcell_sim():
    """The sim section of the default micro cell, as a validated config."""
    from drivers.sim.config import SimWorldConfig

    return SimWorldConfig(**microcell_data()["sim"])


@pytest.fixture(autouse=True)
def isolated_store(tmp_path, monkeypatch):
    """Every test keeps its calibrations in its own folder, never in the user's data directory."""
    monkeypatch.setenv("CELLCTL_STORE", str(tmp_path / "store"))
    return tmp_path / "store"


@pytest.fixture
def pty_pair(tmp_path):
    """Two linked pseudo-terminals from socat: (driver end, simulator end). Killed afterwards."""
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (tools/ensure-system installs it)")
    a, b = str(tmp_path / "ttyA"), str(tmp_path / "ttyB")
    proc = subprocess.Popen(["socat", "-d", "-d", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 5.0
        while not (os.path.exists(a) and os.path.exists(b)):
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail("socat did not create the pty pair within 5 s")
            time.sleep(0.01)
        yield a, b
    finally:
        proc.terminate()
        proc.wait(5)
