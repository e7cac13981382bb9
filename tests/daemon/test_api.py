"""The API's guard rails on the real daemon: token (401/403), operator lock (423), malformed input (4xx,
never 5xx), all refused requests changing nothing; the schema; calibrations export; the CLI client."""

from __future__ import annotations

import os
import stat

import httpx
import pytest

from tests.support.daemon import SMALL, running_daemon, wait_for
from tests.support.wait import eventually

BREAK_AFTER_IDLE_S = 3.0  # this cell's operator_lock.break_after_idle_s (the default is a minute)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    with running_daemon(tmp_path_factory.mktemp("api"), realtime_factor=0.0,
                        lock_break_after_idle_s=BREAK_AFTER_IDLE_S) as d:
        yield d


def state_of(daemon) -> tuple:
    """Everything a refused request must leave as it was."""
    with daemon.client(token=None) as c:
        return (c.get("/jobs").json(), c.get("/calibrations").json(), c.get("/lock").json())


COMMANDS = [("POST", "/jobs", {"routine": "virtual-grid", "params": SMALL}), ("POST", "/jobs/1/pause", {}),
            ("POST", "/jobs/1/resume", None), ("POST", "/jobs/1/ack", None), ("POST", "/jobs/1/abort", None),
            ("POST", "/calibrations/1/activate", None), ("POST", "/calibrations/1/deactivate", None),
            ("POST", "/cell/reconnect", {}),
            ("POST", "/lock", {"holder": "x"}), ("DELETE", "/lock", None)]


def test_token_is_private_and_required(daemon):
    mode = stat.S_IMODE(os.stat(daemon.store / "daemon.token").st_mode)
    assert mode == 0o600
    before = state_of(daemon)
    for token, status in ((None, 401), ("wrong", 403)):
        with daemon.client(token=token) as c:
            for method, path, body in COMMANDS:
                r = c.request(method, path, json=body)
                assert r.status_code == status, (method, path, r.text)
    assert state_of(daemon) == before
    with daemon.client(token=None) as c:  # reading needs no token
        assert c.get("/cell").status_code == 200
        audit = c.get("/audit").json()["audit"]
    assert sum(a["outcome"] == "refused 401" for a in audit) >= len(COMMANDS)
    assert all(a["client"] for a in audit)


def test_the_operator_lock_lets_one_client_command(daemon):
    alice = daemon.client(**{"X-Cellctl-Client": "alice"})
    bob = daemon.client(**{"X-Cellctl-Client": "bob"})
    with alice, bob:
        got = alice.post("/lock", json={"holder": "alice", "ttl_s": 30}).json()
        lock = got["lock_id"]
        assert bob.get("/lock").json()["holder"] == "alice"
        before = state_of(daemon)
        for method, path, body in COMMANDS:
            r = bob.request(method, path, json=body)
            assert r.status_code == 423, (method, path, r.text)
            assert "alice" in r.json()["detail"]
        assert state_of(daemon)[:2] == before[:2]
        assert bob.get("/jobs").status_code == 200  # others can read
        # the holder commands with its lock id
        r = alice.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": 3},
                       headers={"X-Cellctl-Lock": lock})
        assert r.status_code == 201
        job = r.json()["id"]
        assert alice.post(f"/jobs/{job}/abort", headers={"X-Cellctl-Lock": lock}).status_code == 200
        wait_for(alice, job, {"aborted"})
        assert alice.delete("/lock", headers={"X-Cellctl-Lock": lock}).json() == {"held": False}
        # a short lock lapses by itself
        alice.post("/lock", json={"holder": "alice", "ttl_s": 0.3})
        assert bob.post("/jobs/999/abort").status_code == 423
        import time

        time.sleep(0.4)
        assert bob.post("/jobs/999/abort").status_code == 404  # now bob may command (no such job)
        audit = bob.get("/audit").json()["audit"]
        assert any(a["client"].startswith("bob@") and a["outcome"].startswith("refused 423: ") for a in audit)
        assert any(a["client"].startswith("alice@") and a["action"] == "POST /jobs" and a["outcome"] == "ok"
                   for a in audit)



