"""Fixtures of the fleet tests: a real PostgreSQL (servers.py), one per module."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from servers import PostgresServer  # noqa: E402


@pytest.fixture(scope="module")
def postgres():
    server = PostgresServer().start()
    yield server
    server.close()
