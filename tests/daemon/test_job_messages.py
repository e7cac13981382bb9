"""What the job commands say, in the user's terms (issue 25): a pause asked of a running job says it was requested
(its state still says "running"); a refused command says what happened to the job (what finished, what it stored
and activated) and what can be done now; an aborted sequence's results are those of the routines that finished
(HTTP, and `cellctl results` with exit status 130); the audit keeps each refusal's reason."""

from __future__ import annotations

import pytest

from tests.support.daemon import SEED, SMALL, running_daemon, wait_for, wait_step
from tests.support.wait import eventually

pytestmark = pytest.mark.long  # run first: see conftest.py

LONGER = dict(SMALL, rows=8, cols=8)  # 72 steps: still running when the pause is asked for


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    # a sequence's first routine made short
    with running_daemon(tmp_path_factory.mktemp("messages"), routines={"virtual-grid": SMALL}) as d:
        yield d


@pytest.fixture
def cli(daemon, monkeypatch, capsys):
    from cellctl import cli as client

    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)

    def run(*args):
        code = client.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return run


def test_commands_say_what_they_did_and_refusals_what_happened(daemon, cli):
    with daemon.client() as c:
        job = c.post("/jobs", json={"routine": "virtual-grid", "params": LONGER, "seed": SEED}).json()["id"]
        wait_step(c, job, 2)
        code, out, _ = cli("pause", job)
        assert code == 0 and out.strip() == f"job {job}: pause requested: it pauses at the next step boundary"
        wait_for(c, job, {"paused"})
        code, _, err = cli("pause", job)
        assert code == 2 and f"job {job} (virtual-grid) is paused (paused by" in err
        assert err.strip().endswith("it is paused already: resume it or abort it")
        code, out, _ = cli("abort", job)  # held at a step boundary, still the live job: the arm stops
        assert code == 0 and out.strip() == f"job {job}: the arm is stopped now; the job ends aborted, its samples kept"
        wait_for(c, job, {"aborted"})
        r = c.post(f"/jobs/{job}/pause")
        assert r.status_code == 409
        detail = r.json()["detail"]
        assert detail.startswith(f"job {job} (virtual-grid) was aborted (aborted by ")
        assert detail.endswith("; samples kept); nothing was stored (a routine stores its calibration when it "
                               "finishes); there is nothing to pause")
        code, out, err = cli("results", job)  # a single routine stopped before its end: no result, and why
        assert code == 130 and out == "" and f"job {job} (virtual-grid) was aborted" in err

        done = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": SEED}).json()["id"]
        wait_for(c, done, {"done"})
        cal = c.get(f"/jobs/{done}/result").json()["calibration"]
        r = c.post(f"/jobs/{done}/pause")
        assert r.status_code == 409 and r.json()["detail"] == (
            f"job {done} (virtual-grid) has finished (done); it stored and activated calibration {cal['id']} "
            f"(cam1 version {cal['version']}); there is nothing to pause")
        r = c.post(f"/jobs/{done}/ack")
        assert r.status_code == 409 and r.json()["detail"].endswith("; there is no fault to acknowledge")

        # the audit keeps each refusal with its reason
        refused = [a["outcome"] for a in c.get("/audit").json()["audit"] if a["outcome"].startswith("refused 409")]
        assert f"refused 409: job {job} (virtual-grid) is paused (paused by" in refused[-4]
        assert refused[-1].startswith(f"refused 409: job {done} (virtual-grid) has finished (done);")


def test_an_aborted_sequence_lists_the_routines_that_finished_and_what_they_stored(daemon, cli):
    with daemon.client() as c:
        job = c.post("/jobs", json={"routine": "calibrate-cell", "seed": SEED}).json()["id"]
        eventually(lambda: (c.get(f"/jobs/{job}").json().get("progress") or {}).get("item") not in (None, "virtual-grid"),
                   timeout=120, every=0.05, what="calibrate-cell starting its second routine")
        # its first routine has finished and stored cam1's calibration: abort the rest
        assert c.post(f"/jobs/{job}/abort").status_code == 200
        wait_for(c, job, {"aborted"})
        summary = c.get(f"/jobs/{job}/result").json()
        assert summary["complete"] is False and summary["state"] == "aborted"
        finished = list(summary["runs"])
        assert finished[0] == "virtual-grid" and "onboard-camera" in summary["not_finished"]
        cal = summary["runs"]["virtual-grid"]["calibration"]
        assert cal["target"] == "cam1" and cal["active"]
        assert c.get(f"/jobs/{job}/result", params={"item": "virtual-grid"}).json()["calibration"] == cal
        r = c.post(f"/jobs/{job}/resume")
        assert r.status_code == 409
        detail = r.json()["detail"]
        assert detail.startswith(f"job {job} (calibrate-cell) was aborted (aborted by ")
        assert f"; {len(finished)} of its 4 routines finished ({', '.join(finished)}); it stored and activated " \
               f"calibration {cal['id']} (cam1 version {cal['version']})" in detail
        assert detail.endswith("; an aborted job cannot be resumed; submit it again as a new job (it runs from the "
                               "start)")
    code, out, err = cli("results", job)
    assert code == 130, err
    assert "01-virtual-grid" in out  # its report's folder: the finished routine's results are shown
    assert f"job {job} (calibrate-cell) was aborted" in out and "not finished: " in out
