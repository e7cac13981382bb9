"""The event stream (cellctl.fleet.mqtt) against a real Mosquitto: the sink fed with hand-made outbox records
(and once by the replicator), read back by plant-side subscribers (their own paho clients): topics and payloads,
the retained status and its Last Will, retained health, a persistent subscriber across a broker restart, an
outage and a lost PUBACK (SinkDown, then the batch again), refusals (password, ACL), and TLS."""

from __future__ import annotations

import json
import logging
import os
import queue
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable

import paho.mqtt.client as paho
import pytest

from cellctl.config import FleetMqtt, MqttTls
from cellctl.fleet import mqtt
from cellctl.fleet.mqtt import MqttSink, iso
from cellctl.fleet.replicator import Replicator, SinkDown
from cellctl.stores.outbox import Outbox, Record, create, enqueue

from tests.support.servers import MosquittoServer, free_port

PREFIX = "acme/plant1/line3"
INFO = {"description": "glue cell, line 3", "software_revision": "0.4.1", "api_url": "https://cell.plant:8443"}
AT = 1772439300.25  # when the test's records were made


def settings(broker: MosquittoServer, **kw) -> FleetMqtt:
    return FleetMqtt(host="127.0.0.1", port=broker.port, topic_prefix=PREFIX, username=broker.username, **kw)


def make_sink(broker: MosquittoServer, cell: str, password: str | None = None, **kw) -> MqttSink:
    return MqttSink(settings(broker, **kw), cell, password=password or broker.password, info=INFO)


def record(seq: int, kind: str, key: str, body: dict) -> Record:
    return Record(seq, kind, key, body, AT + seq, "jobs")


def job_state(event: int, job: int = 42, to: str = "running") -> Record:
    return record(event, "job_state", f"job_state/{event}",
                  {"id": event, "job": job, "routine": "vr.fine", "at": iso(AT + event), "from": "queued", "to": to,
                   "reason": None, "who": "operator:anna"})


@dataclass
class Message:
    topic: str
    payload: dict
    retain: bool


class Listener:
    """A plant-side subscriber (MQTT 3.1.1, QoS 1): every message it gets, in order. `persistent`: a session the
    broker keeps while it is away (clean_session false) under `client_id`."""

    def __init__(self, broker: MosquittoServer, topics: list[str], client_id: str = "", persistent: bool = False):
        self.messages: queue.Queue[Message] = queue.Queue()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=client_id,
                                  clean_session=not persistent, protocol=paho.MQTTv311)
        self.client.username_pw_set(broker.username, broker.password)
        connected, subscribed = threading.Event(), threading.Event()
        self.client.on_connect = lambda *args: connected.set()
        self.client.on_subscribe = lambda *args: subscribed.set()
        self.client.on_message = lambda c, u, m: self.messages.put(Message(m.topic, json.loads(m.payload), m.retain))
        self.client.connect("127.0.0.1", broker.port, keepalive=30)
        self.client.loop_start()
        assert connected.wait(5), "the listener could not connect"
        self.client.subscribe([(t, 1) for t in topics])
        assert subscribed.wait(5), "the listener could not subscribe"

    def until(self, done: Callable[[list[Message]], bool], timeout: float = 5.0) -> list[Message]:
        """Messages until `done(messages so far)`; fails after `timeout` s with what came."""
        got: list[Message] = []
        deadline = time.monotonic() + timeout
        while not done(got):
            try:
                got.append(self.messages.get(timeout=max(deadline - time.monotonic(), 0)))
            except queue.Empty:
                raise AssertionError(f"waited {timeout} s; got {[(m.topic, m.payload) for m in got]}") from None
        return got

    def take(self, n: int, timeout: float = 5.0) -> list[Message]:
        return self.until(lambda got: len(got) >= n, timeout)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def topics_of(messages: list[Message], cell: str) -> list[str]:
    return [m.topic.removeprefix(f"{PREFIX}/{cell}/") for m in messages]


def in_order_once(messages: list[Message]) -> list[int]:
    """What a subscriber that checks order keeps of the job events: each id once, newer than the last kept."""
    kept: list[int] = []
    for m in messages:
        assert m.payload["key"] == f"job_state/{m.payload['id']}"
        if not kept or m.payload["id"] > kept[-1]:
            kept.append(m.payload["id"])
    return kept


# -- topics and payloads ------------------------------------------------------------------

BIG_RESULT = {"routine": "vr.fine", "model": {"tool_mm": [0.12, -0.03, 41.7]},
              "residuals_um": [round(i * 0.37 % 50, 2) for i in range(20_000)], "verdict": "ok"}
