"""The HTTP API (FastAPI; schema at /openapi.json).

Reading is open to anyone who can reach the socket (127.0.0.1 by default).
Everything else (POST, DELETE) needs `Authorization: Bearer <token>`: missing ->
401, wrong -> 403, checked before the request is even parsed. While a client holds
the operator lock, commands from others (without its `X-Cellctl-Lock`) get 423.
Malformed input gets 422 naming the field and what is allowed; a request on a job
whose state does not allow it gets 409 and changes nothing. Every command, accepted
or refused, is in the audit log with who sent it (`X-Cellctl-Client`) and from where.
The web console (static files in console/) is served at /console/; / redirects there.
"""

from __future__ import annotations

import asyncio
import json
import math
import re
import time
from pathlib import Path
from typing import Any, Literal

from fastapi import FastAPI, Header, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import (
    FileResponse,
    JSONResponse,
    PlainTextResponse,
    RedirectResponse,
    Response,
    StreamingResponse,
)
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field, StrictBool, field_validator

from calibration.routines import ROUTINES, routine_class

from ..calstore import CalibrationStoreError
from ..runs import SEQUENCES, ParamError, routine_params
from . import overlay
from .auth import LockHeld, token_matches
from .contract import PNG, MethodGate, body, errors, install
from .events import sse
from .jobs import STATES, JobError
from .operator_api import operator_router

JobId = PathParam(..., ge=1, le=2**62, description="job id")
CalId = PathParam(..., ge=1, le=2**62, description="calibration id")
CLIENT_RE = re.compile(r"^[\w.@:+-]{1,64}$")
EVENT_ID_PATTERN = r"^[0-9]*$"  # Last-Event-ID: ASCII digits only
CONSOLE_DIR = Path(__file__).with_name("console")


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)  # strict: false is not a seed, "1" not a number


RoutineName = Literal[tuple(sorted(ROUTINES) + sorted(SEQUENCES))]  # type: ignore[valid-type]


class JobSubmit(_Body):
    routine: RoutineName = Field(..., description="a routine or a sequence (GET /routines: their parameters)")
    params: dict[str, Any] = Field(default_factory=dict, description="routine parameters over the cell file's")
    seed: int | None = Field(None, ge=0, le=2**32 - 1, description="simulation seed (simulated cells only)")
    save_images: StrictBool = Field(False, description="keep every camera frame of the job as PNG under its run "
                                                       "folder's images/")

    @field_validator("params")
    @classmethod
    def _finite(cls, params: dict[str, Any]) -> dict[str, Any]:
        """JSON as Python reads it accepts NaN, Infinity (and 1e999): no routine parameter may be one."""
        bad = _non_finite(params, "params")
        if bad:
            raise ValueError(f"{bad}: must be a finite number (NaN and Infinity are not allowed)")
        return params


def _non_finite(value: Any, where: str) -> str | None:
    """The path of the first non-finite float in `value` (dicts and lists walked), else None."""
    if isinstance(value, float):
        return None if math.isfinite(value) else where
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _non_finite(item, f"{where}.{key}")
        if found:
            return found
    return None


class PauseRequest(_Body):
    mode: Literal["deferred", "immediate"] = Field(
        "deferred", description="deferred: at the next step boundary; immediate: stop the arm now")


class LockRequest(_Body):
    holder: str = Field(..., min_length=1, max_length=64, description="who takes the lock (shown to others)")
    ttl_s: float = Field(300.0, gt=0, le=86400, description="seconds until the lock lapses unless renewed")


class ReconnectRequest(_Body):
    device: str | None = Field(None, max_length=64, description="one device by name; default: all")


