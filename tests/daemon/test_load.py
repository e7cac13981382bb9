"""Load on the real daemon (loopback): 50 clients polling the status and 50 following the event stream while a
job runs leave the job's cell time, statistics, model and every sample exactly as when it ran alone.

The load is tools/load_daemon.py's (tests/daemon/daemon_load.py); bounded in time, it ends with the job.
Latencies are printed, never asserted (speed is measured by the tool, not by tests).
"""

from __future__ import annotations

import asyncio

from tests.support.daemon_load import compare_under_load

CLIENTS = 50


def test_fifty_clients_polling_and_following_events_change_nothing(start_daemon):
    daemon = start_daemon(realtime_factor=0.1)  # the job spends its 11.5 s of cell time as 1.15 s of wall time
    rep = asyncio.run(compare_under_load(daemon.url, daemon.token, clients=CLIENTS, poll_interval=0.1,
                                         time_limit_s=90.0))
    assert not rep.errors, rep.errors[:5]
    assert rep.same == {"cell time": True, "stats": True, "model": True, "samples (all columns)": True}
    assert rep.alone["id"] != rep.loaded["id"] and rep.loaded["result"]["n_samples"] == 24
    # the load was there while the job ran: every poller was answered, every stream carried the job's events
    assert len(rep.status_latencies) >= CLIENTS
    assert len(rep.events_per_stream) == CLIENTS and min(rep.events_per_stream) >= 24  # >= one per step
    assert daemon.terminate() == 0
    assert not [e for e in daemon.logs() if e.get("level") == "error"]