def lock_events(client: httpx.Client, until) -> list[dict]:
    """The `lock` events of the daemon's stream (replayed from its start), read until `until(event)` holds."""
    import json

    seen, kind = [], ""
    with client.stream("GET", "/events", params={"since": 0}, timeout=httpx.Timeout(10.0)) as r:
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind == "lock":
                seen.append(json.loads(line[6:]))
                if until(seen[-1]):
                    return seen
    raise AssertionError(f"the stream ended before the awaited lock event: {seen}")


def wait_idle(client, seconds: float, timeout: float = 30.0) -> None:
    """Until the lock's holder has not used it for `seconds` (what a break waits for; half a second more, as
    idle_s is rounded to 0.1 s)."""
    def stale() -> bool:
        now = client.get("/lock").json()
        assert now["held"], now
        return now.get("idle_s", 0.0) >= seconds + 0.5

    eventually(stale, timeout=timeout, every=0.1, what=f"the lock idle for {seconds} s")


def test_a_stale_lock_is_broken_with_a_reason_audited_and_its_holder_told(daemon, capsys, monkeypatch):
    from cellctl import cli

    alice = daemon.client(**{"X-Cellctl-Client": "alice"})
    bob = daemon.client(**{"X-Cellctl-Client": "bob"})
    with alice, bob:
        lock = alice.post("/lock", json={"holder": "alice-console", "ttl_s": 600}).json()["lock_id"]
        r = bob.delete("/lock")  # what the issue saw: the token is not enough to release another's lock
        assert r.status_code == 423 and "only its holder can release it" in r.json()["detail"]
        assert "lock break --reason" in r.json()["detail"]
        # a reason is required: one line naming it, the lock untouched
        for body in (None, {}, {"reason": "   "}):
            r = bob.post("/lock/break", json=body)
            assert r.status_code == 422 and r.json()["detail"].startswith("reason: required"), (body, r.text)
        assert bob.post("/lock/break", json={"reason": "x" * 501}).status_code == 422
        assert bob.get("/lock").json()["holder"] == "alice-console"
        # a lock in use is not broken: alice has just renewed it
        alice.post("/lock", json={"holder": "alice-console", "ttl_s": 600}, headers={"X-Cellctl-Lock": lock})
        r = bob.post("/lock/break", json={"reason": "tab left open on line 3"})
        assert r.status_code == 409 and "is in use" in r.json()["detail"], r.text
        assert bob.get("/lock").json()["holder"] == "alice-console"

        wait_idle(bob, BREAK_AFTER_IDLE_S)  # stale now: neither renewed nor used since
        r = bob.post("/lock/break", json={"reason": "tab left open on line 3"})
        assert r.status_code == 200, r.text
        assert r.json()["broken"] | {"at": 0} == {"holder": "alice-console", "by": r.json()["broken"]["by"],
                                                  "reason": "tab left open on line 3", "at": 0}
        assert r.json()["broken"]["by"].startswith("bob@") and r.json()["lock"] == {"held": False}
        assert bob.get("/lock").json() == {"held": False}
        # the holder is told on the event stream (no lock id in it: the stream is open to all)...
        event = lock_events(bob, lambda e: e["state"] == "broken")[-1]
        assert (event["holder"], event["reason"]) == ("alice-console", "tab left open on line 3")
        assert event["by"].startswith("bob@") and lock not in str(event)
        # ... and by its next command, and its renewal, which take nothing back
        for method, path, body in (("POST", "/jobs/424242/abort", None), ("POST", "/lock", {"holder": "alice-console"})):
            r = alice.request(method, path, json=body, headers={"X-Cellctl-Lock": lock})
            assert r.status_code == 423, r.text
            detail = r.json()["detail"]
            assert "was broken by bob@" in detail and "tab left open on line 3" in detail, detail
            assert r.json()["broken"]["reason"] == "tab left open on line 3"
        assert bob.get("/lock").json() == {"held": False}
        assert bob.post("/jobs/424242/abort").status_code == 404  # free: anyone may command (no such job)
        assert bob.post("/lock/break", json={"reason": "again"}).status_code == 409  # nobody holds it
        audit = bob.get("/audit").json()["audit"]
    broke = [a for a in audit if a["action"] == "POST /lock/break" and a["outcome"] == "ok"]
    assert len(broke) == 1 and broke[0]["client"].startswith("bob@")
    assert broke[0]["target"] == "lock of alice-console" and broke[0]["detail"] == "tab left open on line 3"
    assert sum(a["action"] == "POST /lock/break" and a["outcome"].startswith("refused 422") for a in audit) >= 4

    # the CLI: `cellctl lock break` needs a reason too, and says what it did
    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    with daemon.client() as c:
        c.post("/lock", json={"holder": "forgotten", "ttl_s": 600})
        wait_idle(c, BREAK_AFTER_IDLE_S)
    assert cli.main(["lock", "break"]) == 2
    assert "reason: required" in capsys.readouterr().err
    assert cli.main(["lock", "break", "--reason", "shift change"]) == 0
    assert "lock of forgotten broken (shift change)" in capsys.readouterr().out
    assert cli.main(["lock"]) == 0 and capsys.readouterr().out.strip() == "free"


