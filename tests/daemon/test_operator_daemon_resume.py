"""Through the real daemon: a VR approach whose coarse matching a person answered at the web operator's API,
paused after that step, the daemon restarted, the job resumed. The resumed job replays the answered step on a
fresh simulated world with the answers recorded in its samples and asks nobody; it ends with the figures of the
same job run uninterrupted with the same clicks, and its cell time includes the time the person took (counted
by the simulated clock, restored by the replay)."""

from __future__ import annotations

import json
import time

import pytest

from cellctl.stores.run_folder import read_samples_text

from tests.support.daemon import DaemonProcess, wait_for
from tests.support.operator import Truth, next_request, operator_events, write_vr_cell

SEED = 3
APPROACH = {"via_in": [4.0, 2.0]}  # 3 steps: the coarse matching (4 click requests) and two via points
DELAY_S = 0.4  # the person takes this long before answering each request


def answer_all(client, job: int, truth: Truth, delay_s: float = 0.0, pause_before_last: bool = False) -> list[int]:
    ids, last = [], 0
    for i in range(4):  # both objects in both views
        req = next_request(client, last, job)
        assert req["kind"] == "click_points" and req["job"] == job
        if pause_before_last and i == 3:  # deferred: it takes effect once the answered step is done
            assert client.post(f"/jobs/{job}/pause").status_code == 200
        time.sleep(delay_s)
        r = client.post(req["answer_url"], json={"clicks": truth.clicks(req)})
        assert r.status_code == 200, r.text
        ids.append(req["id"])
        last = req["id"]
    return ids


def samples_of(client, job: int) -> list[dict]:
    return read_samples_text(client.get(f"/jobs/{job}/samples").text)


def waits(rows: list[dict]) -> float:
    return sum(a["waited_s"] for r in rows if r.get("operator") for a in json.loads(r["operator"]))


def test_a_resumed_approach_replays_the_answered_step_and_asks_nobody(tmp_path):
    cell = write_vr_cell(tmp_path, timeout_s=300)
    with DaemonProcess(cell).start(timeout=120) as first:
        c = first.client()
        job = c.post("/jobs", json={"routine": "vr-approach", "params": APPROACH, "seed": SEED}).json()["id"]
        asked = answer_all(c, job, Truth(cell, SEED), DELAY_S, pause_before_last=True)
        paused = wait_for(c, job, {"paused", "done", "faulted", "aborted"})
        assert paused["state"] == "paused" and paused["progress"]["step"] == 1, paused
        before = samples_of(c, job)
        c.close()
    assert {r["step"] for r in before} == {0}
    recorded = json.loads(before[0]["operator"])
    assert [a["request"] for a in recorded] == asked and all(a["outcome"] == "answered" for a in recorded)
    assert all(a["by"].startswith("anonymous@") and a["waited_s"] >= DELAY_S for a in recorded)
    # the wait is cell time: step 0 took the person's time and two captures (0.1 s each)
    assert before[0]["cell_time_s"] == pytest.approx(waits(before) + 0.2, abs=1e-6)

    with DaemonProcess(cell).start(timeout=120) as second:  # restarted: a new process, a fresh world per job
        c = second.client()
        assert c.get(f"/jobs/{job}").json()["state"] == "paused"
        assert c.post(f"/jobs/{job}/resume").status_code == 200
        done = wait_for(c, job, {"done", "faulted", "aborted"})
        assert done["state"] == "done", done  # a replay that differed would have faulted (ReplayMismatch)
        nobody = c.get("/operator/request").json()
        assert nobody["request"] is None and nobody["last"] is None  # nothing was asked since the restart
        resumed = samples_of(c, job)
        result = c.get(f"/jobs/{job}/result").json()

        # the same job uninterrupted, the same clicks (the person's noise is drawn the same way), answered at once
        again = c.post("/jobs", json={"routine": "vr-approach", "params": APPROACH, "seed": SEED}).json()["id"]
        answer_all(c, again, Truth(cell, SEED))
        assert wait_for(c, again, {"done", "faulted", "aborted"})["state"] == "done"
        straight = samples_of(c, again)
        reference = c.get(f"/jobs/{again}/result").json()
        events = operator_events(second, again, 8)
        assert [e["state"] for e in events] == ["waiting", "answered"] * 4  # its own four requests
        c.close()
    assert resumed[0] == before[0] and [r["step"] for r in resumed] == [0, 1, 2]
    skip = ("cell_time_s", "operator")
    assert [{k: v for k, v in r.items() if k not in skip} for r in resumed] == \
           [{k: v for k, v in r.items() if k not in skip} for r in straight]
    assert result["model"] == reference["model"] and result["truth"]["final"] == reference["truth"]["final"]
    # cell time: the uninterrupted job's plus the difference in the person's waits (the replay counted them)
    assert result["cell_time_s"] - waits(resumed) == pytest.approx(reference["cell_time_s"] - waits(straight), abs=1e-6)
    assert result["cell_time_s"] >= 4 * DELAY_S + reference["cell_time_s"] - waits(straight)