def create_app(daemon) -> FastAPI:
    app = FastAPI(title="cellctl daemon", version="1",
                  description="Runs calibration routines on one cell. See the module docstring of cellctl.daemon.api.")
    install(app)  # the schema completed with what every command and every route with parameters answers
    gate = MethodGate(app)

    def who(request: Request) -> tuple[str, str]:
        client = request.headers.get("x-cellctl-client", "anonymous")
        if not CLIENT_RE.match(client):
            client = "invalid-client-name"
        host = request.client.host if request.client else "?"
        return client, f"{host}"

    # -- token before anything else; audit every command -----------------------------------------------

    @app.middleware("http")
    async def guard(request: Request, call_next):
        answered = gate.answer(request)  # OPTIONS, or a method the path does not have: before the token
        if answered is not None:
            return answered
        if request.method in ("GET", "HEAD", "OPTIONS"):
            return await call_next(request)
        client, host = who(request)
        auth = request.headers.get("authorization", "")
        scheme, _, given = auth.partition(" ")
        if not auth:
            response = JSONResponse({"detail": "this request changes the cell: send Authorization: Bearer <token> "
                                               "(cellctl token prints it)"}, status_code=401,
                                    headers={"WWW-Authenticate": "Bearer"})
        elif scheme.lower() != "bearer" or not token_matches(given.strip(), daemon.token):
            response = JSONResponse({"detail": "wrong token"}, status_code=403)
        else:
            response = await call_next(request)
        detail = getattr(request.state, "audit_detail", "")
        outcome = "ok" if response.status_code < 400 else f"refused {response.status_code}"
        await asyncio.to_thread(daemon.jobs.audit, "token" if response.status_code not in (401, 403) else "-",
                                f"{client}@{host}", f"{request.method} {request.url.path}",
                                getattr(request.state, "audit_target", ""), detail, outcome)
        return response

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError):
        problems = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err.get("loc", ()))
            msg = "unknown field" if err.get("type") == "extra_forbidden" else err.get("msg", "invalid")
            problems.append({"field": loc, "problem": msg})
        message = "; ".join(f"{p['field']}: {p['problem']}" for p in problems)
        return JSONResponse({"detail": message, "problems": problems}, status_code=422)

    @app.exception_handler(JobError)
    async def job_error(request: Request, exc: JobError):
        return JSONResponse({"detail": str(exc)}, status_code=exc.status)

    @app.exception_handler(LockHeld)
    async def lock_held(request: Request, exc: LockHeld):
        return JSONResponse({"detail": str(exc), "lock": daemon.lock.status()}, status_code=423)

    Lock = Header(None, alias="X-Cellctl-Lock", max_length=128, description="the operator lock id, if you hold it")

    def commander(request: Request, lock: str | None) -> str:
        """First in every command, after FastAPI has checked the request (a malformed one gets 422 even while
        someone else holds the lock): the operator lock allows this client; returns who it is."""
        daemon.lock.check(lock)
        client, host = who(request)
        return f"{client}@{host}"

    def note(request: Request, target: str, detail: Any = "") -> None:
        request.state.audit_target = target
        request.state.audit_detail = detail if isinstance(detail, str) else json.dumps(detail, default=str)

    # -- cell -------------------------------------------------------------------------------------

    @app.get("/health", summary="liveness")
    def health():
        return {"ok": True, "uptime_s": round(time.time() - daemon.started, 1)}

    def _idle_pose():
        with daemon.worker.guard:
            if daemon.worker.busy:
                return daemon.cells.last_pose
            with daemon.cells.mutex:
                return daemon.cells.read_pose()

    @app.get("/cell", summary="the cell, its devices' states, the arm's reported pose, the live job, the lock")
    async def cell_status():
        current = daemon.worker.current
        if current is None:  # idle: ask the arm (never beside a job: drivers are used from one thread at a time)
            pose = await asyncio.to_thread(_idle_pose)
        else:
            pose = daemon.cells.last_pose  # as the worker last read it, with its time
        return {"cell": daemon.config.cell.name, "simulated": daemon.cells.simulated,
                "devices": daemon.cells.status(), "arm_pose": pose,
                "job": current[0] if current else None, "lock": daemon.lock.status(),
                "cameras": sorted(daemon.config.cameras), "store": str(daemon.store_dir)}

    @app.post("/cell/reconnect", summary="reconnect the devices (all, or one); refused while a job is live",
              responses=errors(409))
    def reconnect(request: Request, body: ReconnectRequest | None = None, lock: str | None = Lock):
        commander(request, lock)
        body = body or ReconnectRequest()
        names = [name for _, name, _ in daemon.cells.named_devices()]
        note(request, body.device or "all", {})
        if body.device is not None and body.device not in names:
            raise HTTPException(422, f"device: {body.device!r} is not a device of this cell (devices: {', '.join(names)})")
        with daemon.worker.guard:
            if daemon.worker.busy:
                raise HTTPException(409, f"job {daemon.worker.current[0]} is live; pause or abort it and wait "
                                         "until it has stopped before reconnecting")
            errors = daemon.cells.connect_all(body.device)
        return {"devices": daemon.cells.status(), "errors": errors}

    @app.get("/routines", summary="routines and sequences a job can run, with their parameters")
    def routines():
        out = {}
        for name in sorted(ROUTINES):
            cls = routine_class(name)
            out[name] = {"params": cls.Params.model_json_schema(), "defaults": daemon.config.routines.get(name, {})}
        return {"routines": out, "sequences": {k: list(v) for k, v in SEQUENCES.items()}}

    # -- lock -------------------------------------------------------------------------------------

    @app.get("/lock", summary="who holds the operator lock")
    def lock_status():
        return daemon.lock.status()

    @app.post("/lock", summary="take (or with your X-Cellctl-Lock, renew) the operator lock")
    def lock_acquire(request: Request, body: LockRequest, x_cellctl_lock: str | None = Header(None, max_length=128)):
        note(request, "lock", {"holder": body.holder, "ttl_s": body.ttl_s})
        info = daemon.lock.acquire(body.holder, body.ttl_s, x_cellctl_lock)
        return dict(info.public(), lock_id=info.lock_id)

    @app.delete("/lock", summary="release the operator lock (its holder only)")
    def lock_release(request: Request, x_cellctl_lock: str | None = Header(None, max_length=128)):
        note(request, "lock")
        daemon.lock.release(x_cellctl_lock)
        return daemon.lock.status()

    # -- jobs -------------------------------------------------------------------------------------

    @app.get("/jobs", summary="jobs, newest first")
    def list_jobs(state: Literal[STATES] | None = Query(None, description="only jobs in this state"),  # type: ignore[valid-type]
                  limit: int = Query(50, ge=1, le=1000)):
        return {"jobs": [j.to_dict() for j in daemon.jobs.list(state, limit)]}

    @app.post("/jobs", status_code=201, summary="submit a job: routine (or sequence) + parameters (+ seed)")
    def submit(request: Request, body: JobSubmit, lock: str | None = Lock):
        by = commander(request, lock)
        note(request, body.routine, body.model_dump())
        if body.routine not in ROUTINES and body.routine not in SEQUENCES:
            raise HTTPException(422, f"routine: {body.routine!r} is not a routine; allowed: "
                                     f"{', '.join(sorted(ROUTINES) + sorted(SEQUENCES))}")
        if body.seed is not None and not daemon.cells.simulated:
            raise HTTPException(422, "seed: applies to simulated cells only; this cell has no 'sim:' section")
        if body.routine in SEQUENCES:
            if body.params:
                raise HTTPException(422, f"params: {body.routine} is a sequence; set each routine's parameters in "
                                         "the cell file")
        else:
            try:
                routine_params(routine_class(body.routine)(), daemon.config, body.params)
            except ParamError as exc:
                raise HTTPException(422, "params: " + str(exc)) from None
        job = daemon.jobs.submit(body.routine, body.params, body.seed, by, save_images=body.save_images)
        request.state.audit_target = f"job {job.id}"
        daemon.hub.publish("state", {"job": job.id, "state": job.state, "reason": "submitted"})
        daemon.worker.wake()
        return job.to_dict()

    @app.get("/jobs/{job_id}", summary="one job with its state history (and result when done)",
             responses=errors(404))
    def show_job(job_id: int = JobId):
        job = daemon.jobs.get(job_id)
        return dict(job.to_dict(with_result=True), history=daemon.jobs.history(job_id))

    @app.post("/jobs/{job_id}/pause", summary="pause at the next step boundary, or stop the arm now",
              responses=errors(404, 409))
    def pause(request: Request, job_id: int = JobId, body: PauseRequest | None = None, lock: str | None = Lock):
        by = commander(request, lock)
        body = body or PauseRequest()
        note(request, f"job {job_id}", {"mode": body.mode})
        return daemon.worker.pause(job_id, body.mode == "immediate", by).to_dict()

    @app.post("/jobs/{job_id}/resume", summary="resume a paused (and, if it faulted, acknowledged) job",
              responses=errors(404, 409))
    def resume(request: Request, job_id: int = JobId, lock: str | None = Lock):
        by = commander(request, lock)
        note(request, f"job {job_id}")
        return daemon.worker.resume(job_id, by).to_dict()

    @app.post("/jobs/{job_id}/ack", summary="acknowledge a faulted job (it becomes paused; nothing moves)",
              responses=errors(404, 409))
    def acknowledge(request: Request, job_id: int = JobId, lock: str | None = Lock):
        by = commander(request, lock)
        note(request, f"job {job_id}")
        return daemon.worker.acknowledge(job_id, by).to_dict()

    @app.post("/jobs/{job_id}/abort", summary="abort: the arm stops, the samples are kept",
              responses=errors(404, 409))
    def abort(request: Request, job_id: int = JobId, lock: str | None = Lock):
        by = commander(request, lock)
        note(request, f"job {job_id}")
        return daemon.worker.abort(job_id, by).to_dict()

    def job_file(job_id: int, name: str, item: str | None) -> Path:
        job = daemon.jobs.get(job_id)
        folder = Path(job.run_dir)
        if item is not None:
            items = SEQUENCES.get(job.routine, ())
            if item not in items:
                raise HTTPException(404, f"item: {item!r} is not part of job {job_id} "
                                         f"(its items: {', '.join(items) or 'none: not a sequence'})")
            folder = folder / f"{items.index(item) + 1:02d}-{item.replace('.', '-')}"
        path = folder / name
        if not path.is_file():
            raise HTTPException(404, f"job {job_id} has no {name} yet (state {job.state})")
        return path

    ItemQuery = Query(None, max_length=64, description="for a sequence: which routine of it")

    @app.get("/jobs/{job_id}/result", summary="result.json of a job (a sequence: its summary, or one item's)",
             responses=errors(404))
    def job_result(job_id: int = JobId, item: str | None = ItemQuery):
        return JSONResponse(json.loads(job_file(job_id, "result.json", item).read_text()))

    @app.get("/jobs/{job_id}/report", summary="report.md", response_class=Response,
             responses={**body("text/markdown", "the report (Markdown)", {"type": "string"}), **errors(404)})
    def job_report(job_id: int = JobId, item: str | None = ItemQuery):
        return PlainTextResponse(job_file(job_id, "report.md", item).read_text(), media_type="text/markdown")

    @app.get("/jobs/{job_id}/plot", summary="the residual plot (PNG)", response_class=Response,
             responses={**PNG, **errors(404)})
    def job_plot(job_id: int = JobId, item: str | None = ItemQuery):
        result = json.loads(job_file(job_id, "result.json", item).read_text())
        name = (result.get("files") or {}).get("plot")
        if not name:
            raise HTTPException(404, f"job {job_id} has no plot")
        return FileResponse(job_file(job_id, name, item), media_type="image/png")

    @app.get("/jobs/{job_id}/samples", summary="every persisted sample (CSV)", response_class=Response,
             responses={**body("text/csv", "one row per sample, with a header row", {"type": "string"}),
                        **errors(404)})
    def job_samples(job_id: int = JobId, item: str | None = ItemQuery):
        return PlainTextResponse(job_file(job_id, "samples.csv", item).read_text(), media_type="text/csv")

    # -- calibrations -------------------------------------------------------------------------

    def calibration(cal_id: int):
        try:
            return daemon.calstore.get(cal_id)
        except CalibrationStoreError as exc:
            raise HTTPException(404, str(exc)) from None

    def cal_summary(c) -> dict:
        return {"id": c.id, "target": c.target, "routine": c.routine, "version": c.version, "created": c.created,
                "active": c.active, "cell": c.cell, "stats": c.result.get("stats", {})}

    @app.get("/calibrations", summary="every calibration version")
    def list_calibrations(target: str | None = Query(None, max_length=64)):
        return {"calibrations": [cal_summary(c) for c in daemon.calstore.list(target)]}

    @app.get("/calibrations/{cal_id}", summary="one calibration with its model", responses=errors(404))
    def show_calibration(cal_id: int = CalId):
        c = calibration(cal_id)
        return dict(cal_summary(c), model=c.model, run_dir=c.run_dir)

    @app.post("/calibrations/{cal_id}/activate", summary="make this version the active one of its target",
              responses=errors(404, 409))
    def activate(request: Request, cal_id: int = CalId, lock: str | None = Lock):
        commander(request, lock)
        note(request, f"calibration {cal_id}")
        calibration(cal_id)
        with daemon.worker.guard:
            if daemon.worker.busy:
                raise HTTPException(409, "a job is live; it reads the active calibrations: activate when it is done")
            return cal_summary(daemon.calstore.activate(cal_id))

    # the YAML has no schema here: it is OpenCV's FileStorage (its !!opencv-matrix tags are not plain YAML)
    @app.get("/calibrations/{cal_id}/export", summary="export as JSON or as OpenCV FileStorage YAML",
             responses={200: {"description": "format=json: JSON; format=opencv: OpenCV FileStorage YAML",
                              "content": {"application/json": {"schema": {"type": "object"}}, "application/x-yaml": {}}},
                        **errors(404)})
    def export(cal_id: int = CalId, format: Literal["json", "opencv"] = Query("json")):
        c = calibration(cal_id)
        doc = {"id": c.id, "target": c.target, "routine": c.routine, "version": c.version, "created": c.created,
               "cell": c.cell, "model": c.model}
        if format == "json":
            return Response(json.dumps(doc, indent=2, allow_nan=False, default=str), media_type="application/json",
                            headers={"Content-Disposition": f'attachment; filename="calibration-{c.id}.json"'})
        return Response(opencv_yaml(doc), media_type="application/x-yaml",
                        headers={"Content-Disposition": f'attachment; filename="calibration-{c.id}.yaml"'})

    # -- cameras ----------------------------------------------------------------------------------

    def latest_frame(name: str):
        """(time, frame): a new capture when the cell is idle, else the live job's latest frame."""
        if name not in daemon.config.cameras:
            raise HTTPException(404, f"no camera {name!r}; cameras: {', '.join(sorted(daemon.config.cameras))}")
        with daemon.worker.guard:  # held: no job starts while we capture
            seen = daemon.worker.frames.get(name)
            if daemon.worker.busy or daemon.cells.not_ready():
                # a live job owns the cell: never capture beside it (in simulation that would change its world)
                if seen is None:
                    raise HTTPException(404, f"camera {name} has taken no frame in this job yet")
                return seen
            with daemon.cells.mutex:
                frame = daemon.cells.cell.cameras[name].capture()
            seen = daemon.worker.frames[name] = (time.time(), frame)
            return seen

    def frame_headers(stamp: float, frame) -> dict:
        return {"X-Frame-Id": str(frame.frame_id), "X-Captured": f"{stamp:.3f}"}

    @app.get("/cameras/{name}/frame.png", summary="the latest frame of a camera (PNG)", response_class=Response,
             responses={**PNG, **errors(404)})
    def camera_frame(name: str = PathParam(..., max_length=64)):
        import cv2

        stamp, frame = latest_frame(name)
        ok, png = cv2.imencode(".png", frame.image)
        if not ok:
            raise HTTPException(500, "could not encode the frame")
        return Response(png.tobytes(), media_type="image/png", headers=frame_headers(stamp, frame))

    @app.get("/cameras/{name}/overlay.png", response_class=Response, responses={**PNG, **errors(404)},
             summary="the latest frame with an overlay: the latest step's features, the active calibration's "
                     "grid, its verification residuals (PNG)")
    def camera_overlay(name: str = PathParam(..., max_length=64),
                       layers: list[Literal[overlay.LAYERS]] = Query([], max_length=3,  # type: ignore[valid-type]
                                                                     description="what to draw (repeat the key)"),
                       width: int | None = Query(None, ge=64, le=10000, description="scale down to this width")):
        stamp, frame = latest_frame(name)
        data = overlay.gather(daemon, name, set(layers))
        png = overlay.encode_png(overlay.render(frame.image, data, width))
        return Response(png, media_type="image/png", headers=frame_headers(stamp, frame))

    # -- events and logs ---------------------------------------------------------------------------

    @app.get("/events", summary="server-sent events: job state changes and progress", response_class=Response,
             responses=body("text/event-stream", "never ends: `id`, `event` (state, progress, operator), `data` "
                                                 "(JSON) per event, and a comment line as keep-alive"))
    async def events(request: Request, job: int | None = Query(None, ge=1, le=2**62),
                     since: int | None = Query(None, ge=0, le=2**62, description="replay events after this id"),
                     last_event_id: str | None = Header(None, max_length=19, pattern=EVENT_ID_PATTERN,
                                                        description="resume after this event id (EventSource)")):
        # validated as ASCII digits ("²".isdigit() is True but int("²") raises); empty means "from now"
        start = since if since is not None else (int(last_event_id) if last_event_id else daemon.hub.last_seq)

        async def stream():
            seq = start
            yield ": cellctl events\n\n"
            while not await request.is_disconnected():
                batch = daemon.hub.since(seq)
                for n, kind, data in batch:
                    seq = n
                    if job is None or data.get("job") == job:
                        yield sse(n, kind, data)
                if not batch:
                    before = daemon.hub.last_seq
                    await daemon.hub.wait(10.0)
                    if daemon.hub.last_seq == before:
                        yield ": keep-alive\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    @app.get("/audit", summary="the audit log of operator commands (oldest first)")
    def audit(limit: int = Query(200, ge=1, le=10000)):
        return {"audit": daemon.jobs.audit_log(limit)}

    # -- the web console: static files, no build step, nothing fetched from elsewhere ---------------

    @app.get("/", include_in_schema=False)
    def root():
        return RedirectResponse("/console/")

    app.include_router(operator_router(daemon))  # /operator: what the web operator waits for
    app.mount("/console", StaticFiles(directory=CONSOLE_DIR, html=True), name="console")

    return app