def test_a_token_without_bearer_is_told_the_form_expected(daemon):
    before = state_of(daemon)
    for value, why in ((daemon.token, "no Bearer scheme"), (f"Basic {daemon.token}", "no Bearer scheme"),
                       ("Bearer", "no token after Bearer")):
        with daemon.client(token=None) as c:
            r = c.post("/jobs/1/abort", headers={"Authorization": value})
            assert r.status_code == 401, (value, r.text)
            assert r.json()["detail"].startswith("Authorization: Bearer TOKEN expected"), r.text
            assert why in r.json()["detail"], (value, r.text)
            assert daemon.token not in r.text and r.headers["www-authenticate"] == "Bearer"
    with daemon.client(token="wrong") as c:
        r = c.post("/jobs/1/abort")
        assert r.status_code == 403 and r.json()["detail"] == "wrong token"
    assert state_of(daemon) == before

BAD = [
    ("POST", "/jobs", b"{not json", 422),
    ("POST", "/jobs", [], 422),
    ("POST", "/jobs", {}, 422),
    ("POST", "/jobs", {"routine": "no-such-routine"}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "params": {"rows": "many"}}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "params": {"rowz": 4}}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "params": [1, 2]}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "seed": -1}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "seed": 2**70}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "colour": "red"}, 422),
    ("POST", "/jobs", {"routine": "calibrate-cell", "params": {"rows": 3}}, 422),
    ("POST", "/jobs", {"routine": "x" * 10000}, 422),
    ("POST", "/jobs", b'{"routine": "hybrid", "params": {"supply_z_mm": NaN}}', 422),  # was 201
    ("POST", "/jobs", b'{"routine": "hybrid", "params": {"supply_z_mm": Infinity}}', 422),
    ("POST", "/jobs", b'{"routine": "hybrid", "params": {"supply_z_mm": 1e999}}', 422),
    ("POST", "/jobs", b'{"routine": "hybrid", "params": {"supply_mm": [40, NaN]}}', 422),
    ("POST", "/jobs", b'{"routine": "virtual-grid", "params": {"margin_mm": NaN}}', 422),
    ("POST", "/jobs", b'{"routine": "virtual-grid", "seed": NaN}', 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "save_images": "yes"}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "save_images": 1}, 422),
    ("POST", "/jobs", {"routine": "virtual-grid", "save_images": "true"}, 422),
    ("POST", "/jobs/abc/pause", {}, 422),
    ("POST", "/jobs/0/pause", {}, 422),
    ("POST", "/jobs/99999999999999999999999/pause", {}, 422),
    ("POST", "/jobs/1/pause", {"mode": "sideways"}, 422),
    ("POST", "/jobs/1/pause", {"mode": "deferred", "extra": 1}, 422),
    ("POST", "/jobs/424242/resume", None, 404),
    ("POST", "/calibrations/-3/activate", None, 422),
    ("POST", "/calibrations/77/activate", None, 404),
    ("POST", "/calibrations/77/deactivate", None, 404),
    ("POST", "/cell/reconnect", {"device": "toaster"}, 422),
    ("POST", "/lock", {"holder": "", "ttl_s": 5}, 422),
    ("POST", "/lock", {"holder": "me", "ttl_s": -5}, 422),
    ("POST", "/lock", {"holder": "me", "ttl_s": "long"}, 422),
    ("GET", "/jobs?state=sleeping", None, 422),
    ("GET", "/jobs?limit=-1", None, 422),
    ("GET", "/jobs/1.5", None, 422),
    ("GET", "/jobs/424242", None, 404),
    ("GET", "/jobs/424242/result", None, 404),
    ("GET", "/calibrations/1/export?format=xml", None, 422),
    ("GET", "/cameras/cam9/frame.png", None, 404),
    ("GET", "/events?job=-1", None, 422),
    ("GET", "/audit?limit=abc", None, 422),
]


