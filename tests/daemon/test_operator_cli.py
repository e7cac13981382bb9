"""`cellctl operator` against the real daemon (its web operator on the simulated VR cell): the pending request
shown, an instruction answered done or declined, a click request shown with where to answer it and refused
here; through the one service, so the lock and the audit apply as for every command."""

from __future__ import annotations

import json
import re

import pytest

from cellctl import cli

from tests.support.daemon import DaemonProcess, wait_for
from tests.support.operator import next_request, write_vr_cell

EXPERIMENTS = {"fig7_runs": 1, "n_runs": 1, "angles_deg": [28.0], "distances_in": [20.0, 2.0], "views": [],
               "standoff_in": 20.0}  # step 0: align by hand (an instruction); step 1: clicks


@pytest.fixture(scope="module")
def vr_daemon(tmp_path_factory):
    with DaemonProcess(write_vr_cell(tmp_path_factory.mktemp("operator-cli"), timeout_s=300)).start(timeout=120) as d:
        yield d


def operator(capsys, *args) -> tuple[int, str, str]:
    code = cli.main(["operator", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cellctl_operator_shows_answers_and_declines(vr_daemon, capsys, monkeypatch):
    monkeypatch.setenv("CELLCTL_URL", vr_daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", vr_daemon.token)
    code, out, _ = operator(capsys)
    assert code == 0 and "no operator request pending" in out

    c = vr_daemon.client()
    job = c.post("/jobs", json={"routine": "vr-experiments", "params": EXPERIMENTS, "seed": 3}).json()["id"]
    req = next_request(c, 0, job)
    assert req["kind"] == "align_by_hand"
    code, out, _ = operator(capsys, "show")
    assert code == 0
    assert f"operator request {req['id']} (align_by_hand, job {job})" in out and req["instruction"] in out
    assert f"cellctl operator done {req['id']}" in out and "standoff_m 0.508" in out
    code, out, _ = operator(capsys, "--json")
    assert code == 0 and json.loads(out)["request"]["id"] == req["id"]

    # the operator lock applies: another client holds it, the answer is refused and nothing changes
    lock = c.post("/lock", json={"holder": "bob", "ttl_s": 60}).json()
    code, _, err = operator(capsys, "done", str(req["id"]))
    assert code == 2 and "423" in err and "bob" in err
    assert c.get("/operator/request").json()["request"]["id"] == req["id"]
    c.request("DELETE", "/lock", headers={"X-Cellctl-Lock": lock["lock_id"]})

    code, out, _ = operator(capsys, "done", str(req["id"]))
    assert code == 0 and out.strip() == f"operator request {req['id']}: answered (job {job})"
    code, _, err = operator(capsys, "done", str(req["id"]))  # answered already
    assert code == 2 and f"operator request {req['id']} is not pending" in err
    code, _, err = operator(capsys, "done")
    assert code == 2 and "give the request's id" in err

    # a click request: shown, with where to answer it; not answerable here, neither done nor declined
    clicks = next_request(c, req["id"], job)
    assert clicks["kind"] == "click_points"
    code, out, _ = operator(capsys)
    assert code == 0 and f"operator request {clicks['id']} (click_points, job {job})" in out
    assert f"answer it at the web console: {vr_daemon.url}/console/" in out
    assert "camera side" in out and "object oru" in out and "at_least 5" in out
    for action in ("done", "decline"):
        code, _, err = operator(capsys, action, str(clicks["id"]))
        assert code == 2 and "asks for clicks" in err and f"{vr_daemon.url}/console/" in err
    assert c.get("/operator/request").json()["request"]["id"] == clicks["id"]
    assert c.post(f"/jobs/{job}/abort").status_code == 200
    assert wait_for(c, job, {"aborted"})["state"] == "aborted"

    # declined from the terminal: the job faults with the reason
    job = c.post("/jobs", json={"routine": "vr-experiments", "params": EXPERIMENTS, "seed": 3}).json()["id"]
    req = next_request(c, clicks["id"], job)
    code, out, _ = operator(capsys, "decline", str(req["id"]), "--reason", "the jog pendant is out of reach")
    assert code == 0 and f"operator request {req['id']}: declined" in out
    faulted = wait_for(c, job, {"faulted", "done", "aborted"})
    assert faulted["state"] == "faulted" and "the jog pendant is out of reach" in faulted["reason"], faulted
    code, out, _ = operator(capsys)
    assert code == 0 and f"the last, request {req['id']} (align_by_hand), ended declined" in out

    # each answer is in the audit log, with the CLI as its client
    audit = [a for a in c.get("/audit").json()["audit"] if a["target"].startswith("operator request")]
    outcomes = [(a["action"].rsplit("/", 1)[-1], a["outcome"].partition(":")[0]) for a in audit]
    assert outcomes == [("done", "refused 423"), ("done", "ok"), ("done", "refused 409"), ("decline", "ok")]
    assert "is not pending" in audit[2]["outcome"]  # a refusal keeps its reason
    assert all(re.match(r"^[\w.@:+-]+@127\.0\.0\.1$", a["client"]) and a["client"] != "anonymous@127.0.0.1"
               for a in audit)
    c.close()


def test_cellctl_operator_on_a_cell_whose_operator_is_not_the_web(start_daemon, capsys, monkeypatch):
    d = start_daemon()  # the micro cell: its operator is simulated
    monkeypatch.setenv("CELLCTL_TOKEN", d.token)
    code, out, _ = operator(capsys, "--url", d.url)
    assert code == 0 and "backend 'sim'" in out and "no operator request pending" in out
    code, _, err = operator(capsys, "done", "1", "--url", d.url)
    assert code == 2 and "not answered here" in err
