"""The daemon on the micro cell driven through real drivers (sim-microcell-ur.yaml: ur-rtde + EPick;
sim-microcell-abb.yaml: the ABB socket driver + VGC10): it starts the cell file's protocol simulators itself,
with its cell and again with each job's fresh world, so a daemon job equals `cellctl run` of the same seed."""

from __future__ import annotations

import pytest

from cellctl.config import load_cell_file
from cellctl.core.runs import run_routine

from tests.support.cells import write_abb_cell_file, write_ur_cell_file
from tests.support.daemon import DaemonProcess, wait_for

pytestmark = pytest.mark.long  # run first: see conftest.py

SMALL_VG = {"rows": 4, "cols": 4, "n_verify": 10}
SEED = 2


def ur_cell(folder):
    return write_ur_cell_file(folder)


def abb_cell(folder):
    return write_abb_cell_file(folder, extra=f"store_dir: {folder / 'store'}")


@pytest.mark.parametrize("make", [ur_cell, abb_cell], ids=["ur", "abb"])
def test_a_daemon_on_a_real_driver_cell_runs_as_cellctl_run_does(tmp_path, make):
    cell_file = make(tmp_path)
    config, text = load_cell_file(cell_file)
    expected = run_routine("virtual-grid", config, text, tmp_path / "in-process", seed=SEED, overrides=SMALL_VG)
    with DaemonProcess(cell_file).start(timeout=120) as daemon, daemon.client() as c:
        devices = {d["name"]: d["state"] for d in c.get("/cell").json()["devices"]}
        assert devices["arm"] == devices["gripper"] == "ready", devices
        job = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL_VG, "seed": SEED}).json()
        assert wait_for(c, job["id"], {"done", "faulted"}, timeout=240)["state"] == "done"
        result = c.get(f"/jobs/{job['id']}/result").json()
        # a second job: the simulators started again on its fresh world
        again = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL_VG, "seed": SEED}).json()
        got = wait_for(c, again["id"], {"done", "faulted"}, timeout=240)
        assert got["state"] == "done", got
        second = c.get(f"/jobs/{again['id']}/result").json()
    for got in (result, second):
        assert got["stats"] == expected["stats"]
        assert got["model"] == expected["model"]
        assert got["cell_time_s"] == expected["cell_time_s"]