@pytest.mark.parametrize("method, path, body, status", BAD, ids=[f"{m} {p[:40]} {str(b)[:30]}" for m, p, b, _ in BAD])
def test_malformed_requests_get_a_4xx_naming_the_field_and_change_nothing(daemon, method, path, body, status):
    before = state_of(daemon)
    with daemon.client() as c:
        if isinstance(body, bytes):
            r = c.request(method, path, content=body, headers={"Content-Type": "application/json"})
        else:
            r = c.request(method, path, json=body)
    assert r.status_code == status, r.text
    assert r.json()["detail"]
    assert state_of(daemon) == before  # a refused GET changes nothing either


def test_malformed_headers_get_a_4xx_and_change_nothing(daemon):
    """Header bytes as they come over the socket (Latin-1): b"\xb2" is "²", which str.isdigit() calls a digit
    and int() refuses; non-ASCII lock ids and tokens, which hmac.compare_digest refuses as str."""
    before = state_of(daemon)
    with daemon.client() as c:
        for value in (b"\xb2", b"\xb9\xb2", "١".encode(), b"12a", b"-1", b"1" * 40):
            with c.stream("GET", "/events", headers={"Last-Event-ID": value}) as r:
                assert r.status_code == 422, (value, r.status_code)
                assert "last-event-id" in r.read().decode().lower()
        for value in (b"3", b""):
            with c.stream("GET", "/events", headers={"Last-Event-ID": value}) as r:
                assert r.status_code == 200
        weird = (b"\xe9", "é".encode(), b"\xb2" * 20, "ü".encode() * 64)
        # nobody holds the lock: any lock id is irrelevant (no such job -> 404)
        for value in weird:
            assert c.post("/jobs/424242/abort", headers={"X-Cellctl-Lock": value}).status_code == 404
    with daemon.client(**{"X-Cellctl-Client": "alice"}) as alice, daemon.client() as other:
        lock = alice.post("/lock", json={"holder": "alice", "ttl_s": 30}).json()["lock_id"]
        try:
            for value in weird:
                for method, path, body in (("POST", "/jobs/424242/abort", None), ("POST", "/lock", {"holder": "eve"}),
                                           ("DELETE", "/lock", None),
                                           ("POST", "/jobs", {"routine": "virtual-grid", "params": SMALL})):
                    r = other.request(method, path, json=body, headers={"X-Cellctl-Lock": value})
                    assert r.status_code in (422, 423), (method, path, value, r.text)
            assert other.get("/lock").json()["holder"] == "alice"
        finally:
            alice.delete("/lock", headers={"X-Cellctl-Lock": lock})
    for value in (b"Bearer \xe9", "Bearer é".encode(), b"Bearer " + "ü".encode() * 50, b"bearer \xb2"):
        with daemon.client(token=None) as c:
            assert c.post("/jobs/1/abort", headers={"Authorization": value}).status_code == 403
    with daemon.client(**{"X-Cellctl-Client": b"\xe9\xb2"}) as c:  # an odd client name is audited as invalid
        assert c.post("/jobs/424242/abort").status_code == 404
    assert state_of(daemon)[:2] == before[:2]
    assert daemon.proc.poll() is None and not [e for e in daemon.logs() if e.get("level") == "error"]