# -- OpenCV FileStorage export -------------------------------------------------------------------


def _fs_key(key: str) -> str:
    """FileStorage keys: a letter first, then letters, digits, underscores."""
    key = re.sub(r"\W", "_", str(key))
    return key if key[:1].isalpha() else f"k_{key}"


def opencv_yaml(doc: dict) -> str:
    """The document as an OpenCV FileStorage YAML: numeric arrays as matrices, maps as maps."""
    import cv2
    import numpy as np

    fs = cv2.FileStorage("calibration.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)

    def write(name: str | None, value) -> None:
        if isinstance(value, dict):
            fs.startWriteStruct(name or "", cv2.FileNode_MAP)
            for k, v in value.items():
                write(_fs_key(k), v)
            fs.endWriteStruct()
        elif isinstance(value, (list, tuple)):
            arr = None
            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                pass
            if arr is not None and arr.ndim in (1, 2) and arr.size and np.all(np.isfinite(arr)):
                fs.write(name, arr.reshape(len(arr), -1) if arr.ndim == 2 else arr.reshape(1, -1))
            else:
                fs.startWriteStruct(name or "", cv2.FileNode_SEQ)
                for v in value:
                    write(None, v)
                fs.endWriteStruct()
        elif value is None:
            _write_scalar(fs, name, "")
        elif isinstance(value, bool) or isinstance(value, int) and abs(value) < 2**31:
            _write_scalar(fs, name, int(value))
        elif isinstance(value, (int, float)):  # FileStorage ints are 32-bit: larger ones go as reals
            _write_scalar(fs, name, float(value))
        else:
            _write_scalar(fs, name, str(value))

    for key, value in doc.items():
        write(_fs_key(key), value)
    return fs.releaseAndGetString()


def _write_scalar(fs, name: str | None, value) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        value = str(value)
    fs.write(name if name is not None else "", value)
