"""The API from its own schema, in-process: the OpenAPI document validates, and non-finite numbers get a 422.

The schemathesis run over every operation is against the running daemon, in test_api_contract.py; this keeps
what needs no socket: FastAPI's TestClient on a Daemon on the simulated micro cell.
"""

from __future__ import annotations

import pytest
import schemathesis  # the `test` extra

from tests.support.daemon import write_cell_file

pytestmark = pytest.mark.filterwarnings("ignore:Using `httpx` with `starlette.testclient`")


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    from starlette.testclient import TestClient

    from cellctl.http.api import create_app
    from cellctl.startup.daemon import Daemon

    daemon = Daemon(write_cell_file(tmp_path_factory.mktemp("fuzz"), realtime_factor=0.0))
    daemon.start()
    app = create_app(daemon)
    client = TestClient(app, raise_server_exceptions=False)  # an exception in the app is a 500 here
    yield daemon, app, client
    client.close()
    daemon.stop("test over")


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
