"""The API from its own schema: the OpenAPI document validates, and every operation in it, fuzzed with
schemathesis (valid and invalid inputs, a bounded number of examples), answers with something below 500;
malformed headers and non-finite numbers get a 4xx.

In-process: FastAPI's TestClient on a Daemon on the simulated micro cell (no socket, no subprocess). One
small job runs first so that job 1, its files and calibration 1 exist; then the worker is stopped, so that
fuzzed submissions stay queued and nothing competes for the two cores. Hypothesis keeps no database
(`database=None`) and draws the same examples every run (`derandomize`); CELLCTL_FUZZ_EXAMPLES changes
how many per operation and mode (default 20).
"""

from __future__ import annotations

import os
import time

import pytest
from daemon_helpers import SMALL, write_cell_file

import schemathesis  # the `test` extra
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode

from cellctl.daemon.auth import OperatorLock

EXAMPLES = int(os.environ.get("CELLCTL_FUZZ_EXAMPLES", "20"))
pytestmark = pytest.mark.filterwarnings("ignore:Using `httpx` with `starlette.testclient`")


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    from starlette.testclient import TestClient

    from cellctl.daemon.api import create_app
    from cellctl.daemon.service import Daemon

    daemon = Daemon(write_cell_file(tmp_path_factory.mktemp("fuzz"), realtime_factor=0.0))
    daemon.start()
    job = daemon.jobs.submit("virtual-grid", SMALL, 3, "fixture@test")
    daemon.worker.wake()
    deadline = time.monotonic() + 60
    while daemon.jobs.get(job.id).state != "done":
        assert time.monotonic() < deadline and daemon.jobs.get(job.id).state in ("queued", "running")
        time.sleep(0.05)
    daemon.worker.shutdown("fuzzing: no job runs")  # submitted jobs stay queued from here on
    app = create_app(daemon)
    client = TestClient(app, raise_server_exceptions=False)  # an exception in the app is a 500 here
    yield daemon, app, client
    client.close()
    daemon.stop("test over")


def send(client, kwargs: dict) -> int:
    """The status of one request; the event stream is closed once it has answered (it never ends)."""
    if isinstance(kwargs.get("data"), (bytes, str)):  # a raw body (schemathesis's negative cases)
        kwargs = dict(kwargs, content=kwargs.pop("data"))
    with client.stream(**kwargs) as r:
        if not r.headers.get("content-type", "").startswith("text/event-stream"):
            r.read()
        return r.status_code


def test_the_openapi_schema_validates(api):
    daemon, app, client = api
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    schema.validate()  # against the OpenAPI meta-schema of its version (raises on any violation)
    results = list(schema.get_all_operations())
    broken = [r.err() for r in results if not hasattr(r, "ok")]  # schemathesis: Ok(operation) | Err(problem)
    assert not broken
    paths = {op.path for op in (r.ok() for r in results)}
    raw = client.get("/openapi.json").json()
    assert paths == set(raw["paths"]) and {"/events", "/jobs", "/jobs/{job_id}/pause"} <= paths


KNOWN = {"job_id": 1, "cal_id": 1, "name": "cam1"}  # the fixture's job, its calibration, a real camera


def test_every_operation_answers_fuzzed_input_without_a_5xx(api):
    daemon, app, client = api
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    failures: list[str] = []
    seen: dict[str, dict[int, int]] = {}
    for result in schema.get_all_operations():
        op = result.ok()  # an Err has no ok(): the schema test names it
        label = f"{op.method.upper()} {op.path}"
        counts = seen.setdefault(label, {})
        strategies = [op.as_strategy(generation_mode=GenerationMode.POSITIVE),
                      op.as_strategy(generation_mode=GenerationMode.NEGATIVE)]
        known = {k: v for k, v in KNOWN.items() if "{" + k + "}" in op.path}
        if known:  # reach past the 404 of an unknown id: the real job, calibration, camera
            strategies.append(op.as_strategy(generation_mode=GenerationMode.POSITIVE, path_parameters=known))

        @settings(max_examples=EXAMPLES * len(strategies), deadline=None, database=None, derandomize=True,
                  suppress_health_check=list(HealthCheck))
        @given(case=st.one_of(strategies), with_token=st.sampled_from([True, True, True, False]))
        def run(case, with_token):
            headers = {"Authorization": f"Bearer {daemon.token}"} if with_token else None
            kwargs = case.as_transport_kwargs(headers=headers)
            try:
                status = send(client, kwargs)
            except Exception as exc:  # noqa: BLE001 - a request the client cannot even send is no server error
                if type(exc).__name__ in ("InvalidURL", "LocalProtocolError", "UnicodeEncodeError"):
                    return
                raise
            finally:
                daemon.lock = OperatorLock()  # a fuzzed POST /lock must not turn every later command into a 423
            counts[status] = counts.get(status, 0) + 1
            if status >= 500:
                failures.append(f"{label}: {status} for {case.as_curl_command()}")

        run()
    print("\n".join(f"{k}: {dict(sorted(v.items()))}" for k, v in seen.items()))
    assert not failures, "\n".join(failures[:20])
    documented = {f"{m.upper()} {path}" for path, ops in client.get("/openapi.json").json()["paths"].items()
                  for m in ops}
    assert set(seen) == documented  # every operation of the schema was fuzzed, the event stream too
    # the fuzzing got past the guards: some requests of every kind were accepted
    assert any(200 in v or 201 in v for k, v in seen.items() if k.startswith("POST"))
    assert all(v for v in seen.values())


def jobs_of(client) -> list:
    return client.get("/jobs", params={"limit": 1000}).json()["jobs"]


NON_FINITE = [b'{"routine": "hybrid", "params": {"supply_z_mm": NaN}}',
              b'{"routine": "hybrid", "params": {"supply_z_mm": Infinity}}',
              b'{"routine": "hybrid", "params": {"supply_z_mm": -Infinity}}',
              b'{"routine": "hybrid", "params": {"supply_z_mm": 1e999}}',
              b'{"routine": "hybrid", "params": {"supply_mm": [40.0, NaN]}}']


@pytest.mark.parametrize("body", NON_FINITE, ids=["nan", "inf", "-inf", "1e999", "nested"])
def test_non_finite_job_parameters_get_a_422_naming_the_field(api, body):
    """supply_z_mm has no bounds: before, NaN passed the routine's own validation and was queued (201)."""
    daemon, app, client = api
    before = jobs_of(client)
    r = client.post("/jobs", content=body, headers={"Authorization": f"Bearer {daemon.token}",
                                                   "Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    field = "params.supply_mm.1" if b"supply_mm" in body else "params.supply_z_mm"
    assert field in r.json()["detail"] and "finite" in r.json()["detail"]
    assert jobs_of(client) == before


# Malformed headers are tested over a real socket (test_api.py): the TestClient re-encodes header values as
# UTF-8, so a lone byte such as b"\xb2" ("²" in Latin-1, a digit to str.isdigit()) never reaches the app.
