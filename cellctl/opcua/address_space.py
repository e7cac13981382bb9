"""The OPC UA address space of a cell, under Objects/Cell in namespace `urn:cellctl`.

Its shape follows the Machinery companion specifications (OPC 40001-1 identification and item state,
OPC 40001-3 job management); docs/how-to/opcua.md ("What the MES sees") lists every node:

    Identification/  Name, Description, SoftwareRevision, Simulated
    State/           CurrentState (Idle, Running, Paused, Faulted, Offline), LiveJobId
    Devices/<name>/  Kind, Backend, State, LastError
    Arm/             X_mm, Y_mm, Z_mm, Alpha_deg
    Jobs/            Start, Pause, Resume, Acknowledge, Abort (methods)
      Live/          Id, Routine, State, Step, Total, CellTime_s, Residual_um
      Last/          Id, Routine, State, Reason, VerificationMean_um, VerificationMax_um, ResultJson
    Calibrations/<target>/  ActiveId, Version, Routine, VerificationMean_um, Health, LastCheck
    Lock/            Held, Holder (variables), Acquire, Release (methods)
    Locate           (method)

Variables are read-only to every client; the server writes them (`Values.set`) when the cell changes.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone

from asyncua import Server, ua
from asyncua.common.node import Node

NAMESPACE = "urn:cellctl"
NULL_TIME = datetime(1601, 1, 1, tzinfo=timezone.utc)  # OPC UA's null DateTime: never

V = ua.VariantType
IDENTIFICATION = {"Name": V.String, "Description": V.String, "SoftwareRevision": V.String, "Simulated": V.Boolean}
STATE = {"CurrentState": V.String, "LiveJobId": V.UInt32}
DEVICE = {"Kind": V.String, "Backend": V.String, "State": V.String, "LastError": V.String}
ARM = {"X_mm": V.Double, "Y_mm": V.Double, "Z_mm": V.Double, "Alpha_deg": V.Double}
LIVE = {"Id": V.UInt32, "Routine": V.String, "State": V.String, "Step": V.UInt32, "Total": V.UInt32,
        "CellTime_s": V.Double, "Residual_um": V.Double}
LAST = {"Id": V.UInt32, "Routine": V.String, "State": V.String, "Reason": V.String, "VerificationMean_um": V.Double,
        "VerificationMax_um": V.Double, "ResultJson": V.String}
CALIBRATION = {"ActiveId": V.UInt32, "Version": V.UInt32, "Routine": V.String, "VerificationMean_um": V.Double,
               "Health": V.String, "LastCheck": V.DateTime}
LOCK = {"Held": V.Boolean, "Holder": V.String}
EMPTY = {V.String: "", V.Boolean: False, V.UInt32: 0, V.Double: math.nan, V.DateTime: NULL_TIME}

# the events: a job's state change (OPC 40001-3's idea of a job state event), and a calibration judged drifted
JOB_EVENT = ("JobStateChangedEventType", [("JobId", V.UInt32), ("Routine", V.String), ("State", V.String),
                                          ("Reason", V.String)])
DRIFT_EVENT = ("CalibrationDriftEventType", [("JobId", V.UInt32), ("Targets", V.String), ("Remedy", V.String)])


class Values:
    """The variable nodes by path ("Jobs/Live/Step"); `set` writes only what changed (one notification each)."""

    def __init__(self, server: Server, idx: int, cell: Node):
        self.server, self.idx, self.cell = server, idx, cell
        self.nodes: dict[str, tuple[Node, ua.VariantType]] = {}
        self.folders: dict[str, Node] = {"": cell}
        self._last: dict[str, object] = {}

    async def folder(self, path: str) -> Node:
        if path not in self.folders:
            parent_path, _, name = path.rpartition("/")
            parent = await self.folder(parent_path)
            self.folders[path] = await parent.add_object(self.idx, name)
        return self.folders[path]

    async def variables(self, path: str, names: dict[str, ua.VariantType]) -> None:
        folder = await self.folder(path)
        for name, vtype in names.items():
            node = await folder.add_variable(self.idx, name, ua.Variant(EMPTY[vtype], vtype))
            self.nodes[f"{path}/{name}"] = (node, vtype)

    async def set(self, path: str, value) -> None:
        node, vtype = self.nodes[path]
        value = EMPTY[vtype] if value is None else value
        if vtype is V.UInt32:
            value = max(int(value), 0)
        elif vtype is V.Double:
            value = float(value)
        if path in self._last and _same(self._last[path], value):
            return
        self._last[path] = value
        await self.server.write_attribute_value(node.nodeid, ua.DataValue(ua.Variant(value, vtype)))


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


async def build(server: Server, status: dict) -> tuple[int, Values]:
    """Objects/Cell and everything under it that the cell file fixes (devices); calibrations grow as they come."""
    idx = await server.register_namespace(NAMESPACE)
    cell = await server.nodes.objects.add_object(idx, "Cell")
    values = Values(server, idx, cell)
    await values.variables("Identification", IDENTIFICATION)
    await values.variables("State", STATE)
    for device in status["devices"]:
        await values.variables(f"Devices/{device['name']}", DEVICE)
    await values.variables("Arm", ARM)
    await values.variables("Jobs/Live", LIVE)
    await values.variables("Jobs/Last", LAST)
    await values.folder("Calibrations")
    await values.variables("Lock", LOCK)
    return idx, values


def argument(name: str, vtype: ua.VariantType, description: str) -> ua.Argument:
    arg = ua.Argument()
    arg.Name = name
    arg.DataType = ua.NodeId(vtype.value)
    arg.ValueRank = -1
    arg.Description = ua.LocalizedText(description)
    return arg