def test_named_fields_and_allowed_values(daemon):
    with daemon.client() as c:
        r = c.post("/jobs/1/pause", json={"mode": "sideways"})
        assert "body.mode" in r.json()["detail"] and "deferred" in r.json()["detail"]
        r = c.post("/jobs", json={"routine": "virtual-grid", "params": {"rowz": 4}})
        assert "rowz" in r.json()["detail"] and "allowed" in r.json()["detail"]
        r = c.post("/jobs", content=b'{"routine": "hybrid", "params": {"supply_z_mm": NaN}}',
                   headers={"Content-Type": "application/json"})
        assert "params.supply_z_mm" in r.json()["detail"] and "finite" in r.json()["detail"]


def test_schema_status_frames_and_calibration_exports(daemon):
    import cv2
    import numpy as np

    with daemon.client() as c:
        schema = c.get("/openapi.json").json()
        assert {"/jobs", "/jobs/{job_id}/pause", "/events", "/calibrations/{cal_id}/export"} <= set(schema["paths"])
        status = c.get("/cell").json()
        assert {d["name"]: d["state"] for d in status["devices"]}["cam1"] == "ready"
        png = c.get("/cameras/cam1/frame.png")
        assert png.headers["content-type"] == "image/png"
        image = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert image.shape[:2] == (2050, 2448)
        job = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": 4}).json()
        wait_for(c, job["id"], {"done"})
        cal = c.get(f"/jobs/{job['id']}").json()["result"]["calibration"]
        exported = c.get(f"/calibrations/{cal['id']}/export", params={"format": "json"}).json()
        assert exported["target"] == "cam1" and exported["model"]["map"]["a"]
        yaml_text = c.get(f"/calibrations/{cal['id']}/export", params={"format": "opencv"}).text
    path = daemon.store.parent / "cal.yaml"
    path.write_text(yaml_text)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("target").string() == "cam1"
    assert fs.getNode("model").getNode("map").getNode("a").real() == exported["model"]["map"]["a"]
    assert list(fs.getNode("model").getNode("map").getNode("image_size").mat().ravel()) == \
        exported["model"]["map"]["image_size"]
    fs.release()


