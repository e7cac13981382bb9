"""The API keeps its own contract: schemathesis against the running daemon finds nothing.

A real daemon (`python -m cellctl.startup`, as `cellctl serve` starts it) on loopback, on the simulated
micro cell, with one finished job and so one calibration. Every operation of its /openapi.json is run
through schemathesis's examples, coverage and fuzzing phases (valid and invalid input, undocumented
methods, requests without or with a wrong token) with exactly these checks: an answer below 500, a status
code, a content type and a body the schema documents for the operation, invalid input refused, an
undocumented method answered 405 with `Allow`, a command without a valid token refused. A second pass
reaches past the 404 of an unknown id with the fixture's job, calibration and camera.

The test cleans up after what it was allowed to do, so that one case does not decide the next ones'
answers: an operator lock it took is released (else every later command would get 423), a job it
submitted is aborted while still queued (else the worker would spend the run on it and every command
that needs an idle cell would get 409).

Hypothesis keeps no database and draws the same examples every run (`derandomize`);
CELLCTL_FUZZ_EXAMPLES changes how many the fuzzing draws per operation (default 5; the coverage phase
adds its own, a few dozen per operation). The event stream never ends: it is
read until it has been quiet for a moment, then closed; a camera's live stream (MJPEG) is read to its first
frame, then closed.
"""

from __future__ import annotations

import os

import pytest
import requests
import schemathesis  # the `test` extra
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode
from schemathesis.config import SchemathesisConfig
from schemathesis.core.failures import FailureGroup
from schemathesis.pytest.lazy import get_all_tests  # what @schema.parametrize runs (its fixture form fails on pytest 9)

from tests.support.api_contract import CHECKS, finish_one_job, undo
from tests.support.daemon import DaemonProcess, write_cell_file

EXAMPLES = int(os.environ.get("CELLCTL_FUZZ_EXAMPLES", "5"))
EVENTS_QUIET_S = 0.1  # the stream's first line comes at once; then it is silent until an event




@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """The daemon, with one finished job."""
    daemon = DaemonProcess(write_cell_file(tmp_path_factory.mktemp("contract"), realtime_factor=0.0)).start()
    finish_one_job(daemon)
    session = requests.Session()
    session.trust_env = False  # loopback: no proxy settings to read from the environment at every request
    yield daemon, session
    session.close()
    daemon.terminate()
    daemon.log.close()


@pytest.fixture(scope="module")
def live_schema(cell):
    daemon, _ = cell
    config = SchemathesisConfig.from_dict({
        "generation": {"deterministic": True, "max-examples": EXAMPLES},
        "phases": {"examples": {"enabled": True}, "coverage": {"enabled": True}, "fuzzing": {"enabled": True},
                   "stateful": {"enabled": False}},
    })
    return schemathesis.openapi.from_url(f"{daemon.url}/openapi.json", config=config)




def send(case, daemon: DaemonProcess, session: requests.Session):
    """Send the case with the token, then undo what it changed."""
    auth = {"Authorization": f"Bearer {daemon.token}"}
    if case.path.endswith("/live.mjpg"):
        return send_live(case, daemon, session, auth)
    timeout = (5.0, EVENTS_QUIET_S) if case.path == "/events" else 30.0
    try:
        response = case.call(base_url=daemon.url, session=session, headers=auth, timeout=timeout)
    except requests.exceptions.ReadTimeout:
        if case.path != "/events":
            raise
        timeout = (5.0, 2.0)  # a loaded machine sent the stream's head later than the quiet time: once more, patient
        response = case.call(base_url=daemon.url, session=session, headers=auth, timeout=timeout)
    undo(session, daemon.url, daemon.token, case.method, case.path, response)
    transport = {"base_url": daemon.url, "session": session, "headers": auth, "timeout": timeout}
    return response, auth, transport


