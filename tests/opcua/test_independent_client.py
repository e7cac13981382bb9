"""An OPC UA client nobody in the project wrote (node-opcua, Node.js) drives the cell as an MES would:
browse Objects/Cell, Start("virtual-grid", "{}", 3) with a user name and the daemon's token, follow
Jobs/Live/Step by subscription and JobStateChangedEventType events up to done, read
Jobs/Last/VerificationMean_um and find the HTTP API's figure; under None and Basic256Sha256 SignAndEncrypt."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.long  # run first: see conftest.py

NODE_CLIENT = Path(__file__).resolve().parent / "node"
ADDRESS_SPACE = {"Identification", "State", "Devices", "Arm", "Jobs", "Calibrations", "Lock", "Locate"}


def run_mes(cell, mode: str, **options) -> dict:
    if not (NODE_CLIENT / "node_modules").is_dir():
        pytest.fail("the node-opcua client is not installed: run tools/ensure-node (tools/test does)")
    pki = cell.folder / f"pki-{mode}"
    shutil.rmtree(pki, ignore_errors=True)
    args = {"url": cell.url, "mode": mode, "user": "mes-line-4", "password": cell.daemon.token,
            "routine": "virtual-grid", "parameters": "{}", "seed": 3, "pki": str(pki),
            "cert": str(cell.client.pem), "key": str(cell.client.key), "appUri": cell.client.uri,
            "serverCert": str(cell.server_cert), **options}
    done = subprocess.run(["node", "mes.mjs", json.dumps(args)], cwd=NODE_CLIENT, capture_output=True, text=True,
                          timeout=240)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    assert lines, f"node client printed no result:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
    return json.loads(lines[-1])


@pytest.mark.parametrize("mode", ["None", "SignAndEncrypt"])
def test_an_mes_runs_a_job_through_node_opcua(opcua_cell, mode):
    out = run_mes(opcua_cell, mode)
    assert "error" not in out, out
    assert ADDRESS_SPACE <= set(out["browse"])
    assert out["name"] == "sim-microcell"
    assert out["start_status"] == "Good"
    job = out["job"]
    with opcua_cell.daemon.client() as http:
        assert http.get(f"/jobs/{job}").json()["submitted_by"] == "mes-line-4@opcua"
        result = http.get(f"/jobs/{job}/result").json()
    # the subscription saw the job's steps go by, in order, up to its last
    steps = [s for s in out["steps"] if s]
    assert len(steps) >= 5 and steps == sorted(steps) and steps[-1] == result["n_samples"], out["steps"]
    states = [e["state"] for e in out["events"] if e["job"] == job]
    assert states[-1] == "done" and "running" in states, out["events"]
    assert all(e["routine"] == "virtual-grid" for e in out["events"] if e["job"] == job)
    assert out["last_id"] == job
    assert out["verification_mean_um"] == result["stats"]["verification"]["mean_um"]


def test_an_anonymous_node_opcua_start_is_refused(opcua_cell):
    with opcua_cell.daemon.client() as http:
        before = len(http.get("/jobs").json()["jobs"])
        out = run_mes(opcua_cell, "None", user=None)
        assert out.get("start_status") != "Good"
        assert "BadUserAccessDenied" in (out.get("error", "") + out.get("start_status", "")), out
        assert len(http.get("/jobs").json()["jobs"]) == before
