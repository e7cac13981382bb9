"""Fixtures of the daemon tests (their helpers: tests/support/daemon.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.daemon import SEED, SMALL, DaemonProcess, write_cell_file


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
