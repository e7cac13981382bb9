"""The OPC UA server through asyncua's client over TCP: the address space, reading, subscriptions, every
method, both security modes, who may call (anonymous, a wrong token, a certificate, the operator lock),
and bad arguments, after which the server still answers."""

from __future__ import annotations

import asyncio
import json
import math

import pytest
from asyncua import ua

from tests.support.opcua import I32, SMALL, U32, B, D, S, Session, jobs, run, start_args, wait_idle

PATHS = {
    "Identification": ["Name", "Description", "SoftwareRevision", "Simulated"],
    "State": ["CurrentState", "LiveJobId"],
    "Arm": ["X_mm", "Y_mm", "Z_mm", "Alpha_deg"],
    "Jobs/Live": ["Id", "Routine", "State", "Step", "Total", "CellTime_s", "Residual_um"],
    "Jobs/Last": ["Id", "Routine", "State", "Reason", "VerificationMean_um", "VerificationMax_um", "ResultJson"],
}












def test_anonymous_sessions_browse_and_read_everything_the_issue_names(opcua_cell):
    async def go():
        async with Session(opcua_cell) as s:
            for folder, names in PATHS.items():
                for name in names:
                    await s.read(f"{folder}/{name}")
            assert await s.read("Identification/Name") == "sim-microcell"
            assert await s.read("Identification/Simulated") is True
            assert await s.read("State/CurrentState") in ("Idle", "Running")
            devices = [(await n.read_browse_name()).Name for n in await (await s.node("Devices")).get_children()]
            assert {"arm", "gripper", "cam1", "cam2"} <= set(devices)
            assert await s.read("Devices/arm/State") == "ready"
            assert math.isfinite(await s.read("Arm/X_mm"))
            cal = await s.read("Calibrations/cam1/ActiveId")
            assert cal > 0 and await s.read("Calibrations/cam1/Health") in ("ok", "unchecked", "drift")
            with pytest.raises(ua.UaStatusCodeError):  # variables are the server's to write
                await (await s.node("State/CurrentState")).write_value(ua.Variant("Idle", S))
    run(go())


def test_anonymous_and_wrong_token_sessions_cannot_call(opcua_cell):
    before = len(jobs(opcua_cell))

    async def go():
        async with Session(opcua_cell) as s:
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await s.call("Jobs/Start", *start_args())
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await s.call("Locate", ua.Variant("cam1", S), ua.Variant(1000.0, D), ua.Variant(800.0, D))
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with Session(opcua_cell, "mes", "not-the-token"):
                pass
    run(go())
    assert len(jobs(opcua_cell)) == before


def test_a_job_started_paused_resumed_and_aborted_with_events(opcua_cell):
    token = opcua_cell.daemon.token

    async def go():
        async with Session(opcua_cell, "line-plc", token) as s:
            seen: list = []

            class Handler:
                def event_notification(self, event):
                    seen.append(event)

            sub = await s.client.create_subscription(50, Handler())
            etype = await s.client.nodes.root.get_child(["0:Types", "0:EventTypes", "0:BaseEventType",
                                                         f"{s.ns}:JobStateChangedEventType"])
            await sub.subscribe_events(s.client.nodes.server, etype)
            job = await s.call("Jobs/Start", *start_args(params=json.dumps({"rows": 5, "cols": 5, "passes": 1})))
            for _ in range(200):
                if await s.read("Jobs/Live/Step") >= 2:
                    break
                await asyncio.sleep(0.05)
            assert await s.read("Jobs/Live/Id") == job and await s.read("Jobs/Live/Routine") == "virtual-grid"
            await s.call("Jobs/Pause", ua.Variant(job, U32), ua.Variant(False, B))
            for _ in range(200):
                if await s.read("State/CurrentState") == "Paused":
                    break
                await asyncio.sleep(0.05)
            assert await s.read("State/CurrentState") == "Paused"
            await s.call("Jobs/Resume", ua.Variant(job, U32))
            await s.call("Jobs/Abort", ua.Variant(job, U32))
            for _ in range(200):
                if any(e.State == "aborted" for e in seen):
                    break
                await asyncio.sleep(0.05)
            states = [e.State for e in seen if e.JobId == job]
            assert states[0] in ("queued", "running") and "paused" in states and states[-1] == "aborted", states
            await asyncio.sleep(1.5)
            assert await s.read("Jobs/Last/Id") == job and await s.read("Jobs/Last/State") == "aborted"
            # acknowledging a job that is not faulted is refused with the service's reason
            with pytest.raises(ua.UaStatusCodeError):
                await s.call("Jobs/Acknowledge", ua.Variant(job, U32))
            return job
    job = run(go())
    with opcua_cell.daemon.client() as http:
        audit = [a for a in http.get("/audit").json()["audit"] if a["target"] == f"job {job}"]
    assert {a["action"] for a in audit} >= {"OPC UA Jobs/Pause", "OPC UA Jobs/Resume", "OPC UA Jobs/Abort"}
    assert all(a["client"] == "line-plc@opcua" and a["who"] == "token" for a in audit)