HEALTH_TARGETS = {
    "cam1": {"calibration_id": 12, "drifted": True, "p_value": 0.003, "drift": {"shift_um": 85.0},
             "action": "touch-up: run check with update=true"},
    "nozzle": {"calibration_id": 14, "drifted": False, "p_value": 0.61, "drift": {"shift_um": 4.0}, "action": "ok"},
}
ONE_OF_EACH = [
    record(1, "job", "job/42", {"id": 42, "routine": "vr.fine", "params": {}, "seed": 1, "state": "running",
                                "reason": None, "submitted_by": "anna", "created": iso(AT), "updated": iso(AT),
                                "event": 7}),
    job_state(7),
    record(3, "samples", "samples/42//0", {"job": 42, "item": "", "step": 0, "rows": [{"x_mm": 1.5}]}),
    record(4, "progress", "progress/42//0", {"job": 42, "routine": "vr.fine", "item": None, "step": 1, "total": 64,
                                             "cell_time_s": 3.2, "eta_cell_s": 201.6, "residual_um": None}),
    record(5, "result", "result/42/", {"job": 42, "item": "", "routine": "vr.fine", "result": BIG_RESULT}),
    record(6, "calibration", "calibration/5", {"id": 5, "target": "cam1", "routine": "vr.fine", "version": 3,
                                               "created": iso(AT), "active": True, "cell_file": "", "result": {},
                                               "samples": None}),
    record(7, "activation", "activation/5", {"id": 5, "target": "cam1"}),
    record(8, "health_check", "health_check/3", {"id": 3, "created": "2026-03-02T07:00:12+0100", "verdict": "drift",
                                                 "targets": HEALTH_TARGETS}),
    record(9, "audit", "audit/77", {"id": 77, "at": iso(AT), "who": "anna", "client": "cli", "action": "submit",
                                    "target": "job", "detail": "", "outcome": "ok"}),
    record(10, "cell", "cell", {"state": "running", "live_job": 42}),
]


def test_each_record_kind_is_published_on_its_topic_with_its_payload(mosquitto):
    cell = "cell-topics"
    listener = Listener(mosquitto, [f"{PREFIX}/{cell}/#"])
    sink = make_sink(mosquitto, cell)
    sink.connect()
    try:
        sink.deliver(ONE_OF_EACH)
        got = listener.take(7)
    finally:
        sink.close(graceful=True)
        listener.close()

    # in the outbox's order; job, samples, calibration, activation and audit are the plant database's alone
    assert topics_of(got, cell) == ["status", "events/job", "events/progress", "results/vr.fine", "health/cam1",
                                    "health/nozzle", "status"]
    assert [m.retain for m in got] == [False] * 7  # live to a subscriber that was there already
    connected, event, progress, result, cam1, nozzle, status = (m.payload for m in got)
    assert connected["state"] == "online" and connected["live_job"] is None  # no `cell` record yet
    assert event == {"cell": cell, "key": "job_state/7", **ONE_OF_EACH[1].body}  # its own "at"
    assert progress == {"cell": cell, "key": "progress/42//0", "at": iso(AT + 4), **ONE_OF_EACH[3].body}
    assert result == {"cell": cell, "key": "result/42/", "at": iso(AT + 5), "job": 42, "item": "",
                      "routine": "vr.fine", "result": BIG_RESULT}  # the result as is, 300 kB of it
    assert cam1 == {"cell": cell, "key": "health_check/3", "at": iso(AT + 8), "id": 3,
                    "created": "2026-03-02T07:00:12+0100", "verdict": "drift", "target": "cam1",
                    **HEALTH_TARGETS["cam1"]}
    assert nozzle["target"] == "nozzle" and nozzle["action"] == "ok" and nozzle["key"] == "health_check/3"
    assert status == {"cell": cell, "key": "cell", "at": iso(AT + 10), "state": "online", "live_job": 42,
                      "cell_state": "running", **INFO}

    # health is retained per target: a dashboard that comes later gets each target's latest check
    late = Listener(mosquitto, [f"{PREFIX}/{cell}/health/+"])
    try:
        retained = late.take(2)
    finally:
        late.close()
    assert sorted((m.topic, m.retain, m.payload["drifted"]) for m in retained) == [
        (f"{PREFIX}/{cell}/health/cam1", True, True), (f"{PREFIX}/{cell}/health/nozzle", True, False)]


