"""The plant's event stream: a cell's records published to an MQTT broker (paho-mqtt, MQTT 5), for dashboards,
historians and the MES. The replicator (replicator.py) hands `MqttSink.deliver` the outbox's records in order.

Topics, under `<topic_prefix>/<cell>/` (topic_prefix is the fleet settings' ISA-95 path such as
`acme/plant1/line3`; cell is the cell's plant name):

| topic             | retained | made from            | when                                                        |
|-------------------|----------|----------------------|-------------------------------------------------------------|
| status            | yes      | connect, `cell`      | the cell connects, its live job changes, it stops; the      |
|                   |          | records, Last Will   | broker's Last Will when its link breaks or it falls silent  |
| events/job        | no       | `job_state` records  | every job state change                                      |
| events/progress   | no       | `progress` records   | a step, at most one per job every progress_interval_s      |
| results/<routine> | no       | `result` records     | a routine finished (a sequence's routines one by one)       |
| health/<target>   | yes      | `health_check`       | a check of calibrations: one message per target checked     |

The other records (job, samples, calibration, activation, audit) go to the plant database only.

Every message is QoS 1 and a JSON object with "cell" and "at" (ISO 8601, UTC). A message made from a record
has "key", the record's identity in this cell, and the record's own fields. Delivery is at least once: after
an outage a message can come twice (the same key); a subscriber that cares drops the second. Job events
carry "id", the job_state id, which increases per cell: a subscriber can check their order. A persistent
subscriber (clean_session false, or a session expiry) gets what was published while it was away. The status
messages the cell makes itself (connect, stop) and the will have no "key": they are states, the newest wins.
Every status carries the daemon's description, software_revision and api_url.

status (retained), online: on connect (live_job and cell_state as last known, null before the first `cell`
record since the daemon started) and on every `cell` record:

    {"cell": "cell-7", "state": "online", "live_job": 42, "cell_state": "running",
     "at": "2026-03-02T08:15:00.120Z", "key": "cell", "description": "line 3 glue cell",
     "software_revision": "0.4.1", "api_url": "https://cell-7.plant:8443"}

status, offline: the cell stopped (it says so before it disconnects), or the broker's Last Will when the cell's
link broke or the cell fell silent (1.5 keep-alives after it did; Mosquitto 2.0 looks every 5 s, so up to 5 s
more). The will's "at" is when the cell connected (the broker sends it later, unchanged), and it has no live
job (it would be stale):

    {"cell": "cell-7", "state": "offline", "reason": "cell stopped", "live_job": null, "cell_state": "idle",
     "at": "2026-03-02T17:00:03.500Z", "description": "...", "software_revision": "0.4.1", "api_url": "..."}
    {"cell": "cell-7", "state": "offline", "reason": "connection lost", "at": "2026-03-02T08:14:59.870Z", ...}

events/job:

    {"cell": "cell-7", "key": "job_state/311", "at": "2026-03-02T08:15:00.118Z", "id": 311, "job": 42,
     "routine": "<routine>", "from": "queued", "to": "running", "reason": null, "who": "operator:anna"}

events/progress:

    {"cell": "cell-7", "key": "progress/42//17", "at": "2026-03-02T08:16:40.002Z", "job": 42,
     "routine": "<routine>", "item": null, "step": 17, "total": 64, "cell_time_s": 51.2,
     "eta_cell_s": 142.0, "residual_um": 38.5}

results/<routine> (the name of the routine that finished, as one topic level), "result" being the
result.json the cell keeps, unchanged (it can be large):

    {"cell": "cell-7", "key": "result/42/", "at": "2026-03-02T08:21:13.540Z", "job": 42, "item": "",
     "routine": "<routine>", "result": {"routine": "<routine>", "model": {...}, "stats": {...}, ...}}

health/<target> (retained: the target's latest check), "verdict" being the whole check's:

    {"cell": "cell-7", "key": "health_check/9", "at": "2026-03-02T06:00:12.001Z", "id": 9,
     "created": "2026-03-02T07:00:12+0100", "verdict": "drift", "target": "cam1", "calibration_id": 12,
     "drifted": true, "p_value": 0.003, "drift": {...}, "action": "touch-up: run check with update=true"}

A name that cannot be a topic level ('/', '+', '#' in it) has those characters replaced by '_' in the topic;
the payload keeps it as is.

The publisher is a fresh clean-session client per connection, client id `cellctl-<cell>`: what has not been
acknowledged is the outbox's to send again, not paho's. `deliver` waits for every PUBACK (DELIVER_TIMEOUT_S)
and raises SinkDown otherwise (also for a PUBACK refusing the message, such as an ACL's "Not authorized"), so
the replicator keeps the records and sends them again later. A link dropped after a failure ends with MQTT 5's
"disconnect with will message": the status says offline until the cell is back, rather than online.
"""

from __future__ import annotations

import json
import logging
import ssl
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import paho.mqtt.client as paho
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.reasoncodes import ReasonCode

from cellctl.fleet.replicator import SinkDown
from cellctl.stores.outbox import Record