def test_the_operator_lock_holds_for_opc_ua_sessions(opcua_cell):
    token = opcua_cell.daemon.token
    with opcua_cell.daemon.client() as http:
        lock = http.post("/lock", json={"holder": "engineer at the cell", "ttl_s": 60}).json()
        before = len(jobs(opcua_cell))

        async def refused():
            async with Session(opcua_cell, "mes", token) as s:
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                    await s.call("Jobs/Start", *start_args())
                for _ in range(40):  # the variables follow the lock within a refresh (1 s)
                    if await s.read("Lock/Held"):
                        break
                    await asyncio.sleep(0.1)
                assert await s.read("Lock/Held") is True
                assert await s.read("Lock/Holder") == "engineer at the cell"
        run(refused())
        assert len(jobs(opcua_cell)) == before
        http.request("DELETE", "/lock", headers={"X-Cellctl-Lock": lock["lock_id"]})

    async def holds():
        async with Session(opcua_cell, "mes", token) as s:
            lock_id = await s.call("Lock/Acquire", ua.Variant("MES line 4", S), ua.Variant(60.0, D))
            with opcua_cell.daemon.client() as http:  # now an HTTP client without the lock is the one refused
                assert http.post("/jobs", json={"routine": "virtual-grid", "params": json.loads(SMALL)}).status_code == 423
            job = await s.call("Jobs/Start", *start_args())
            await s.call("Jobs/Abort", ua.Variant(job, U32))
            await s.call("Lock/Release")
            assert isinstance(lock_id, str) and lock_id
    run(holds())
    wait_idle(opcua_cell)


def test_secure_channels_take_trusted_clients_only_and_certificates_as_users(opcua_cell):
    async def go():
        for mode in (ua.MessageSecurityMode.Sign, ua.MessageSecurityMode.SignAndEncrypt):
            async with Session(opcua_cell, "mes", opcua_cell.daemon.token, secure=(opcua_cell.client, mode)) as s:
                x, y, sigma, warning = await s.call("Locate", ua.Variant("cam1", S), ua.Variant(1224.0, D),
                                                    ua.Variant(1025.0, D))
                assert math.isfinite(x) and math.isfinite(y) and warning == ""  # the image's centre is calibrated
        with pytest.raises(ua.uaerrors.BadCertificateUntrusted):  # refused at CreateSession
            async with Session(opcua_cell, secure=(opcua_cell.stranger, ua.MessageSecurityMode.SignAndEncrypt)):
                pass
        # a user certificate the cell file lists may call; one it does not list leaves the session anonymous
        secure = (opcua_cell.client, ua.MessageSecurityMode.SignAndEncrypt)
        async with Session(opcua_cell, secure=secure, user_cert=opcua_cell.operator) as s:
            await s.call("Locate", ua.Variant("cam1", S), ua.Variant(1224.0, D), ua.Variant(1025.0, D))
        async with Session(opcua_cell, secure=secure, user_cert=opcua_cell.stranger) as s:
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await s.call("Locate", ua.Variant("cam1", S), ua.Variant(1224.0, D), ua.Variant(1025.0, D))
    run(go())


def test_bad_arguments_get_bad_statuses_and_the_server_stays_up(opcua_cell):
    token = opcua_cell.daemon.token
    before = len(jobs(opcua_cell))
    cases = [
        (("Jobs/Start", *start_args(routine="no-such-routine")), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", *start_args(params="{not json")), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", *start_args(params="[1, 2]")), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", *start_args(params='{"rows": "many"}')), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", *start_args(params='{"rows": NaN}')), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", *start_args(seed=-7)), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", *start_args(routine="x" * 200_000)), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", ua.Variant(5, I32), ua.Variant("{}", S), ua.Variant(3, I32)), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Start", ua.Variant("virtual-grid", S)), ua.uaerrors.BadArgumentsMissing),
        (("Jobs/Pause", ua.Variant(999_999, U32), ua.Variant(False, B)), ua.uaerrors.BadNotFound),
        (("Jobs/Abort", ua.Variant(-1, I32)), ua.uaerrors.BadInvalidArgument),
        (("Jobs/Resume", ua.Variant(999_999, U32)), ua.uaerrors.BadNotFound),
        (("Locate", ua.Variant("cam9", S), ua.Variant(1.0, D), ua.Variant(1.0, D)), ua.uaerrors.BadNotFound),
        (("Locate", ua.Variant("cam1", S), ua.Variant(99999.0, D), ua.Variant(-5.0, D)),
         ua.uaerrors.BadInvalidArgument),  # off the image
        (("Locate", ua.Variant("cam1", S), ua.Variant(math.nan, D), ua.Variant(1.0, D)), ua.uaerrors.BadInvalidArgument),
        (("Lock/Acquire", ua.Variant("x", S), ua.Variant(-5.0, D)), ua.uaerrors.BadInvalidArgument),
    ]

    async def go():
        async with Session(opcua_cell, "fuzz", token) as s:
            for (path, *args), expected in cases:
                with pytest.raises(expected):
                    await s.call(path, *args)
            assert await s.read("Identification/Name") == "sim-microcell"  # still up, same session
    run(go())
    assert len(jobs(opcua_cell)) == before


def test_the_service_caps_the_lock_and_every_refusal_is_audited(opcua_cell):
    """The lock's TTL has the HTTP API's cap (the service's), and a call refused before it reached the service (its
    Parameters not JSON) is in the audit log as the service's own refusals are."""
    token = opcua_cell.daemon.token

    async def go():
        async with Session(opcua_cell, "audited", token) as s:
            with pytest.raises(ua.uaerrors.BadInvalidArgument):
                await s.call("Lock/Acquire", ua.Variant("MES", S), ua.Variant(86401.0, D))
            with pytest.raises(ua.uaerrors.BadInvalidArgument):
                await s.call("Jobs/Start", *start_args(params="{never json"))
    run(go())
    with opcua_cell.daemon.client() as http:
        audit = [a for a in http.get("/audit", params={"limit": 10000}).json()["audit"]
                 if a["client"] == "audited@opcua"]
    assert [(a["action"], a["outcome"][:11]) for a in audit] == [("OPC UA Lock/Acquire", "refused 422"),
                                                                 ("OPC UA Start", "refused 422")], audit
    assert "ttl_s: 86401.0; allowed: seconds > 0, at most 86400" in audit[0]["outcome"]
    assert "Parameters: not JSON" in audit[1]["outcome"]
