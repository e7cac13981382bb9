"""The OPC UA server's events from the event hub, in-process over a stand-in service: a drift verdict is a
CalibrationDriftEventType, a fault a JobStateChangedEventType of severity >= 700."""

from __future__ import annotations

import asyncio

from asyncua import Client

from cellctl.config import load_cell_file
from cellctl.core.events import EventHub
from cellctl.opcua.server import OpcuaServer

from tests.conftest import MICROCELL
from tests.support.ports import free_port


class Quiet:
    """The service verbs the server reads, for an idle cell with one faulted job and nothing calibrated."""

    def status(self):
        return {"simulated": True, "job": None, "arm_pose": None, "lock": {"held": False},
                "devices": [{"name": "arm", "kind": "arm", "backend": "sim", "state": "ready"}]}

    def jobs(self, state=None, limit=50):
        return [{"id": 7, "routine": "calibration-check", "state": "faulted", "reason": "VacuumLost", "acknowledged": False}]

    def calibrations(self, target=None):
        return []

    def health(self):
        return {"targets": {}}


def test_drift_verdicts_and_faults_are_events(tmp_path):
    port = free_port()
    config, _ = load_cell_file(MICROCELL)
    config = config.model_copy(update={"opcua": config.opcua.model_copy(update={"enabled": True, "port": port})})
    got: list = []

    class Handler:
        def event_notification(self, event):
            got.append(event)

    async def go():
        hub = EventHub()
        hub.attach(asyncio.get_running_loop())
        server = OpcuaServer(config, Quiet(), hub, tmp_path, "secret")
        url = await server.start()
        try:
            async with Client(url) as client:
                ns = await client.get_namespace_index("urn:cellctl")
                types = await client.nodes.root.get_child(["0:Types", "0:EventTypes", "0:BaseEventType"])
                sub = await client.create_subscription(50, Handler())
                for name in ("JobStateChangedEventType", "CalibrationDriftEventType"):
                    await sub.subscribe_events(client.nodes.server, await types.get_child(f"{ns}:{name}"))
                await asyncio.sleep(0.3)
                hub.publish("state", {"job": 7, "state": "faulted", "reason": "VacuumLost"})
                hub.publish("health", {"job": 8, "verdict": "drift", "drifted": ["cam1"],
                                       "actions": {"cam1": "touch-up: run check with update=true", "nozzle": "ok"}})
                for _ in range(60):
                    if len(got) >= 2:
                        break
                    await asyncio.sleep(0.05)
                state = await (await client.nodes.objects.get_child(
                    [f"{ns}:Cell", f"{ns}:State", f"{ns}:CurrentState"])).read_value()
                return state
        finally:
            await server.stop()

    state = asyncio.run(asyncio.wait_for(go(), 60))
    assert state == "Faulted"  # a faulted job nobody acknowledged
    fault = next(e for e in got if getattr(e, "State", None) == "faulted")
    assert fault.JobId == 7 and fault.Routine == "calibration-check" and fault.Reason == "VacuumLost" and fault.Severity >= 700
    drift = next(e for e in got if hasattr(e, "Targets"))
    assert drift.Targets == "cam1" and drift.JobId == 8 and "touch-up" in drift.Remedy and drift.Severity >= 500