def send_live(case, daemon: DaemonProcess, session: requests.Session, auth: dict):
    """A camera's live stream (MJPEG) never ends while its client reads, and schemathesis reads a body whole (an
    event stream only until a time-out): sent here, its head and first frame read, then the connection closed (the
    daemon stops capturing); a refusal's body is read whole. Validated as schemathesis's own answer."""
    from schemathesis.core.transport import Response

    timeout = 30.0
    kwargs = case.as_transport_kwargs(base_url=daemon.url, headers=auth)
    raw = session.request(**{**kwargs, "stream": True, "timeout": timeout})
    if raw.headers.get("content-type", "").startswith("multipart/"):
        head = b""
        for chunk in raw.iter_content(8192):
            head += chunk
            if b"\r\n\r\n" in head:
                break
        raw._content, raw._content_consumed = head, True  # what the checks read
        raw.close()
    else:
        raw.content  # noqa: B018 - read whole
    response = Response.from_requests(raw, verify=True)
    undo(session, daemon.url, daemon.token, case.method, case.path, response)
    return response, auth, {"base_url": daemon.url, "session": session, "headers": auth, "timeout": timeout}


class Findings:
    """Each operation's answers by status, and every distinct failure (operation, what failed)."""

    def __init__(self):
        self.statuses: dict[str, dict[int, int]] = {}
        self.failures: dict[tuple[str, str], str] = {}
        self.phases: dict[str, int] = {}

    def validate(self, case, daemon, session) -> None:
        response, auth, transport = send(case, daemon, session)
        phase = case.meta.phase.name.value if case.meta else "?"
        self.phases[phase] = self.phases.get(phase, 0) + 1
        counts = self.statuses.setdefault(case.operation.label, {})
        counts[response.status_code] = counts.get(response.status_code, 0) + 1
        try:
            case.validate_response(response, checks=CHECKS, headers=auth, transport_kwargs=transport)
        except FailureGroup as group:
            for failure in group.exceptions:
                self.failures.setdefault((case.operation.label, failure.title), str(group))

    def report(self) -> str:
        return "\n\n".join(f"{op}: {title}\n{text[:1500]}" for (op, title), text in sorted(self.failures.items()))


SETTINGS = settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=True,
                    suppress_health_check=list(HealthCheck))
KNOWN_SETTINGS = settings(SETTINGS, max_examples=max(EXAMPLES // 3, 1))


def test_every_operation_keeps_its_contract(cell, live_schema):
    daemon, session = cell
    findings = Findings()

    def test(case):
        findings.validate(case, daemon, session)

    for result in get_all_tests(schema=live_schema, test_func=test, settings=SETTINGS, given_kwargs={}):
        operation, run = result.ok()  # an Err (a schema schemathesis cannot read) has no ok()
        run()
    assert not findings.failures, findings.report()
    documented = {f"{m.upper()} {path}" for path, ops in live_schema.raw_schema["paths"].items() for m in ops}
    assert set(findings.statuses) == documented  # every operation was run, the event stream too
    # it got past the guards: some commands of every kind were accepted
    assert any(200 in v or 201 in v for k, v in findings.statuses.items() if k.startswith("POST"))


KNOWN = {"job_id": 1, "cal_id": 1, "name": "cam1"}  # the fixture's job, its calibration, a real camera


def test_operations_on_the_real_job_calibration_and_camera_keep_their_contract(cell, live_schema):
    """The fuzzing above reaches job 1 and calibration 1 (the smallest ids) but never a camera's name."""
    daemon, session = cell
    findings = Findings()
    for result in live_schema.get_all_operations():
        op = result.ok()
        known = {k: v for k, v in KNOWN.items() if "{" + k + "}" in op.path}
        if known:
            strategy = op.as_strategy(generation_mode=GenerationMode.POSITIVE, path_parameters=known)
            KNOWN_SETTINGS(given(case=strategy)(lambda case: findings.validate(case, daemon, session)))()
    assert not findings.failures, findings.report()
    assert all(200 in v for k, v in findings.statuses.items() if k.startswith("GET") and "operator" not in k)