def test_a_name_that_is_no_topic_level_does_not_block_the_outbox(mosquitto):
    cell = "cell-names"
    listener = Listener(mosquitto, [f"{PREFIX}/{cell}/health/+"])
    sink = make_sink(mosquitto, cell)
    sink.connect()
    try:
        sink.deliver([record(1, "health_check", "health_check/1", {
            "id": 1, "created": "", "verdict": "ok", "targets": {"cam/+#": HEALTH_TARGETS["nozzle"]}})])
        [got] = listener.take(1)
    finally:
        sink.close(graceful=True)
        listener.close()
    assert got.topic == f"{PREFIX}/{cell}/health/cam___" and got.payload["target"] == "cam/+#"


def test_status_is_retained_online_then_offline_after_a_graceful_close(mosquitto):
    cell = "cell-status"
    topic = f"{PREFIX}/{cell}/status"
    sink = make_sink(mosquitto, cell)
    sink.connect()
    watcher = Listener(mosquitto, [topic])  # after the connect: what it gets is the retained status
    try:
        [online] = watcher.take(1)
        assert online.retain and online.payload["state"] == "online" and online.payload["cell"] == cell
        assert {k: online.payload[k] for k in INFO} == INFO and "at" in online.payload

        sink.deliver([record(1, "cell", "cell", {"state": "paused", "live_job": 9})])
        [changed] = watcher.take(1)
        assert (changed.payload["state"], changed.payload["live_job"], changed.payload["cell_state"]) == (
            "online", 9, "paused")

        sink.close(graceful=True)
        [offline] = watcher.take(1)
        assert offline.payload["state"] == "offline" and offline.payload["reason"] == "cell stopped"
        assert (offline.payload["live_job"], offline.payload["cell_state"]) == (9, "paused")  # as it stopped
    finally:
        sink.close(graceful=True)
        watcher.close()

    late = Listener(mosquitto, [topic])
    try:
        [kept] = late.take(1)
    finally:
        late.close()
    assert kept.retain and kept.payload["state"] == "offline" and kept.payload["reason"] == "cell stopped"


def test_the_replicator_carries_an_outbox_to_the_stream_and_the_cell_says_offline_when_it_stops(mosquitto,
                                                                                                tmp_path):
    cell = "cell-replicated"
    listener = Listener(mosquitto, [f"{PREFIX}/{cell}/#"])
    db = sqlite3.connect(tmp_path / "jobs.db")
    create(db)
    for r in (job_state(1), ONE_OF_EACH[2], job_state(2, to="done"), ONE_OF_EACH[-1]):
        enqueue(db, r.kind, r.key, r.body)
    db.commit()
    outbox = Outbox(tmp_path / "jobs.db", "jobs")
    replicator = Replicator([outbox], [make_sink(mosquitto, cell)], poll_s=0.05)
    replicator.start()
    try:
        got = listener.until(lambda got: len(got) == 4)
    finally:
        replicator.stop()
        outbox.close()
        db.close()
    got += listener.take(1)
    listener.close()
    assert replicator.delivered == {"mqtt": 4}  # the samples record too: skipped, and passed
    assert [(t, m.payload.get("id"), m.payload["state"] if t == "status" else None)
            for t, m in zip(topics_of(got, cell), got)] == [
        ("status", None, "online"), ("events/job", 1, None), ("events/job", 2, None), ("status", None, "online"),
        ("status", None, "offline")]


# -- the Last Will ------------------------------------------------------------------------

CHILD = """
import json, os, sys, time
from cellctl.config import FleetMqtt
from cellctl.fleet.mqtt import MqttSink
sink = MqttSink(FleetMqtt(**json.loads(sys.argv[1])), sys.argv[2], password=os.environ["MQTT_PASSWORD"])
sink.connect()
time.sleep(120)
"""


