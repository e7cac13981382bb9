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
