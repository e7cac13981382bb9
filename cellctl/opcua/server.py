"""The OPC UA server: a front end over the cell's service, in the daemon's event loop.

Methods translate their arguments, call the service verb (in a thread: verbs may wait on the cell) and
map its refusals to Bad status codes; the lock, the validation and the audit are the service's. The
variables follow the cell: the server re-reads the service whenever the event hub says something
happened (a job's progress or state) and once a second anyway (devices, the arm, calibrations).
The hub's job state changes and drift verdicts become OPC UA events.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from contextvars import ContextVar
from datetime import datetime, timezone
from importlib.metadata import version
from pathlib import Path

from asyncua import Server, ua
from asyncua.crypto.permission_rules import UserRole

from cellctl.config import CellFile, OpcuaSettings
from cellctl.errors import InvalidRequest, ServiceError
from cellctl.opcua.address_space import CALIBRATION, DRIFT_EVENT, JOB_EVENT, NAMESPACE, argument, build
from cellctl.opcua.security import (
    CURRENT_USER,
    CellServer,
    CellUser,
    CellUsers,
    SessionRules,
    TrustedClients,
    server_certificate,
)
from cellctl.service.interface import Caller
from cellctl.startup.tls import is_loopback
from cellctl.stores.client_certificates import ClientCertificates, read_certificate

log = logging.getLogger("cellctl.opcua")
V = ua.VariantType
TERMINAL = ("done", "faulted", "aborted")
POLICIES = {"none": ua.SecurityPolicyType.NoSecurity, "sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
            "sign_encrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt}
# the service's refusals by their HTTP status, as OPC UA says them (the message goes with it, as diagnostic info)
STATUS = {400: ua.StatusCodes.BadInvalidArgument, 422: ua.StatusCodes.BadInvalidArgument,
          404: ua.StatusCodes.BadNotFound, 423: ua.StatusCodes.BadUserAccessDenied,
          409: ua.StatusCodes.BadInvalidState, 503: ua.StatusCodes.BadResourceUnavailable,
          507: ua.StatusCodes.BadResourceUnavailable}  # 507: the store's disk is below its floor
FAULT_SEVERITY, DRIFT_SEVERITY, STATE_SEVERITY = 800, 600, 200
READS = ("Locate",)  # methods that change nothing: their refusals are not audited (HTTP's GETs are not either)
# set when a method's call reaches the service, which audits it (and its refusal) from there on
REACHED_SERVICE: ContextVar[bool] = ContextVar("reached_service", default=False)


def software_revision() -> str:
    return version("cellctl")


class OpcuaServer:
    def __init__(self, config: CellFile, service, hub, store_dir: Path, token: str, count=None):
        self.config, self.settings = config, config.opcua
        self.service, self.hub = service, hub
        self.store_dir, self.token = Path(store_dir), token
        self.count = count or (lambda outcome: None)  # the metrics' request counter
        self.server: Server | None = None
        self._tasks: list[asyncio.Task] = []
        self._jobs_seen: dict[int, str] = {}

    # -- start and stop -------------------------------------------------------------------------
    async def start(self) -> str:
        """Serve; returns the endpoint URL. Refuses (InvalidRequest) a `none` endpoint beyond loopback."""
        s: OpcuaSettings = self.settings
        if "none" in s.security and not is_loopback(s.host):
            raise InvalidRequest(f"opcua.security: 'none' is offered only when bound to loopback, not {s.host}; "
                                 "remove it (sign, sign_encrypt remain) or bind opcua.host to 127.0.0.1")
        app_uri = f"{NAMESPACE}:{self.config.cell.name}"
        clients = ClientCertificates(self.store_dir / "opcua", {p: read_certificate(p, "opcua.trusted_clients")
                                                                for p in s.trusted_clients})
        users = {name: read_certificate(p, f"opcua.user_certs.{name}") for name, p in s.user_certs.items()}
        cert, key = server_certificate(self.store_dir / "opcua", app_uri, s.host)
        server = CellServer(user_manager=CellUsers(self.token, users))
        await server.init()
        url = f"opc.tcp://{s.host}:{s.port}/cellctl"
        server.set_endpoint(url)
        server.set_server_name(f"cellctl {self.config.cell.name}")
        await server.set_application_uri(app_uri)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        server.set_security_policy([POLICIES[p] for p in s.security], permission_ruleset=SessionRules(clients))
        server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken, ua.X509IdentityToken])
        server.set_certificate_validator(TrustedClients(clients))
        await server.set_build_info(NAMESPACE, "cellctl", "cellctl", software_revision(), "0",
                                    datetime.now(timezone.utc))
        status = await asyncio.to_thread(self.service.status)
        idx, self.values = await build(server, status)
        await self._methods(idx)
        await self._events(server, idx)
        self.server = server
        await server.start()
        await self._identify()
        self._tasks = [asyncio.create_task(self._follow(), name="opcua-follow")]
        log.info("opc ua serving", extra={"url": url, "security": s.security})
        return url

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.server is not None:
            await self.server.stop()
            self.server = None

    # -- methods --------------------------------------------------------------------------------
    async def _methods(self, idx: int) -> None:
        jobs = await self.values.folder("Jobs")
        job_id = ("JobId", V.UInt32, "the job's id (as in the HTTP API)")
        await self._method(jobs, idx, "Start", self._start,
                           [("Routine", V.String, "routine or sequence name"),
                            ("Parameters", V.String, "the routine's parameters as a JSON object"),
                            ("Seed", V.Int32, "simulated cells: the simulation seed; -1 = none")],
                           [("JobId", V.UInt32, "the new job's id")])
        await self._method(jobs, idx, "Pause", self._pause,
                           [job_id, ("Immediate", V.Boolean, "stop in the middle of a move")], [])
        for name, verb in (("Resume", "resume"), ("Acknowledge", "acknowledge"), ("Abort", "abort")):
            await self._method(jobs, idx, name, self._job_verb(verb), [job_id], [])
        lock = await self.values.folder("Lock")
        await self._method(lock, idx, "Acquire", self._acquire,
                           [("Holder", V.String, "who holds it, shown to everyone"),
                            ("Ttl_s", V.Double, "seconds until it expires unless renewed")],
                           [("LockId", V.String, "presented by this session from now on")])
        await self._method(lock, idx, "Release", self._release, [], [])
        await self._method(self.values.cell, idx, "Locate", self._locate,
                           [("Camera", V.String, "camera name"), ("U", V.Double, "pixel column"),
                            ("V", V.Double, "pixel row")],
                           [("X_mm", V.Double, "robot x"), ("Y_mm", V.Double, "robot y"),
                            ("Sigma_um", V.Double, "1-sigma uncertainty per axis"),
                            ("Warning", V.String, "empty, or why the answer is less sure (outside the calibrated "
                                                  "region: Sigma_um is the grown uncertainty there)")])

    async def _method(self, parent, idx, name, work, inputs, outputs) -> None:
        async def call(_parent, *args):
            return await self._call(name, work, inputs, list(args))

        await parent.add_method(idx, name, call, [argument(*a) for a in inputs], [argument(*a) for a in outputs])

    async def _call(self, name: str, work, inputs, args: list) -> ua.CallMethodResult:
        """Check the arguments against their declaration, run the verb, and say the outcome as a status."""
        result = ua.CallMethodResult()
        result.InputArgumentResults = [ua.StatusCode() for _ in args]
        REACHED_SERVICE.set(False)
        if len(args) != len(inputs):
            code = ua.StatusCodes.BadArgumentsMissing if len(args) < len(inputs) else ua.StatusCodes.BadTooManyArguments
            return await self._refuse(result, name, code, f"{name} takes {len(inputs)} arguments "
                                                     f"({', '.join(a[0] for a in inputs)}), got {len(args)}")
        values = []
        for i, ((arg, vtype, _), given) in enumerate(zip(inputs, args)):
            if not isinstance(given, ua.Variant) or given.VariantType is not vtype or given.is_array:
                result.InputArgumentResults[i] = ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
                got = given.VariantType.name if isinstance(given, ua.Variant) else type(given).__name__
                return await self._refuse(result, name, ua.StatusCodes.BadInvalidArgument,
                                    f"{arg}: must be a {vtype.name}, got {got}", i)
            values.append(given.Value)
        user = CURRENT_USER.get()
        if user is None or user.role is not UserRole.User:  # the rules refuse these first; never rely on it alone
            return await self._refuse(result, name, ua.StatusCodes.BadUserAccessDenied, "calling needs a user identity")
        try:
            out = await work(user, *values)
        except ServiceError as exc:
            code = STATUS.get(getattr(exc, "status", 400), ua.StatusCodes.BadInvalidState)
            return await self._refuse(result, name, code, str(exc), _argument_named(str(exc), inputs), exc)
        except Exception:  # noqa: BLE001 - a bug in a verb must not take the server down
            log.exception("opc ua method failed", extra={"method": name})
            self.count("error")
            result.StatusCode = ua.StatusCode(ua.StatusCodes.BadInternalError)
            return result
        self.count("ok")
        result.OutputArguments = out
        return result

    async def _refuse(self, result, name, code, message: str, argument_index: int | None = None,
                      exc: ServiceError | None = None) -> ua.CallMethodResult:
        status = ua.status_codes.get_name_and_doc(code)[0]
        log.info("opc ua call refused", extra={"method": name, "status": status, "reason": message})
        if not REACHED_SERVICE.get() and name not in READS:  # refused here, before the service: audit it as HTTP does
            user = CURRENT_USER.get()
            caller = (self._caller(user, name) if user is not None else
                      Caller(who="anonymous@opcua", via=f"OPC UA {name}", credential="-"))
            refusal = exc if exc is not None else InvalidRequest(f"{status}: {message}")
            await asyncio.to_thread(self.service.record_refusal, caller, name, "", refusal)
        self.count(f"refused {status}")
        result.StatusCode = ua.StatusCode(code)
        info = ua.DiagnosticInfo(AdditionalInfo=message)
        result.InputArgumentDiagnosticInfos = [info if argument_index in (None, i) else ua.DiagnosticInfo()
                                               for i in range(len(result.InputArgumentResults))]
        return result

    def _caller(self, user: CellUser, via: str) -> Caller:
        REACHED_SERVICE.set(True)
        return Caller(who=f"{user.name}@opcua", lock=user.lock_id, via=f"OPC UA {via}", credential=user.credential)

    async def _start(self, user, routine: str, parameters: str, seed: int) -> list:
        try:
            params = json.loads(parameters) if parameters.strip() else {}
        except json.JSONDecodeError as exc:
            raise InvalidRequest(f"Parameters: not JSON ({exc.msg} at character {exc.pos}); "
                                 'give a JSON object such as {"rows": 4}') from None
        if not isinstance(params, dict):
            raise InvalidRequest(f"Parameters: must be a JSON object, got {type(params).__name__}")
        job = await asyncio.to_thread(self.service.submit, self._caller(user, "Jobs/Start"), routine, params,
                                      None if seed == -1 else seed)
        return [ua.Variant(job["id"], V.UInt32)]

    async def _pause(self, user, job_id: int, immediate: bool) -> list:
        await asyncio.to_thread(self.service.pause, self._caller(user, "Jobs/Pause"), job_id, immediate)
        return []

    def _job_verb(self, verb: str):
        async def work(user, job_id: int) -> list:
            await asyncio.to_thread(getattr(self.service, verb), self._caller(user, f"Jobs/{verb.title()}"), job_id)
            return []

        return work

    async def _acquire(self, user, holder: str, ttl_s: float) -> list:
        info = await asyncio.to_thread(self.service.acquire_lock, self._caller(user, "Lock/Acquire"), holder, ttl_s)
        user.lock_id = info["lock_id"]  # this session presents it from now on
        return [ua.Variant(info["lock_id"], V.String)]

    async def _release(self, user) -> list:
        await asyncio.to_thread(self.service.release_lock, self._caller(user, "Lock/Release"))
        user.lock_id = None
        return []

    async def _locate(self, user, camera: str, u: float, v: float) -> list:
        found = await asyncio.to_thread(self.service.locate, camera, u, v)
        sigma = found.get("sigma_um")
        return [ua.Variant(found["x_mm"], V.Double), ua.Variant(found["y_mm"], V.Double),
                ua.Variant(math.nan if sigma is None else float(sigma), V.Double),
                ua.Variant(found.get("warning") or "", V.String)]

    # -- events -----------------------------------------------------------------------------------
    async def _events(self, server: Server, idx: int) -> None:
        """Each event type from two notifiers: the Server object (where clients look first) and Cell."""
        self._generators = {}
        for key, (name, fields) in (("job", JOB_EVENT), ("drift", DRIFT_EVENT)):
            etype = await server.create_custom_event_type(idx, name, ua.ObjectIds.BaseEventType, fields)
            self._generators[key] = [await server.get_event_generator(etype, node)
                                     for node in (ua.ObjectIds.Server, self.values.cell)]

    async def _emit(self, key: str, severity: int, message: str, **fields) -> None:
        for gen in self._generators[key]:
            for name, value in fields.items():
                setattr(gen.event, name, value)
            gen.event.Severity = severity
            await gen.trigger(message=message)

    # -- following the cell -------------------------------------------------------------------------
    async def _identify(self) -> None:
        status = await asyncio.to_thread(self.service.status)
        v = self.values
        await v.set("Identification/Name", self.config.cell.name)
        await v.set("Identification/Description", self.config.cell.description)
        await v.set("Identification/SoftwareRevision", software_revision())
        await v.set("Identification/Simulated", bool(status["simulated"]))

    async def _follow(self) -> None:
        seq = self.hub.last_seq
        while True:
            try:
                events = self.hub.since(seq)
                if events:
                    seq = events[-1][0]
                await self._refresh(events)
            except asyncio.CancelledError:
                raise
            except Exception:  # noqa: BLE001 - the next round tries again; the server stays up
                log.exception("opc ua refresh failed")
            await self.hub.wait(1.0)
            await asyncio.sleep(0.05)  # a burst of progress events costs one refresh

    async def _refresh(self, events: list) -> None:
        snap = await asyncio.to_thread(self._snapshot)
        v = self.values
        status, live, last = snap["status"], snap["live"], snap["last"]
        await v.set("State/CurrentState", current_state(status, live, snap["faulted"]))
        await v.set("State/LiveJobId", status["job"])
        for device in status["devices"]:
            base = f"Devices/{device['name']}"
            for key, name in (("kind", "Kind"), ("backend", "Backend"), ("state", "State"), ("error", "LastError")):
                await v.set(f"{base}/{name}", device.get(key, ""))
        pose = status.get("arm_pose") or {}
        for key, name in (("x_mm", "X_mm"), ("y_mm", "Y_mm"), ("z_mm", "Z_mm"), ("alpha_deg", "Alpha_deg")):
            await v.set(f"Arm/{name}", pose.get(key))
        progress = (live or {}).get("progress") or {}
        for key, name in (("id", "Id"), ("routine", "Routine"), ("state", "State")):
            await v.set(f"Jobs/Live/{name}", (live or {}).get(key))
        for key, name in (("step", "Step"), ("total", "Total"), ("cell_time_s", "CellTime_s"),
                          ("residual_um", "Residual_um")):
            await v.set(f"Jobs/Live/{name}", progress.get(key))
        if last is not None:
            verification = (last.get("result") or {}).get("stats", {}).get("verification", {})
            for key, value in (("Id", last["id"]), ("Routine", last["routine"]), ("State", last["state"]),
                               ("Reason", last["reason"]), ("VerificationMean_um", verification.get("mean_um")),
                               ("VerificationMax_um", verification.get("max_um")),
                               ("ResultJson", json.dumps(last.get("result"), default=str) if last.get("result") else "")):
                await v.set(f"Jobs/Last/{key}", value)
        for target, info in snap["health"].items():
            await self._calibration(target, info, snap["calibrations"].get(target))
        lock = status.get("lock") or {}
        await v.set("Lock/Held", bool(lock.get("held")))
        await v.set("Lock/Holder", lock.get("holder", ""))
        await self._announce(events, snap["routines"])

    def _snapshot(self) -> dict:
        """Everything the variables show, read from the service (in a thread: the stores are SQLite)."""
        status = self.service.status()
        live = self.service.job(status["job"]) if status["job"] else None
        recent = self.service.jobs(limit=20)
        ended = next((j for j in recent if j["state"] in TERMINAL), None)
        last = None
        if ended is not None:
            last = dict(ended)
            try:
                last["result"] = self.service.result(ended["id"]) if ended["state"] == "done" else None
            except ServiceError:
                last["result"] = None
        actives = {c["target"]: c for c in self.service.calibrations() if c["active"]}
        return {"status": status, "live": live, "last": last, "health": self.service.health()["targets"],
                "calibrations": actives, "faulted": any(j["state"] == "faulted" and not j["acknowledged"]
                                                        for j in recent),
                "routines": {j["id"]: j["routine"] for j in recent}}

    async def _calibration(self, target: str, info: dict, summary: dict | None) -> None:
        base = f"Calibrations/{target}"
        v = self.values
        if f"{base}/ActiveId" not in v.nodes:  # a target calibrated for the first time since the start
            await v.variables(base, CALIBRATION)
        active, check = info["active"], info.get("last_check")
        verification = ((summary or {}).get("stats") or {}).get("verification", {})
        await v.set(f"{base}/ActiveId", active["id"])
        await v.set(f"{base}/Version", active["version"])
        await v.set(f"{base}/Routine", active["routine"])
        await v.set(f"{base}/VerificationMean_um", verification.get("mean_um"))
        await v.set(f"{base}/Health", info["verdict"])
        await v.set(f"{base}/LastCheck", _time(check["created"]) if check else None)

    async def _announce(self, events: list, routines: dict) -> None:
        for _, kind, data in events:
            if kind == "state":
                job, state, reason = int(data["job"]), data["state"], data.get("reason") or ""
                routine = routines.get(job, "")
                severity = FAULT_SEVERITY if state == "faulted" else STATE_SEVERITY
                await self._emit("job", severity, f"job {job} ({routine}) {state}: {reason}".rstrip(": "),
                                 JobId=ua.Variant(job, V.UInt32), Routine=routine, State=state, Reason=reason)
            elif kind == "health":
                drifted = ", ".join(data.get("drifted") or [])
                actions = data.get("actions") or {}
                remedy = "; ".join(f"{t}: {actions[t]}" for t in data.get("drifted") or [] if t in actions)
                await self._emit("drift", DRIFT_SEVERITY, f"calibration drifted: {drifted}",
                                 JobId=ua.Variant(int(data.get("job") or 0), V.UInt32), Targets=drifted,
                                 Remedy=remedy)


def current_state(status: dict, live: dict | None, faulted: bool) -> str:
    """Machinery's item state, from the cell's: Offline when a device is not ready, Faulted while a faulted
    job is not acknowledged, else what the live job does."""
    if any(d["state"] != "ready" for d in status["devices"]):
        return "Offline"
    if live is not None:
        return {"paused": "Paused", "faulted": "Faulted"}.get(live["state"], "Running")
    return "Faulted" if faulted else "Idle"


def _argument_named(message: str, inputs) -> int | None:
    """The argument a refusal's message starts with ("Routine: ..."), so its diagnostic sits on that one."""
    head = message.partition(":")[0].strip().lower()
    return next((i for i, a in enumerate(inputs) if a[0].lower() == head), None)


def _time(value) -> datetime:
    if isinstance(value, (int, float)):
        return datetime.fromtimestamp(value, timezone.utc)
    return datetime.fromisoformat(str(value).replace("Z", "+00:00"))