def test_an_arm_calibration_exports_as_urdf_over_http_and_activates_only_on_its_cell(daemon, capsys, monkeypatch):
    """format=urdf over the API and the CLI client: the same document as the service's, refused (422) for another
    target naming the formats it allows; an arm calibration of another cell is refused at activate (409)."""
    import numpy as np
    import pinocchio as pin

    from geometry.kinematic_table import KinematicTable, nominal_table

    from cellctl import cli as client
    from cellctl.stores.calibrations import CalibrationStore

    table = nominal_table("ur5e")
    table = table.with_vector(table.vector() + np.random.default_rng(8).normal(0.0, 1e-3, table.vector().size))
    store = CalibrationStore(daemon.store)  # as arm-kinematics would store it (never active here: the cell is 4-axis)
    try:
        arm = store.save("arm", {"routine": "arm-kinematics", "cell": "a-ur5e-cell", "stats": {},
                                 "model": {"kind": "arm-kinematics", "arm_model": "ur5e", "table": table.to_dict(),
                                           "nominal": nominal_table("ur5e").to_dict(), "tool": None}},
                         "", activate=False)
        cam = store.save("cam1", {"routine": "virtual-grid", "cell": "sim-microcell", "model": {"kind": "planar"},
                                  "stats": {}}, "", activate=False)
    finally:
        store.close()
    table = KinematicTable.from_dict(arm.model["table"])
    with daemon.client() as c:
        r = c.get(f"/calibrations/{arm.id}/export", params={"format": "urdf"})
        assert r.status_code == 200 and r.headers["content-type"].startswith("application/xml")
        assert f'filename="calibration-{arm.id}.urdf"' in r.headers["content-disposition"]
        model = pin.buildModelFromXML(r.text)
        data = model.createData()
        for q in np.random.default_rng(9).uniform(-3.0, 3.0, (20, 6)):
            pin.framesForwardKinematics(model, data, q)
            assert np.abs(data.oMf[model.getFrameId("flange")].homogeneous - table.forward(q)).max() < 1e-9
        refused = c.get(f"/calibrations/{cam.id}/export", params={"format": "urdf"})
        assert refused.status_code == 422 and "allowed for it: json, opencv" in refused.json()["detail"]
        before = state_of(daemon)
        refused = c.post(f"/calibrations/{arm.id}/activate")
        assert refused.status_code == 409
        assert "arm of cell 'a-ur5e-cell', and this cell is 'sim-microcell'" in refused.json()["detail"]
        assert state_of(daemon) == before
        off = c.post(f"/calibrations/{arm.id}/deactivate")  # out of use: allowed on any cell
        assert off.status_code == 200 and off.json()["active"] is False
    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    assert client.main(["calibrations", "export", str(arm.id), "--format", "urdf"]) == 0
    assert capsys.readouterr().out == r.text


def test_the_schema_documents_every_answer_and_options_lists_the_methods(daemon):
    with daemon.client(token=None) as c:
        schema = c.get("/openapi.json").json()
        paths = schema["paths"]
        for path, operations in paths.items():
            for method, op in operations.items():
                command = method in ("post", "delete")
                assert (op.get("security") == [{"bearer": []}]) == command, (method, path)
                assert not command or {"401", "403", "423"} <= set(op["responses"]), (method, path)
                errors = {code: r for code, r in op["responses"].items() if code[0] == "4"}
                assert all(r["content"]["application/json"]["schema"] == {"$ref": "#/components/schemas/ErrorBody"}
                           for r in errors.values()), (method, path)
            url = path.format(job_id=1, cal_id=1, name="cam1", request_id=1, routine="hand-eye", motion_id=1)
            documented = {m.upper() for m in operations}
            r = c.options(url)
            assert r.status_code == 204 and set(r.headers["allow"].split(", ")) == documented, (path, r.headers)
            for method in {"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE"} - documented:  # before the token, too
                r = c.request(method, url)
                assert r.status_code == 405 and set(r.headers["allow"].split(", ")) == documented, (method, path)
    media = {path: set(ops["get"]["responses"]["200"]["content"]) for path, ops in paths.items() if "get" in ops}
    assert media["/jobs/{job_id}/report"] == {"text/markdown"} and media["/jobs/{job_id}/samples"] == {"text/csv"}
    assert media["/calibrations/{cal_id}/export"] == {"application/json", "application/x-yaml", "application/xml"}
    assert media["/jobs/{job_id}/plot"] == media["/cameras/{name}/frame.png"] == {"image/png"}
    assert media["/events"] == {"text/event-stream"}
    assert {"404"} <= set(paths["/jobs/{job_id}/result"]["get"]["responses"])
    assert {"404", "409"} <= set(paths["/jobs/{job_id}/abort"]["post"]["responses"])


def test_a_job_item_that_does_not_exist_gets_404(daemon):
    with daemon.client() as c:
        single = c.post("/jobs", json={"routine": "virtual-grid", "params": SMALL, "seed": 4}).json()["id"]
        sequence = c.post("/jobs", json={"routine": "calibrate-cell"}).json()["id"]
        for job in (single, sequence):
            c.post(f"/jobs/{job}/abort")
        # not an item of the sequence; an item of a job that is not a sequence; no such job
        for job, item in ((sequence, "nope"), (single, "virtual-grid"), (424242, None), (424242, "virtual-grid")):
            for what in ("result", "report", "plot", "samples"):
                r = c.get(f"/jobs/{job}/{what}", params={"item": item} if item else None)
                assert r.status_code == 404 and r.json()["detail"], (job, what, item, r.text)


