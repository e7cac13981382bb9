"""A daemon builds a simulated world per job: the last job's world must be freed when the next one is built. On a
cell with protocol simulators (the ABB socket protocol, the VGC10's Modbus server) their servers leave reference
cycles that would hold each world, tens of MB of images, until Python's rare full collection: the soak
(tools/soak.py) saw the daemon grow by that much a job. With Python's collector off, as between its full
collections, only the last two jobs' worlds may remain (the one before the live one may still be ending its
simulators' threads when the next is built; it goes with the next collection)."""

from __future__ import annotations

import gc
import weakref

from fastapi.testclient import TestClient

from cellctl.http.api import create_app
from cellctl.startup.daemon import Daemon

from tests.support.cells import write_abb_cell_file
from tests.support.daemon import SMALL, wait_for


def test_each_jobs_world_is_freed_when_the_next_is_built(tmp_path, monkeypatch):
    monkeypatch.delenv("CELLCTL_STORE", raising=False)  # the cell file's store_dir
    daemon = Daemon(write_abb_cell_file(tmp_path, extra=f"store_dir: {tmp_path / 'store'}"))
    daemon.start()
    worlds = []
    gc.disable()
    try:
        with TestClient(create_app(daemon), headers={"Authorization": f"Bearer {daemon.token}"}) as c:
            for seed in (0, 1, 2, 0):
                job = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": seed}).json()
                assert wait_for(c, job["id"], {"done", "faulted"})["state"] == "done"
                worlds.append(weakref.ref(daemon.cells.cell.context.existing_world))
        alive = [i for i, w in enumerate(worlds) if w() is not None]
        assert set(alive) <= {2, 3}, f"the worlds of jobs {alive} are still held (of 0-3, only 2 and 3 may be)"
    finally:
        gc.enable()
        daemon.stop("test over")
