"""Fixtures of the fleet tests: a real PostgreSQL and a real Mosquitto (servers.py), one of each per module."""

from __future__ import annotations

import pytest

from tests.support.servers import MosquittoServer, PostgresServer


@pytest.fixture(scope="module")
def postgres():
    server = PostgresServer().start()
    yield server
    server.close()


@pytest.fixture(scope="module")
def mosquitto():
    """A broker that wants a username and password (`mosquitto.username`, `.password`); a test that stops it
    resumes it before it ends."""
    server = MosquittoServer().start()
    yield server
    server.close()
