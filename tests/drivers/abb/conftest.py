"""The ABB driver's fixtures: the simulator in each reply dialect, an AbbArm connected to it; and no thread left
behind by any test here."""

from __future__ import annotations

import pytest

from drivers.sim.servers.abb import DIALECTS, AbbServer

from tests.support.abb import (
    abb_on,
    sim_arm,
)


@pytest.fixture(autouse=True)
def _threads_end_with_each_test(no_leftover_threads):
    """Servers, drivers and their logger threads all end with the test."""


@pytest.fixture(params=DIALECTS)
def server(request, microcell_sim):
    """The simulator in each reply dialect: every test of the driver against it runs in both."""
    with AbbServer(sim_arm(microcell_sim), reply_dialect=request.param) as srv:
        yield srv



@pytest.fixture
def arm(server):
    device = abb_on(server)
    device.connect()
    yield device
    device.close()
