import os
import shutil
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from tests.support.wait import eventually

ROOT = Path(__file__).resolve().parents[1]
MICROCELL = ROOT / "config" / "sim-microcell.yaml"


def microcell_data() -> dict:
    return yaml.safe_load(MICROCELL.read_text())


@pytest.fixture
def microcell_sim():
    """The sim section of the default micro cell, as a validated config."""
    from drivers.sim.micro.config import SimWorldConfig

    return SimWorldConfig(**microcell_data()["sim"])


@pytest.fixture
def no_leftover_threads():
    """Servers, drivers and their logger threads all end with the test (a module asks for it: autouse there)."""
    before = set(threading.enumerate())
    yield

    def left() -> list[str]:
        return [t.name for t in set(threading.enumerate()) - before if t.is_alive()]

    try:
        eventually(lambda: not left(), timeout=3.0, what="the test's threads ending")
    except AssertionError:
        pytest.fail(f"threads left running: {left()}")


@pytest.fixture(scope="session", autouse=True)
def no_user_store(tmp_path_factory):
    """Module and session fixtures too keep their calibrations in a folder of the test run's, never in the user's
    data directory (a cell's store has one owner at a time: two runs there would refuse each other)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CELLCTL_STORE", str(tmp_path_factory.mktemp("session-store")))
        yield


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
        def created() -> bool:
            assert proc.poll() is None, f"socat exited with {proc.returncode}"
            return os.path.exists(a) and os.path.exists(b)

        eventually(created, timeout=5.0, every=0.01, what="socat's pty pair")
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
        from tests.support.shared_runs import copy_store

        return copy_store(self.store_path, where)


@pytest.fixture(scope="session")
def calibrated_cell(tmp_path_factory, request) -> CalibratedCell:
    """The slowest run of the suite, made once per test run (seed 5: every figure in the README's tables). With
    several workers (pytest-xdist) the first to need it makes it while the others wait, then all read it."""
    from tests.support.shared_runs import made_once

    def make(folder: Path, store_path: Path) -> dict:
        from cellctl.config import load_cell_file
        from cellctl.core.runs import run_sequence
        from cellctl.stores.calibrations import CalibrationStore

        config, text = load_cell_file(MICROCELL)
        store = CalibrationStore(store_path)
        try:
            return run_sequence("calibrate-and-place", config, text, folder, seed=CALIBRATED_SEED, store=store)
        finally:
            store.close()

    run = made_once(request, tmp_path_factory, "calibrated-cell", make)
    return CalibratedCell(CALIBRATED_SEED, run.folder, run.store_path, run.result)


@pytest.fixture(scope="module")
def browser():
    """Debian's Chromium, headless, driven by Playwright (tests/chromium.py)."""
    from tests.support.chromium import CHROMIUM, CHROMIUM_ARGS, require_chromium

    require_chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
        yield b
        b.close()


def pytest_collection_modifyitems(config, items):
    """Modules marked `long` first, each keeping its own order: with several workers (tools/test) the short
    modules then fill in around the long ones, instead of a worker starting a long one when the rest is done."""
    items.sort(key=lambda item: item.get_closest_marker("long") is None)


@pytest.fixture(scope="module")
def microcell():
    """The micro cell's file, loaded: (config, text)."""
    from cellctl.config import load_cell_file

    return load_cell_file(MICROCELL)
