"""What the API contract test and tools/fuzz_daemon.py share: the checks run on every response, a finished job to
read, and undoing what a fuzzed command changed."""

from __future__ import annotations

from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    ignored_auth,
    negative_data_rejection,
    response_schema_conformance,
    status_code_conformance,
    unsupported_method,
)

from tests.support.daemon import DaemonProcess, wait_for

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance,
          negative_data_rejection, unsupported_method, ignored_auth]


def finish_one_job(daemon: DaemonProcess) -> None:
    """Job 1 done (virtual-grid, seed 3) and calibration 1 made by it: real ids for the cases to reach."""
    with daemon.client() as client:
        job = client.post("/jobs", json={"routine": "virtual-grid", "params": TINY, "seed": 3}).json()
        assert wait_for(client, job["id"], {"done", "faulted", "aborted"})["state"] == "done"
        assert [c["id"] for c in client.get("/calibrations").json()["calibrations"]] == [1]


def undo(session, url: str, token: str, method: str, path: str, response) -> None:
    """Undo what an accepted case changed that would decide the next cases' answers (see the docstring)."""
    if method != "POST" or not 200 <= response.status_code < 300:
        return
    auth = {"Authorization": f"Bearer {token}"}
    if path == "/lock":
        session.delete(f"{url}/lock", headers={**auth, "X-Cellctl-Lock": response.json()["lock_id"]})
    elif path == "/jobs":
        session.post(f"{url}/jobs/{response.json()['id']}/abort", headers=auth)


TINY = {"rows": 3, "cols": 3, "n_verify": 3, "passes": 1}  # 12 steps: the smallest grid the model fits
