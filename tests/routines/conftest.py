"""Fixtures of the routine tests: the ABB cells on free ports; the UR5e cell's wrist camera calibrated once."""

import pytest

from tests.conftest import ROOT
from tests.support.cells import write_abb_cell_file
from tests.support.shared_runs import SharedRun, made_once


@pytest.fixture
def abb_cell_file(tmp_path):
    """The micro cell on the ABB and VGC10 simulators."""
    return write_abb_cell_file(tmp_path)


@pytest.fixture
def irb120_abb_cell_file(tmp_path):
    """The IRB 120 CSM cell on the ABB simulator."""
    return write_abb_cell_file(tmp_path, base="sim-irb120-abb.yaml", gripper=False)


@pytest.fixture(scope="session")
def wrist_hand_eye_seed2(request, tmp_path_factory) -> SharedRun:
    """hand-eye of the wrist camera on config/sim-ur5e-handeye.yaml, seed 2, at the routine's defaults (15 poses + 5
    held out) without the touch test: the calibration test_iso9283.py measures through and test_table_pick.py picks
    through, made once per test run (tests/support/shared_runs.py); each module copies its store."""
    from cellctl.config import load_cell_file
    from cellctl.core import runs
    from cellctl.stores.calibrations import CalibrationStore

    def make(run, store_path):
        config, text = load_cell_file(ROOT / "config" / "sim-ur5e-handeye.yaml")
        store = CalibrationStore(store_path)
        try:
            return runs.run_routine("hand-eye", config, text, run, seed=2, store=store, overrides={"touches": 0})
        finally:
            store.close()

    return made_once(request, tmp_path_factory, "wrist-hand-eye-seed2", make)
