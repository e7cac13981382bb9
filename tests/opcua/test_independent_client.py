"""An OPC UA client nobody in the project wrote (node-opcua, Node.js) drives the cell as an MES would:
browse Objects/Cell, Start("virtual-grid", "{}", 3) with a user name and the daemon's token, follow
Jobs/Live/Step by subscription and JobStateChangedEventType events up to done, read
Jobs/Last/VerificationMean_um and find the HTTP API's figure; under None and Basic256Sha256 SignAndEncrypt.

A fresh node-opcua client with the certificate it made itself (trusted by nobody) browses anonymously under
None (the server ignores the certificate there) but cannot start a job; under SignAndEncrypt it is refused and
its certificate kept in the store's opcua/rejected/, and once `cellctl opcua trust` trusts it, it connects, the
daemon still running."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.long  # run first: see conftest.py

NODE_CLIENT = Path(__file__).resolve().parent / "node"
ADDRESS_SPACE = {"Identification", "State", "Devices", "Arm", "Jobs", "Calibrations", "Lock", "Locate"}


def run_mes(cell, mode: str, pki: str | None = None, **options) -> dict:
    """The node client's result. `pki`: a folder kept between runs, in which a client given no certificate
    (cert=None) makes its own; by default a fresh one per mode, with the certificate the cell file trusts."""
    if not (NODE_CLIENT / "node_modules").is_dir():
        pytest.fail("the node-opcua client is not installed: run tools/ensure-node (tools/test does)")
    folder = cell.folder / (pki or f"pki-{mode}")
    if pki is None:
        shutil.rmtree(folder, ignore_errors=True)
    args = {"url": cell.url, "mode": mode, "user": "mes-line-4", "password": cell.daemon.token,
            "routine": "virtual-grid", "parameters": "{}", "seed": 3, "pki": str(folder),
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
    # the subscription saw the job's steps go by, in order, towards its last: the server samples the live job at
    # each refresh, so on a loaded machine the job can take its last step and end between two samples (the final
    # count is Jobs/Last's result, read below)
    steps = [s for s in out["steps"] if s]
    assert len(steps) >= 5 and steps == sorted(steps) and steps[-1] <= result["n_samples"], out["steps"]
    states = [e["state"] for e in out["events"] if e["job"] == job]
    assert states[-1] == "done" and "running" in states, out["events"]
    assert all(e["routine"] == "virtual-grid" for e in out["events"] if e["job"] == job)
    assert out["last_id"] == job
    assert out["verification_mean_um"] == result["stats"]["verification"]["mean_um"]


def test_an_anonymous_node_opcua_start_is_refused(opcua_cell):
    """Under None a client's certificate, trusted or not, gives it no right: commands need a user."""
    with opcua_cell.daemon.client() as http:
        before = len(http.get("/jobs").json()["jobs"])
        for pki, cert in (("pki-anonymous-trusted", str(opcua_cell.client.pem)), ("pki-anonymous-own", None)):
            shutil.rmtree(opcua_cell.folder / pki, ignore_errors=True)
            out = run_mes(opcua_cell, "None", pki=pki, user=None, cert=cert, appUri=f"urn:cellctl-test:{pki}")
            assert out.get("start_status") != "Good"
            assert "BadUserAccessDenied" in (out.get("error", "") + out.get("start_status", "")), out
        assert len(http.get("/jobs").json()["jobs"]) == before


def rejected(cell) -> Path:
    return cell.daemon.store / "opcua" / "rejected"


def test_a_fresh_node_opcua_client_browses_anonymously_under_none(opcua_cell):
    pki = "pki-fresh-none"
    shutil.rmtree(opcua_cell.folder / pki, ignore_errors=True)
    out = run_mes(opcua_cell, "None", pki=pki, user=None, cert=None, appUri="urn:cellctl-test:fresh-none",
                  browseOnly=True)
    assert "error" not in out, out  # was: BadCertificateUntrusted
    assert ADDRESS_SPACE <= set(out["browse"]) and out["name"] == "sim-microcell"
    own = out["certificate_sha1"]  # the certificate node-opcua made for itself, presented in CreateSession
    assert len(own) == 40
    assert not (rejected(opcua_cell) / f"{own}.der").exists()  # ignored under None: not even kept


def cellctl(cell, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLCTL_")}
    return subprocess.run([sys.executable, "-m", "cellctl.cli", *args, "--config", str(cell.daemon.cell_file)],
                          capture_output=True, text=True, timeout=60, env=env)


def test_an_untrusted_node_opcua_client_is_rejected_kept_trusted_and_connects_without_a_restart(opcua_cell):
    pki, uri = "pki-fresh-secure", "urn:cellctl-test:fresh-secure"
    shutil.rmtree(opcua_cell.folder / pki, ignore_errors=True)
    pid = opcua_cell.daemon.proc.pid
    for _ in range(2):  # a retry is refused the same way, and its certificate is kept once
        out = run_mes(opcua_cell, "SignAndEncrypt", pki=pki, user=None, cert=None, appUri=uri, browseOnly=True)
        assert "BadCertificateUntrusted" in out.get("error", ""), out
    own = out["certificate_sha1"]
    assert [p.name for p in rejected(opcua_cell).iterdir() if own in p.name] == [f"{own}.der"]

    listed = cellctl(opcua_cell, "opcua", "certificates", "--json")
    assert listed.returncode == 0, listed.stderr
    entry = next(c for c in json.loads(listed.stdout)["rejected"] if c["thumbprint"] == own)
    assert entry["application_uri"] == uri

    # the daemon owns the store: the command goes through it, and its audit records it
    trusted = cellctl(opcua_cell, "opcua", "trust", own[:10])
    assert trusted.returncode == 0, trusted.stderr
    assert own[:12] in trusted.stdout and "daemon" in trusted.stderr
    assert not (rejected(opcua_cell) / f"{own}.der").exists()
    assert (opcua_cell.daemon.store / "opcua" / "trusted" / f"{own}.der").is_file()

    out = run_mes(opcua_cell, "SignAndEncrypt", pki=pki, user=None, cert=None, appUri=uri, browseOnly=True)
    assert "error" not in out, out
    assert out["certificate_sha1"] == own and ADDRESS_SPACE <= set(out["browse"])
    assert opcua_cell.daemon.proc.poll() is None and opcua_cell.daemon.proc.pid == pid  # no restart
    with opcua_cell.daemon.client() as http:
        audit = [a for a in http.get("/audit").json()["audit"] if a["target"] == f"opc ua certificate {own}"]
    assert [a["outcome"] for a in audit] == ["ok"] and audit[0]["action"] == "POST /opcua/certificates/trust"
