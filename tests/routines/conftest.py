"""Fixtures of the routine tests: the ABB cells on free ports."""

import pytest

from tests.support.cells import write_abb_cell_file


@pytest.fixture
def abb_cell_file(tmp_path):
    """The micro cell on the ABB and VGC10 simulators."""
    return write_abb_cell_file(tmp_path)


@pytest.fixture
def irb120_abb_cell_file(tmp_path):
    """The IRB 120 CSM cell on the ABB simulator."""
    return write_abb_cell_file(tmp_path, base="sim-irb120-abb.yaml", gripper=False)