if TYPE_CHECKING:  # only for the annotations: the sink needs nothing else of the cell file's models
    from cellctl.config import FleetMqtt

log = logging.getLogger("cellctl.fleet")

CONNECT_TIMEOUT_S = 5.0  # TCP, TLS and the broker's CONNACK, each
DELIVER_TIMEOUT_S = 10.0  # every PUBACK of a batch
CLOSE_TIMEOUT_S = 2.0  # the offline status's PUBACK when the cell stops
SKIPPED = frozenset({"job", "samples", "calibration", "activation", "audit"})  # the plant database's alone
NOT_AUTHORISED = (134, 135)  # CONNACK: bad user name or password; not authorized


def iso(t: float) -> str:
    """Seconds since the epoch as ISO 8601 UTC with milliseconds, as the job store writes its times."""
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


def level(name: Any) -> str:
    """A name as one topic level: no separator, no wildcard (paho refuses those, and the record would block
    the outbox for good)."""
    text = str(name)
    for c in "/+#\0":
        text = text.replace(c, "_")
    return text or "_"


class _Link:
    """One connection's client and what its network thread has told us about it."""

    def __init__(self, client: paho.Client):
        self.client = client
        self.answered = threading.Event()  # CONNACK came, or the connection closed before it did
        self.reason: ReasonCode | None = None  # the CONNACK's reason code
        self.lost = threading.Event()  # the connection closed: this client is done (no auto-reconnect)
        self.refused: dict[int, str] = {}  # mid -> the broker's reason for refusing that PUBLISH (PUBACK >= 0x80)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self._on_publish

    def _on_connect(self, client, userdata, flags, reason, properties) -> None:
        self.reason = reason
        self.answered.set()

    def _on_disconnect(self, client, userdata, flags, reason, properties) -> None:
        self.lost.set()
        self.answered.set()

    def _on_publish(self, client, userdata, mid, reason, properties) -> None:
        if reason.is_failure:  # e.g. the broker's ACL denies the topic: it acknowledges and drops the message
            self.refused[mid] = str(reason)


