import os
import shutil
import subprocess
import time
from dataclasses import dataclass
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


# -- one full-size calibration of the default micro cell, shared by the session ------------------------------

CALIBRATED_SEED = 5


@dataclass(frozen=True)
class CalibratedCell:
    """calibrate-and-place at the cell file's defaults: its run folder, its (closed) store and its results."""

    seed: int
    folder: Path
    store_path: Path
    done: dict

    def store_copy(self, where: Path):
        """A test's own copy of the store (a CalibrationStore): what it saves stays out of the other tests' inputs."""
        from cellctl.calstore import CalibrationStore

        shutil.copytree(self.store_path, where)
        return CalibrationStore(where)


@pytest.fixture(scope="session")
def calibrated_cell(tmp_path_factory) -> CalibratedCell:
    """The slowest run of the suite, made once (seed 5: every figure in the README's tables)."""
    from cellctl.calstore import CalibrationStore
    from cellctl.config import load_cell_file
    from cellctl.runs import run_sequence

    config, text = load_cell_file(MICROCELL)
    folder = tmp_path_factory.mktemp("calibrated-cell")
    store = CalibrationStore(folder / "store")
    done = run_sequence("calibrate-and-place", config, text, folder / "cc", seed=CALIBRATED_SEED, store=store)
    store.close()
    return CalibratedCell(CALIBRATED_SEED, folder / "cc", folder / "store", done)


@pytest.fixture(scope="module")
def browser():
    """Debian's Chromium, headless, driven by Playwright (tests/chromium.py)."""
    from chromium import CHROMIUM, CHROMIUM_ARGS, require_chromium

    require_chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
        yield b
        b.close()