def test_the_last_will_says_offline_when_the_cell_dies_or_falls_silent(mosquitto):
    """Two cells in processes of their own: one killed (SIGKILL: its kernel closes the socket, no DISCONNECT),
    one frozen (SIGSTOP: the socket stays open and silent, as behind a pulled cable): the broker publishes each
    one's will, the frozen one's once it has been silent for 1.5 keep-alives."""
    keepalive_s = 5
    killed, frozen = "cell-killed", "cell-frozen"
    watcher = Listener(mosquitto, [f"{PREFIX}/{cell}/status" for cell in (killed, frozen)])
    options = settings(mosquitto, keepalive_s=keepalive_s).model_dump_json()
    env = {**os.environ, "MQTT_PASSWORD": mosquitto.password}
    children = {cell: subprocess.Popen([sys.executable, "-c", CHILD, options, cell], env=env,
                                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
                for cell in (killed, frozen)}

    def states(got: list[Message], state: str) -> set[str]:
        return {m.payload["cell"] for m in got if m.payload["state"] == state}

    try:
        try:
            watcher.until(lambda got: states(got, "online") == {killed, frozen}, timeout=30)
        except AssertionError:
            for child in children.values():
                child.kill()
            raise AssertionError({cell: child.communicate()[1].decode() for cell, child in children.items()}) from None
        os.kill(children[frozen].pid, signal.SIGSTOP)
        os.kill(children[killed].pid, signal.SIGKILL)
        # 1.5 keep-alives of silence after the frozen cell's last packet (sent before now); Mosquitto 2.0 counts
        # whole seconds and looks only every 5 s: up to 6 s more
        offline = watcher.until(lambda got: states(got, "offline") == {killed, frozen},
                                timeout=1.5 * keepalive_s + 6.5)
    finally:
        for child in children.values():
            child.kill()  # a stopped process is killed too
            child.wait(10)
            child.stderr.close()
        watcher.close()
    for message in offline:
        assert message.payload["reason"] == "connection lost" and message.payload["state"] == "offline"
        assert "live_job" not in message.payload  # the will is fixed at connect: no stale live job
    assert [m.payload["cell"] for m in offline] == [killed, frozen]  # the dead socket at once, the silent one later

    late = Listener(mosquitto, [f"{PREFIX}/{frozen}/status"])
    try:
        [kept] = late.take(1)
    finally:
        late.close()
    assert kept.retain and kept.payload["state"] == "offline"


# -- outages ------------------------------------------------------------------------------

def test_a_persistent_subscriber_gets_every_job_event_in_order_across_a_broker_restart(mosquitto):
    cell = "cell-restart"
    topic = f"{PREFIX}/{cell}/events/job"
    Listener(mosquitto, [topic], client_id="historian-restart", persistent=True).close()  # away from now on
    sink = make_sink(mosquitto, cell)
    try:
        sink.connect()
        sink.deliver([job_state(1), job_state(2)])
        mosquitto.stop()  # graceful: the broker keeps the historian's session and its queued messages
        mosquitto.resume()
        sink.connect()
        sink.deliver([job_state(3, to="done"), job_state(4, job=43)])
    finally:
        sink.close(graceful=True)
    historian = Listener(mosquitto, [topic], client_id="historian-restart", persistent=True)
    try:
        got = historian.take(4)
    finally:
        historian.close()
    assert [m.payload["id"] for m in got] == [1, 2, 3, 4]


def test_deliver_is_sink_down_while_the_broker_is_stopped_and_the_same_batch_arrives_after(mosquitto):
    cell = "cell-outage"
    topic = f"{PREFIX}/{cell}/events/job"
    Listener(mosquitto, [topic], client_id="historian-outage", persistent=True).close()
    sink = make_sink(mosquitto, cell)
    batch = [job_state(2), job_state(3)]
    try:
        sink.connect()
        sink.deliver([job_state(1)])
        mosquitto.stop()
        try:
            with pytest.raises(SinkDown, match="MQTT broker 127.0.0.1"):
                sink.deliver(batch)
            sink.close(graceful=False)  # as the replicator does
            with pytest.raises(SinkDown, match="unreachable"):
                sink.connect()
        finally:
            mosquitto.resume()
        sink.connect()
        sink.deliver(batch)  # the same batch again: the replicator has not moved its cursor
    finally:
        sink.close(graceful=True)
    historian = Listener(mosquitto, [topic], client_id="historian-outage", persistent=True)
    try:
        got = historian.until(lambda got: 3 in {m.payload["id"] for m in got})
    finally:
        historian.close()
    assert in_order_once(got) == [1, 2, 3]


def test_a_batch_not_acknowledged_in_time_is_sink_down_and_its_duplicates_are_told_apart_by_key(mosquitto,
                                                                                               monkeypatch):
    """The broker hangs (SIGSTOP: the connection stays open, nothing is acknowledged): deliver gives up with
    SinkDown; the broker, back, may still pass on what it had read, then gets the batch again."""
    monkeypatch.setattr(mqtt, "DELIVER_TIMEOUT_S", 0.5)
    cell = "cell-hung"
    listener = Listener(mosquitto, [f"{PREFIX}/{cell}/events/job"])
    sink = make_sink(mosquitto, cell)
    batch = [job_state(2), job_state(3)]
    try:
        sink.connect()
        sink.deliver([job_state(1)])
        os.kill(mosquitto.proc.pid, signal.SIGSTOP)
        try:
            with pytest.raises(SinkDown, match=r"did not acknowledge 2 of 2 messages in 0.5 s"):
                sink.deliver(batch)
            sink.close(graceful=False)
        finally:
            os.kill(mosquitto.proc.pid, signal.SIGCONT)
        sink.connect()
        sink.deliver(batch)
        sink.deliver([job_state(4)])  # the last one: everything before it has come when it does
        got = listener.until(lambda got: any(m.payload["id"] == 4 for m in got))
    finally:
        sink.close(graceful=True)
        listener.close()
    assert in_order_once(got) == [1, 2, 3, 4]


def test_deliver_and_heartbeat_without_a_connection_are_sink_down(mosquitto):
    sink = make_sink(mosquitto, "cell-unconnected")
    with pytest.raises(SinkDown, match="not connected"):
        sink.deliver([job_state(1)])
    with pytest.raises(SinkDown, match="not connected"):
        sink.heartbeat()
    sink.close(graceful=True)  # nothing to close: no error


# -- refusals -----------------------------------------------------------------------------

def test_a_wrong_password_is_sink_down_saying_not_authorised_without_the_password(mosquitto, caplog):
    caplog.set_level(logging.DEBUG)
    secret = "wrong-secret-4711"
    sink = make_sink(mosquitto, "cell-badpw", password=secret)
    with pytest.raises(SinkDown) as refused:
        sink.connect()
    message = str(refused.value)
    assert "not authorised" in message and f"127.0.0.1:{mosquitto.port}" in message and "'cellctl'" in message
    assert secret not in message and secret not in caplog.text and secret not in repr(sink)
    with pytest.raises(SinkDown, match="not connected"):
        sink.deliver([job_state(1)])  # nothing half-open was left behind


def test_connect_fails_soon_when_the_broker_is_down_or_silent(monkeypatch):
    down = FleetMqtt(host="127.0.0.1", port=free_port(), topic_prefix=PREFIX)
    with pytest.raises(SinkDown, match=r"MQTT broker 127.0.0.1:\d+ unreachable: .*refused"):
        MqttSink(down, "cell-down").connect()

    monkeypatch.setattr(mqtt, "CONNECT_TIMEOUT_S", 0.5)
    with socket.create_server(("127.0.0.1", 0)) as silent:  # accepts the TCP connection, never answers
        settings_ = FleetMqtt(host="127.0.0.1", port=silent.getsockname()[1], topic_prefix=PREFIX)
        with pytest.raises(SinkDown, match="did not answer the connection in 0.5 s"):
            MqttSink(settings_, "cell-silent").connect()


def test_a_topic_the_broker_refuses_is_sink_down(tmp_path):
    cell = "cell-acl"
    acl = f"user cellctl\ntopic readwrite {PREFIX}/{cell}/status\n"  # the status only, no events
    broker = MosquittoServer(acl=acl).start()
    try:
        sink = make_sink(broker, cell)
        sink.connect()  # the status is allowed
        try:
            with pytest.raises(SinkDown, match=f"refused to publish to {PREFIX}/{cell}/events/job: Not authorized"):
                sink.deliver([job_state(1)])
        finally:
            sink.close(graceful=True)
    finally:
        broker.close()


def test_tls_with_the_brokers_certificate_relative_to_the_cell_file(tmp_path):
    from cellctl.startup.tls import make_certificate

    make_certificate(tmp_path / "broker.crt", tmp_path / "broker.key", ["127.0.0.1"], common_name="broker")
    broker = MosquittoServer(tls=(tmp_path / "broker.crt", tmp_path / "broker.key")).start()
    try:
        trusted = MqttSink(settings(broker, tls=MqttTls(ca_file="broker.crt")), "cell-tls", broker.password,
                           base_dir=tmp_path)
        trusted.connect()  # TLS, then the status published and acknowledged
        trusted.deliver([job_state(1)])
        trusted.close(graceful=True)

        system_cas = MqttSink(settings(broker, tls=MqttTls()), "cell-tls", broker.password, base_dir=tmp_path)
        with pytest.raises(SinkDown, match="TLS with the MQTT broker .* failed: .*certificate verify failed"):
            system_cas.connect()
        missing = MqttSink(settings(broker, tls=MqttTls(ca_file="nowhere.crt")), "cell-tls", broker.password,
                           base_dir=tmp_path)
        with pytest.raises(SinkDown, match="MQTT TLS files: .*No such file"):
            missing.connect()
    finally:
        broker.close()
