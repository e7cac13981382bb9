"""The daemon on the micro cell driven through real drivers (sim-microcell-ur.yaml: ur-rtde + EPick;
sim-microcell-abb.yaml: the ABB socket driver + VGC10): it starts the cell file's protocol simulators itself,
with its cell and again with each job's fresh world, so a daemon job equals `cellctl run` of the same seed."""

from __future__ import annotations

import pytest
from daemon_helpers import DaemonProcess, wait_for

from cellctl.config import load_cell_file
from cellctl.runs import run_routine
from drivers.sim.servers import free_ports
from tests.conftest import ROOT

SMALL_VG = {"rows": 4, "cols": 4, "n_verify": 10}
SEED = 2


def ur_cell(folder):
    path = folder / "ur.yaml"
    path.write_text(f"extends: {ROOT / 'config' / 'sim-microcell-ur.yaml'}\nstore_dir: {folder / 'store'}\n")
    return path


def abb_cell(folder):
    """sim-microcell-abb.yaml on free ports (the committed file's may be taken on a CI machine)."""
    motion, vgc = free_ports(2)
    while vgc in (motion, motion + 1):
        vgc, = free_ports()
    path = folder / "abb.yaml"
    path.write_text(f"""extends: {ROOT / 'config' / 'sim-microcell-abb.yaml'}
store_dir: {folder / 'store'}
arm: {{motion_port: {motion}, logger_port: {motion + 1}}}
gripper: {{port: {vgc}}}
sim:
  servers:
    - {{protocol: abb, port: {motion}}}
    - {{protocol: vgc10, port: {vgc}}}
""")
    return path


@pytest.mark.parametrize("make", [ur_cell, abb_cell], ids=["ur", "abb"])
def test_a_daemon_on_a_real_driver_cell_runs_as_cellctl_run_does(tmp_path, make):
    cell_file = make(tmp_path)
    config, text = load_cell_file(cell_file)
    expected = run_routine("virtual-grid", config, text, tmp_path / "in-process", seed=SEED, overrides=SMALL_VG)
    with DaemonProcess(cell_file).start(timeout=60) as daemon, daemon.client() as c:
        devices = {d["name"]: d["state"] for d in c.get("/cell").json()["devices"]}
        assert devices["arm"] == devices["gripper"] == "ready", devices
        job = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL_VG, "seed": SEED}).json()
        assert wait_for(c, job["id"], {"done", "faulted"}, timeout=240)["state"] == "done"
        result = c.get(f"/jobs/{job['id']}/result").json()
        # a second job: the simulators started again on its fresh world
        again = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL_VG, "seed": SEED}).json()
        assert wait_for(c, again["id"], {"done", "faulted"}, timeout=240)["state"] == "done"
        second = c.get(f"/jobs/{again['id']}/result").json()
    for got in (result, second):
        assert got["stats"] == expected["stats"]
        assert got["model"] == expected["model"]
        assert got["cell_time_s"] == expected["cell_time_s"]