def test_a_malformed_command_gets_422_even_while_another_client_holds_the_lock(daemon):
    with daemon.client(**{"X-Cellctl-Client": "alice"}) as alice, daemon.client() as other:
        lock = alice.post("/lock", json={"holder": "alice", "ttl_s": 30}).json()["lock_id"]
        try:
            for method, path, body in (("POST", "/jobs/abc/pause", {}), ("POST", "/jobs", {"routine": "virtual-grid",
                                                                                          "seed": False}),
                                       ("POST", "/operator/requests/0/decline", None),
                                       ("POST", "/operator/requests/1/clicks", {"clicks": [{"model_index": True}]})):
                r = other.request(method, path, json=body)
                assert r.status_code == 422, (method, path, r.text)
            assert other.post("/jobs/1/abort").status_code == 423  # well formed: the lock decides
        finally:
            alice.delete("/lock", headers={"X-Cellctl-Lock": lock})


def test_cli_client_verbs(daemon, capsys, monkeypatch):
    from cellctl import cli as client

    monkeypatch.setenv("CELLCTL_URL", daemon.url)
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    assert client.main(["status"]) == 0
    assert "cam1" in capsys.readouterr().out
    assert client.main(["run", "virtual-grid", "--seed", "5", "--wait", "--quiet"]
                       + [f"--param={k}={v}" for k, v in SMALL.items()]) == 0
    out = capsys.readouterr().out
    assert "done" in out and "radial error" in out.lower()
    assert client.main(["jobs"]) == 0
    assert "virtual-grid" in capsys.readouterr().out
    assert client.main(["pause", "424242"]) == 2
    assert "no job 424242" in capsys.readouterr().err
    assert client.main(["run", "virtual-grid", "--param", "rowz=3"]) == 2
    assert "rowz" in capsys.readouterr().err
    assert client.main(["calibrations"]) == 0
    assert "cam1" in capsys.readouterr().out
    monkeypatch.setenv("CELLCTL_TOKEN", "wrong")
    assert client.main(["abort", "1"]) == 2
    assert "403" in capsys.readouterr().err
    monkeypatch.delenv("CELLCTL_URL")
    assert client.main(["status", "--url", daemon.url]) == 0
    with httpx.Client() as h:
        h.get(daemon.url + "/health").raise_for_status()


TINY = {"rows": 3, "cols": 3, "n_verify": 0, "passes": 1}


def test_save_images_keeps_every_frame_of_the_job(daemon, capsys, monkeypatch):
    """`cellctl run --save-images` through the daemon: one PNG per frame the samples came from, in the run
    folder's images/; without it, none."""
    import re

    from cellctl import cli
    from cellctl.stores.run_folder import RunFolder

    assert cli.build_parser().parse_args(["run", "virtual-grid", "--save-images"]).save_images
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    assert cli.main(["run", "virtual-grid", "--url", daemon.url, "--seed", "5", "--save-images", "--wait", "--quiet"]
                    + [f"--param={k}={v}" for k, v in TINY.items()]) == 0
    saving = int(re.search(r"job (\d+) queued", capsys.readouterr().out).group(1))
    with daemon.client() as c:
        plain = c.post("/jobs", json={"routine": "virtual-grid", "params": TINY, "seed": 5}).json()
        assert plain["save_images"] is False
        wait_for(c, plain["id"], {"done"})
        jobs = {j: c.get(f"/jobs/{j}").json() for j in (saving, plain["id"])}
    assert jobs[saving]["state"] == "done" and jobs[saving]["save_images"] is True
    folder = RunFolder(jobs[saving]["run_dir"])
    rows = folder.samples()
    frames = {(r["camera"], r["frame_id"]) for r in rows}
    pngs = sorted(p.name for p in folder.images_path.glob("*.png"))
    assert len(frames) == len(pngs) == 9
    assert sorted({name for r in rows for name in r["image"].split(";")}) == [f"images/{n}" for n in pngs]
    plain_folder = RunFolder(jobs[plain["id"]]["run_dir"])
    assert len(plain_folder.samples()) == len(rows)
    assert not list(plain_folder.images_path.glob("*.png"))


