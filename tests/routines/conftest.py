"""What several routine tests share: one full-size calibration of the default micro cell."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest

from cellctl.calstore import CalibrationStore
from cellctl.config import load_cell_file
from cellctl.runs import run_sequence
from tests.conftest import MICROCELL

CALIBRATED_SEED = 5


@dataclass(frozen=True)
class CalibratedCell:
    """calibrate-and-place at the cell file's defaults: its run folder, its (closed) store and its results."""

    seed: int
    folder: Path
    store_path: Path
    done: dict

    def store_copy(self, where: Path) -> CalibrationStore:
        """A test's own copy of the store: what it saves stays out of the other tests' inputs."""
        shutil.copytree(self.store_path, where)
        return CalibrationStore(where)


@pytest.fixture(scope="session")
def calibrated_cell(tmp_path_factory) -> CalibratedCell:
    """The slowest run of the suite, made once (seed 5: every figure in the README's tables)."""
    config, text = load_cell_file(MICROCELL)
    folder = tmp_path_factory.mktemp("calibrated-cell")
    store = CalibrationStore(folder / "store")
    done = run_sequence("calibrate-and-place", config, text, folder / "cc", seed=CALIBRATED_SEED, store=store)
    store.close()
    return CalibratedCell(CALIBRATED_SEED, folder / "cc", folder / "store", done)