class MqttSink:
    """The event stream as a replicator sink: `connect`, `deliver` (all or nothing: every PUBACK or SinkDown),
    `heartbeat`, `close`."""

    name = "mqtt"

    def __init__(self, settings: FleetMqtt, cell: str, password: str | None = None, base_dir: Path | None = None,
                 info: dict | None = None):
        self.settings, self.cell = settings, cell
        self._password = password
        self.base_dir = Path(base_dir) if base_dir is not None else Path.cwd()
        self.info = dict(info or {})
        self.root = f"{settings.topic_prefix}/{level(cell)}"
        self.broker = f"{settings.host}:{settings.port}"
        self._link: _Link | None = None
        self._cell_state: str | None = None  # the last `cell` record's, for the status on (re)connect and stop
        self._live_job: int | None = None

    def __repr__(self) -> str:  # never the password
        return f"MqttSink({self.broker}, {self.root})"

    # -- the Sink protocol ----------------------------------------------------------------

    def connect(self) -> None:
        self.close(graceful=False)
        client = self._client()
        link = _Link(client)
        try:
            client.connect(self.settings.host, self.settings.port, keepalive=self.settings.keepalive_s,
                           clean_start=True)
        except ssl.SSLError as exc:
            raise SinkDown(f"TLS with the MQTT broker {self.broker} failed: {exc}") from None
        except (OSError, ValueError) as exc:
            raise SinkDown(f"MQTT broker {self.broker} unreachable: {exc}") from None
        client.loop_start()
        self._link = link
        try:
            if not link.answered.wait(CONNECT_TIMEOUT_S):
                raise SinkDown(f"MQTT broker {self.broker} did not answer the connection in {CONNECT_TIMEOUT_S:g} s")
            if link.reason is None:
                raise SinkDown(f"MQTT broker {self.broker} closed the connection before accepting it")
            if link.reason.value in NOT_AUTHORISED:
                raise SinkDown(f"MQTT broker {self.broker} refused the connection: not authorised ({link.reason}); "
                               f"check the username ({self.settings.username!r}) and the password")
            if link.reason.is_failure:
                raise SinkDown(f"MQTT broker {self.broker} refused the connection: {link.reason}")
            self._publish([("status", self._status("online"), True)], DELIVER_TIMEOUT_S)
        except SinkDown:
            self.close(graceful=False)
            raise

    def deliver(self, records: list[Record]) -> None:
        messages = [m for record in records for m in self._messages(record)]
        self._publish(messages, DELIVER_TIMEOUT_S)
        for record in records:  # only once the broker has them all: a failed batch comes again
            if record.kind == "cell":
                self._cell_state, self._live_job = record.body.get("state"), record.body.get("live_job")

    def heartbeat(self) -> None:
        # Liveness itself is MQTT's: keep-alive pings, and the Last Will when they stop. Here: is the link up?
        self._check()

    def close(self, graceful: bool) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        client = link.client
        try:
            if graceful and not link.lost.is_set():
                try:  # best effort: the cell is stopping either way
                    self._publish([("status", self._status("offline", reason="cell stopped"), True)],
                                  CLOSE_TIMEOUT_S, link)
                except SinkDown as exc:
                    log.debug("offline status not acknowledged: %s", exc)
                client.disconnect()  # a clean DISCONNECT: the broker drops the Last Will
            else:
                # Not stopping, the link is broken or a batch timed out: the broker publishes the Last Will now
                # (offline, connection lost) rather than leaving the status online until we are back.
                client.disconnect(reasoncode=ReasonCode(PacketTypes.DISCONNECT, "Disconnect with will message"))
        finally:
            client.loop_stop()

    # -- internals ------------------------------------------------------------------------

    def _client(self) -> paho.Client:
        """A fresh client: MQTT 5, clean start, no reconnecting of its own (the replicator does that, with a
        fresh client), the Last Will set, credentials and TLS as configured."""
        client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=f"cellctl-{self.cell}",
                             protocol=paho.MQTTv5, reconnect_on_failure=False)
        client.connect_timeout = CONNECT_TIMEOUT_S
        if self.settings.username:
            client.username_pw_set(self.settings.username, self._password)
        if self.settings.tls is not None:
            client.tls_set_context(self._tls_context())
        will = self._status("offline", reason="connection lost")
        for stale in ("live_job", "cell_state"):  # the will is fixed at connect: these would be stale
            will.pop(stale)
        client.will_set(f"{self.root}/status", json.dumps(will), qos=1, retain=True)
        return client

    def _tls_context(self) -> ssl.SSLContext:
        tls = self.settings.tls
        path = lambda p: str(self.base_dir / p) if p else None  # noqa: E731 - relative to the cell file
        try:
            context = ssl.create_default_context(cafile=path(tls.ca_file))  # None: the system's CAs
            if tls.cert_file:
                context.load_cert_chain(path(tls.cert_file), path(tls.key_file))
        except (OSError, ValueError) as exc:  # a missing or unreadable file, a key that does not match
            raise SinkDown(f"MQTT TLS files: {exc}") from None
        return context

    def _status(self, state: str, **extra: Any) -> dict:
        return {"cell": self.cell, "state": state, **extra, "live_job": self._live_job,
                "cell_state": self._cell_state, "at": iso(time.time()), **self.info}

    def _payload(self, record: Record, fields: dict) -> str:
        # the record's own fields win over "at" (a job_state has its own, in the same format)
        return json.dumps({"cell": self.cell, "key": record.key, "at": iso(record.at), **fields})

    def _messages(self, record: Record) -> list[tuple[str, str, bool]]:
        """(topic under the cell's root, payload, retained) for one record; [] for a kind not published."""
        body, kind = record.body, record.kind
        if kind == "job_state":
            return [("events/job", self._payload(record, body), False)]
        if kind == "progress":
            return [("events/progress", self._payload(record, body), False)]
        if kind == "result":
            return [(f"results/{level(body.get('routine', ''))}", self._payload(record, body), False)]
        if kind == "health_check":
            common = {k: v for k, v in body.items() if k != "targets"}
            return [(f"health/{level(target)}", self._payload(record, {**common, "target": target, **checked}), True)
                    for target, checked in body.get("targets", {}).items()]
        if kind == "cell":
            status = {"state": "online", "live_job": body.get("live_job"), "cell_state": body.get("state"),
                      **self.info}
            return [("status", self._payload(record, status), True)]
        if kind not in SKIPPED:
            log.debug("record kind %r is not published to the event stream", kind)
        return []

    def _check(self, link: _Link | None = None) -> _Link:
        link = link or self._link
        if link is None or link.lost.is_set() or not link.client.is_connected():
            raise SinkDown(f"not connected to the MQTT broker {self.broker}")
        return link

    def _publish(self, messages: list[tuple[str, Any, bool]], timeout: float, link: _Link | None = None) -> None:
        """Publish (QoS 1) and wait for every PUBACK; SinkDown if one is missing, refused, or the link drops."""
        link = self._check(link)
        sent = []
        for topic, payload, retain in messages:
            data = payload if isinstance(payload, str) else json.dumps(payload)
            sent.append((topic, link.client.publish(f"{self.root}/{topic}", data, qos=1, retain=retain)))
        deadline = time.monotonic() + timeout
        for topic, info in sent:
            while True:
                if info.rc not in (paho.MQTT_ERR_SUCCESS, paho.MQTT_ERR_AGAIN):
                    raise SinkDown(f"not connected to the MQTT broker {self.broker}")
                if info.is_published():
                    break
                if link.lost.is_set():
                    raise SinkDown(f"connection to the MQTT broker {self.broker} lost while publishing")
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = sum(not i.is_published() for _, i in sent)
                    raise SinkDown(f"MQTT broker {self.broker} did not acknowledge {missing} of {len(sent)} "
                                   f"messages in {timeout:g} s")
                info.wait_for_publish(min(left, 0.25))  # short slices: notice a lost link at once
            refused = link.refused.pop(info.mid, None)
            if refused is not None:
                raise SinkDown(f"MQTT broker {self.broker} refused to publish to {self.root}/{topic}: {refused}")