def test_a_jobs_database_from_before_save_images_opens_and_gains_the_column(tmp_path):
    import sqlite3

    from cellctl.stores.jobs import JobStore

    path = tmp_path / "jobs.sqlite"
    db = sqlite3.connect(path)
    db.executescript("""
        CREATE TABLE jobs (id INTEGER PRIMARY KEY AUTOINCREMENT, routine TEXT NOT NULL, params TEXT NOT NULL,
            seed INTEGER, state TEXT NOT NULL, reason TEXT NOT NULL DEFAULT '',
            acknowledged INTEGER NOT NULL DEFAULT 1, created TEXT NOT NULL, updated TEXT NOT NULL,
            submitted_by TEXT NOT NULL, run_dir TEXT NOT NULL, progress TEXT, result TEXT);
        INSERT INTO jobs (routine, params, seed, state, created, updated, submitted_by, run_dir)
            VALUES ('virtual-grid', '{"rows": 3}', 5, 'paused', 't0', 't0', 'old@test', 'jobs/000001');
    """)
    db.commit()
    db.close()
    store = JobStore(path)
    old = store.get(1)
    assert (old.routine, old.params, old.state, old.save_images) == ("virtual-grid", {"rows": 3}, "paused", False)
    assert old.to_dict()["save_images"] is False
    new = store.submit("virtual-grid", {}, 5, "new@test", save_images=True)
    store.close()
    store = JobStore(path)  # the column is there now: opening again changes nothing; the flag is kept
    assert store.get(new.id).save_images is True and store.get(1).save_images is False
    store.close()
    columns = [row[1] for row in sqlite3.connect(path).execute("PRAGMA table_info(jobs)")]
    assert columns.count("save_images") == 1


def test_every_registered_routine_is_offered_and_reported_with_no_code_of_its_own(daemon, capsys, monkeypatch):
    """GET /routines offers every routine of the table with its parameters; a routine's own tables reach the
    result, report.md, the plot and the CLI's results through the generic rendering (shown with repeatability,
    which was added as one file, its truth function and one registration)."""
    from calibration.routines import routine_class, routine_names

    from cellctl import cli

    with daemon.client() as c:
        offered = c.get("/routines").json()["routines"]
        assert set(offered) == set(routine_names())
        assert all(offered[n]["params"]["properties"] for n in routine_names())
        cam1 = c.post("/jobs", json={"routine": "virtual-grid", "params": TINY, "seed": 5}).json()
        assert wait_for(c, cam1["id"], {"done", "faulted"})["state"] == "done"
        job = c.post("/jobs", json={"routine": "repeatability", "seed": 5,
                                    "params": routine_class("repeatability").small_params}).json()
        assert wait_for(c, job["id"], {"done", "faulted"})["state"] == "done"
        result = c.get(f"/jobs/{job['id']}/result").json()
        report = c.get(f"/jobs/{job['id']}/report").text
        plot = c.get(f"/jobs/{job['id']}/plot")
    assert result["tables"] and all(f"## {t['title']}" in report for t in result["tables"])
    assert result["stats"]["repeatability"]["rp_max_um"] > 0
    assert plot.status_code == 200 and plot.content[:8] == b"\x89PNG\r\n\x1a\n"
    monkeypatch.setenv("CELLCTL_TOKEN", daemon.token)
    assert cli.main(["results", str(job["id"]), "--url", daemon.url]) == 0
    assert result["tables"][0]["title"].split()[0] in capsys.readouterr().out
