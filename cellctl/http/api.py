"""The HTTP API (FastAPI; schema at /openapi.json).

Reading is open to anyone who can reach the socket (127.0.0.1 by default; beyond loopback only
over HTTPS: tls.py), /metrics too (Prometheus's text format: metrics.py).
Everything else (POST, DELETE) needs `Authorization: Bearer <token>`: missing (or
without the `Bearer` scheme) -> 401, wrong -> 403, checked before the request is even parsed. Malformed input gets
422 naming the field and what is allowed; then, while a client holds the operator
lock, commands from others (without its `X-Cellctl-Lock`) get 423 (as does one presenting a lock
id someone broke: POST /lock/break, saying who and why); a request on a job
whose state does not allow it gets 409 and changes nothing. The schema documents each
of these answers per route, with its error body (contract.py); OPTIONS answers a path's
methods in `Allow`, and a method the path does not have gets 405. Every command, accepted
or refused, is in the audit log with who sent it (`X-Cellctl-Client`) and from where.
The web console (static files in console/) is served at /console/; / redirects there. A cell in a fleet
(`fleet.postgres` in its cell file) also serves the fleet page, read from the plant database, at /fleet/.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any, Literal

from fastapi import FastAPI, Header, Query, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from pydantic import Field, StrictBool

from calibration.routines import runnable_names

from cellctl.core.events import sse
from cellctl.errors import InvalidRequest, LockHeld, ServiceError
from cellctl.http import metrics, overlay
from cellctl.http.camera_api import camera_router
from cellctl.http.commission_api import commission_router
from cellctl.http.contract import LOCK as Lock
from cellctl.http.contract import PNG, Body, MethodGate, body, client_of, errors, install
from cellctl.http.manual_api import manual_router
from cellctl.http.operator_api import operator_router
from cellctl.http.store_api import store_router
from cellctl.service import Blob, Caller
from cellctl.service.auth import MAX_LOCK_TTL_S, LockBroken, token_matches
from cellctl.service.interface import ExportFormat
from cellctl.service.local import MAX_SEED, frame_headers
from cellctl.stores.jobs import STATES

JobId = PathParam(..., ge=1, le=2**62, description="job id")
CalId = PathParam(..., ge=1, le=2**62, description="calibration id")
EVENT_ID_PATTERN = r"^[0-9]*$"  # Last-Event-ID: ASCII digits only
CONSOLE_DIR = Path(__file__).parents[1] / "console"  # the web console's static files, a front end of its own


RoutineName = Literal[runnable_names()]  # type: ignore[valid-type]


class JobSubmit(Body):
    routine: RoutineName = Field(..., description="a routine or a sequence (GET /routines: their parameters)")
    params: dict[str, Any] = Field(default_factory=dict, description="routine parameters over the cell file's")
    seed: int | None = Field(None, ge=0, le=MAX_SEED, description="simulation seed (simulated cells only)")
    save_images: StrictBool = Field(False, description="keep every camera frame of the job as PNG under its run "
                                                       "folder's images/")


class PauseRequest(Body):
    mode: Literal["deferred", "immediate"] = Field(
        "deferred", description="deferred: at the next step boundary; immediate: stop the arm now")


class LockRequest(Body):
    holder: str = Field(..., min_length=1, max_length=64, description="who takes the lock (shown to others)")
    ttl_s: float = Field(300.0, gt=0, le=MAX_LOCK_TTL_S, description="seconds until the lock lapses unless renewed")


class LockBreak(Body):
    reason: str = Field("", max_length=500, description="why the lock is broken (required: the holder is told, "
                                                        "and the audit keeps it)")


class ReconnectRequest(Body):
    device: str | None = Field(None, max_length=64, description="one device by name; default: all")


class TrustRequest(Body):
    thumbprint: str | None = Field(None, max_length=128, description="a rejected (or known) certificate's SHA-1 "
                                                                     "thumbprint, or its first 8+ hex digits")
    certificate_pem: str | None = Field(None, max_length=65536, description="or the certificate itself (PEM)")


def create_app(daemon) -> FastAPI:
    app = FastAPI(title="cellctl daemon", version="1",
                  description="Runs calibration routines on one cell. See the module docstring of cellctl.http.api.")
    install(app)  # the schema completed with what every command and every route with parameters answers
    gate = MethodGate(app)
    service = daemon.service

    def caller(request: Request, lock: str | None) -> Caller:
        """The command's caller for the service, which audits it from here on (so the middleware does not)."""
        request.state.audited = True
        return Caller(client_of(request), lock, f"{request.method} {request.url.path}")

    # -- the token before anything else; audit what never reached the service -------------------

    @app.middleware("http")
    async def guard(request: Request, call_next):
        answered = gate.answer(request)  # OPTIONS, or a method the path does not have: before the token
        if answered is not None:
            return answered
        if request.method in ("GET", "HEAD", "OPTIONS"):
            return await call_next(request)
        auth = request.headers.get("authorization", "")
        scheme, _, given = auth.partition(" ")
        if not auth:
            response = JSONResponse({"detail": "this request changes the cell: send Authorization: Bearer <token> "
                                               "(cellctl token prints it)"}, status_code=401,
                                    headers={"WWW-Authenticate": "Bearer"})
        elif scheme.lower() != "bearer" or not given.strip():  # e.g. the bare token: say the form, not "wrong"
            missing = "no token after Bearer" if scheme.lower() == "bearer" else "the header has no Bearer scheme"
            response = JSONResponse({"detail": f"Authorization: Bearer TOKEN expected ({missing}); cellctl token "
                                               "prints the token"}, status_code=401,
                                    headers={"WWW-Authenticate": "Bearer"})
        elif not token_matches(given.strip(), daemon.token):
            response = JSONResponse({"detail": "wrong token"}, status_code=403)
        else:
            response = await call_next(request)
        if not getattr(request.state, "audited", False):  # refused before the service saw it (token, malformed)
            outcome = "ok" if response.status_code < 400 else f"refused {response.status_code}"
            await asyncio.to_thread(daemon.jobs.audit, "token" if response.status_code not in (401, 403) else "-",
                                    client_of(request), f"{request.method} {request.url.path}",
                                    getattr(request.state, "audit_target", ""),
                                    getattr(request.state, "audit_detail", ""), outcome)
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

    @app.exception_handler(ServiceError)
    async def refused(request: Request, exc: ServiceError):
        body: dict[str, Any] = {"detail": str(exc)}
        if exc.problems:
            body["problems"] = exc.problems
        if isinstance(exc, LockHeld):
            body["lock"] = daemon.lock.status()
        if isinstance(exc, LockBroken):  # the console tells its operator, and does not take the lock back
            body["broken"] = exc.broken.public()
        return JSONResponse(body, status_code=exc.status)

    def blob(b: Blob) -> Response:
        return Response(b.data, media_type=b.media_type, headers=b.headers)

    # -- cell -------------------------------------------------------------------------------------

    @app.get("/health", summary="liveness")
    def health():
        return {"ok": True, "uptime_s": round(time.monotonic() - daemon.started, 1)}

    @app.get("/cell", summary="the cell, its devices' states, the arm's reported pose, the live job, the lock")
    async def cell_status():
        return await asyncio.to_thread(service.status)

    @app.post("/cell/reconnect", summary="reconnect the devices (all, or one); refused while a job is live",
              responses=errors(409))
    def reconnect(request: Request, body: ReconnectRequest | None = None, lock: str | None = Lock):
        return service.reconnect(caller(request, lock), (body or ReconnectRequest()).device)

    @app.get("/routines", summary="routines and sequences a job can run, with their parameters")
    def routines():
        return service.routines()

    # -- lock -------------------------------------------------------------------------------------

    @app.get("/lock", summary="who holds the operator lock")
    def lock_status():
        return service.lock_status()

    @app.post("/lock", summary="take (or with your X-Cellctl-Lock, renew) the operator lock")
    def lock_acquire(request: Request, body: LockRequest, lock: str | None = Lock):
        return service.acquire_lock(caller(request, lock), body.holder, body.ttl_s)

    @app.delete("/lock", summary="release the operator lock (its holder only)")
    def lock_release(request: Request, lock: str | None = Lock):
        return service.release_lock(caller(request, lock))

    @app.post("/lock/break", summary="break a stale operator lock, whoever holds it, with a reason (audited; the "
              "holder is told)", responses=errors(409))
    def lock_break(request: Request, body: LockBreak | None = None, lock: str | None = Lock):
        return service.break_lock(caller(request, lock), (body or LockBreak()).reason)

    # -- the OPC UA server's client certificates ---------------------------------------------------

    @app.get("/opcua/certificates", summary="the OPC UA client certificates trusted on secure channels, and those "
             "refused there (kept in the store's opcua/rejected/)")
    def opcua_certificates():
        return service.opcua_certificates()

    @app.post("/opcua/certificates/trust", summary="trust an OPC UA client certificate from its next session on: a "
              "rejected one by thumbprint, or one given as PEM (audited)", responses=errors(404))
    def opcua_trust(request: Request, body: TrustRequest, lock: str | None = Lock):
        pem = body.certificate_pem.encode() if body.certificate_pem is not None else None
        return service.trust_opcua_certificate(caller(request, lock), body.thumbprint, pem)

    # -- jobs -------------------------------------------------------------------------------------

    @app.get("/jobs", summary="jobs, newest first")
    def list_jobs(state: Literal[STATES] | None = Query(None, description="only jobs in this state"),  # type: ignore[valid-type]
                  limit: int = Query(50, ge=1, le=1000)):
        return {"jobs": service.jobs(state, limit)}

    @app.get("/routines/{routine}/plan", summary="the poses a routine that plans its own motion will visit, before "
             "anything moves (read-only: no lock, no motion)", responses=errors(404))
    def plan(routine: str = PathParam(..., max_length=64),
             params: str = Query("{}", max_length=10_000, description="routine parameters over the cell file's, "
                                 'as a JSON object, e.g. {"poses": 20}')):
        try:
            values = json.loads(params)
        except ValueError as exc:
            raise InvalidRequest(f"params: not JSON ({exc}); allowed: a JSON object of parameters") from None
        if not isinstance(values, dict):
            raise InvalidRequest(f"params: {params!r}; allowed: a JSON object of parameters, e.g. {{\"poses\": 20}}")
        return service.plan(routine, values)

    @app.post("/jobs", status_code=201, summary="submit a job: routine (or sequence) + parameters (+ simulation seed)",
              responses=errors(507))
    def submit(request: Request, body: JobSubmit, lock: str | None = Lock):
        return service.submit(caller(request, lock), body.routine, body.params, body.seed, body.save_images)

    @app.get("/jobs/{job_id}", summary="one job with its state history (and result when done)",
             responses=errors(404))
    def show_job(job_id: int = JobId):
        return service.job(job_id)

    @app.post("/jobs/{job_id}/pause", summary="pause at the next step boundary, or stop the arm now",
              responses=errors(404, 409))
    def pause(request: Request, job_id: int = JobId, body: PauseRequest | None = None, lock: str | None = Lock):
        return service.pause(caller(request, lock), job_id, (body or PauseRequest()).mode == "immediate")

    @app.post("/jobs/{job_id}/resume", summary="resume a paused (and, if it faulted, acknowledged) job",
              responses=errors(404, 409, 507))
    def resume(request: Request, job_id: int = JobId, lock: str | None = Lock):
        return service.resume(caller(request, lock), job_id)

    @app.post("/jobs/{job_id}/ack", summary="acknowledge a faulted job (it becomes paused; nothing moves)",
              responses=errors(404, 409))
    def acknowledge(request: Request, job_id: int = JobId, lock: str | None = Lock):
        return service.acknowledge(caller(request, lock), job_id)

    @app.post("/jobs/{job_id}/abort", summary="abort: the arm stops, the samples are kept",
              responses=errors(404, 409))
    def abort(request: Request, job_id: int = JobId, lock: str | None = Lock):
        return service.abort(caller(request, lock), job_id)

    ItemQuery = Query(None, max_length=64, description="for a sequence: which routine of it")

    @app.get("/jobs/{job_id}/result", summary="result.json of a job (a sequence: its summary, or one item's; a "
             "sequence that did not finish: the summary of the routines that did, with complete: false)",
             responses=errors(404))
    def job_result(job_id: int = JobId, item: str | None = ItemQuery):
        return JSONResponse(service.result(job_id, item))

    @app.get("/jobs/{job_id}/report", summary="report.md", response_class=Response,
             responses={**body("text/markdown", "the report (Markdown)", {"type": "string"}), **errors(404)})
    def job_report(job_id: int = JobId, item: str | None = ItemQuery):
        return blob(service.job_file(job_id, "report.md", item))

    @app.get("/jobs/{job_id}/plot", summary="the residual plot (PNG)", response_class=Response,
             responses={**PNG, **errors(404)})
    def job_plot(job_id: int = JobId, item: str | None = ItemQuery):
        return blob(service.job_file(job_id, "plot", item))

    @app.get("/jobs/{job_id}/samples", summary="every persisted sample (CSV)", response_class=Response,
             responses={**body("text/csv", "one row per sample, with a header row", {"type": "string"}),
                        **errors(404)})
    def job_samples(job_id: int = JobId, item: str | None = ItemQuery):
        return blob(service.job_file(job_id, "samples.csv", item))

    # -- calibrations -------------------------------------------------------------------------

    @app.get("/calibrations", summary="every calibration version")
    def list_calibrations(target: str | None = Query(None, max_length=64)):
        return {"calibrations": service.calibrations(target)}

    @app.get("/calibrations/{cal_id}", summary="one calibration with its model", responses=errors(404))
    def show_calibration(cal_id: int = CalId):
        return service.calibration(cal_id)

    @app.post("/calibrations/{cal_id}/activate", summary="make this version the active one of its target",
              responses=errors(404, 409))
    def activate(request: Request, cal_id: int = CalId, lock: str | None = Lock):
        return service.activate(caller(request, lock), cal_id)

    @app.post("/calibrations/{cal_id}/deactivate", summary="take this version out of use (its target has none)",
              responses=errors(404, 409))
    def deactivate(request: Request, cal_id: int = CalId, lock: str | None = Lock):
        return service.deactivate(caller(request, lock), cal_id)

    # the YAML has no schema here: it is OpenCV's FileStorage (its !!opencv-matrix tags are not plain YAML)
    @app.get("/calibrations/{cal_id}/export", summary="export as JSON, as OpenCV FileStorage YAML, or (an arm "
             "calibration) as URDF",
             responses={200: {"description": "format=json: JSON; format=opencv: OpenCV FileStorage YAML; "
                                             "format=urdf (target arm only): the calibrated arm as URDF",
                              "content": {"application/json": {"schema": {"type": "object"}}, "application/x-yaml": {},
                                          "application/xml": {}}},
                        **errors(404, 422)})
    def export(cal_id: int = CalId, format: ExportFormat = Query("json")):
        doc = service.export(cal_id, format)
        return Response(doc.text, media_type=doc.media_type,
                        headers={"Content-Disposition": f'attachment; filename="{doc.filename}"'})

    @app.get("/health/calibrations", summary="do the calibrations hold: per target the active version, its last "
             "check, the verdict (ok, drift, unchecked), every check")
    def calibration_health():
        return service.health()

    @app.get("/locate", summary="robot x_mm, y_mm of what a camera sees at a pixel, with its 1-σ sigma_um and the "
             "calibration (id, version, health) it used; read-only", responses=errors(404))
    def locate(camera: str = Query(..., max_length=64), u_px: float = Query(..., allow_inf_nan=False),
               v_px: float = Query(..., allow_inf_nan=False),
               diameter_px: float | None = Query(None, gt=0, allow_inf_nan=False, description="a sphere's apparent "
                                                 "diameter, for a calibration that corrects sphere heights"),
               arm_x_mm: float | None = Query(None, allow_inf_nan=False, description="the arm's reported pose, "
                                              "for a camera that rides on it (all three or none)"),
               arm_y_mm: float | None = Query(None, allow_inf_nan=False),
               arm_alpha_deg: float | None = Query(None, allow_inf_nan=False),
               z_mm: float | None = Query(None, allow_inf_nan=False, description="a hand-eye camera: the height "
                                          "of the plane to locate on (base frame; default: the board's plane)"),
               flange: str | None = Query(None, max_length=400, description="a wrist camera (hand-eye): the flange "
                                          "pose x_mm,y_mm,z_mm,qw,qx,qy,qz (default: the arm's pose now)")):
        pose = (arm_x_mm, arm_y_mm, arm_alpha_deg)
        if any(v is not None for v in pose) and any(v is None for v in pose):
            raise InvalidRequest("arm_x_mm, arm_y_mm, arm_alpha_deg: give all three or none")
        values = None
        if flange is not None:
            try:
                values = tuple(float(v) for v in flange.split(","))
            except ValueError:
                raise InvalidRequest(f"flange: {flange!r}; allowed: seven numbers x_mm,y_mm,z_mm,qw,qx,qy,qz "
                                     "separated by commas") from None
        return service.locate(camera, u_px, v_px, pose if pose[0] is not None else None, diameter_px, z_mm, values)

    # -- cameras ----------------------------------------------------------------------------------

    @app.get("/cameras/{name}/frame.png", summary="the latest frame of a camera (PNG)", response_class=Response,
             responses={**PNG, **errors(404)})
    def camera_frame(name: str = PathParam(..., max_length=64)):
        return blob(service.frame(name))

    @app.get("/cameras/{name}/features", responses=errors(404),
             summary="what a camera sees now: each feature (nozzle, sphere) with its pixel, robot position, sigma_um "
                     "and apparent diameter")
    def camera_features(name: str = PathParam(..., max_length=64)):
        return service.features(name)

    @app.get("/cameras/{name}/overlay.png", response_class=Response, responses={**PNG, **errors(404)},
             summary="the latest frame with an overlay: the latest step's features, the active calibration's "
                     "grid, its verification residuals (PNG)")
    def camera_overlay(name: str = PathParam(..., max_length=64),
                       layers: list[Literal[overlay.LAYERS]] = Query([], max_length=3,  # type: ignore[valid-type]
                                                                     description="what to draw (repeat the key)"),
                       width: int | None = Query(None, ge=64, le=10000, description="scale down to this width")):
        stamp, frame = service.latest_frame(name)
        data = overlay.gather(daemon, name, set(layers))
        png = overlay.encode_png(overlay.render(frame.image, data, width))
        return Response(png, media_type="image/png", headers=frame_headers(stamp, frame))

    # -- events and logs ---------------------------------------------------------------------------

    @app.get("/events", summary="server-sent events: job state changes and progress", response_class=Response,
             responses=body("text/event-stream", "never ends: `id`, `event` (state, progress, operator, health, "
                                                 "lock), `data` (JSON) per event, and a comment line as keep-alive"))
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
        return {"audit": service.audit(limit)}

    # -- the web console: static files, no build step, nothing fetched from elsewhere ---------------

    @app.get("/", include_in_schema=False)
    def root():
        return RedirectResponse("/console/")

    metrics.install(app, daemon)  # /metrics; after `guard`, so the requests it refuses are counted too
    app.include_router(operator_router(daemon))  # /operator: what the web operator waits for
    app.include_router(manual_router(daemon))  # /manual, /gripper: jog, move-to, the vacuum by hand
    app.include_router(camera_router(daemon))  # /cameras/{name}/live.mjpg, settings: the live camera view
    app.include_router(commission_router(daemon))  # /cell/commission: the device self-test
    app.include_router(store_router(daemon))  # /store/backup: a backup of the store now
    app.mount("/console", StaticFiles(directory=CONSOLE_DIR, html=True), name="console")
    plant = daemon.config.fleet.postgres if daemon.config.fleet is not None else None
    if plant is not None:  # the whole fleet as the plant database has it: read-only, so open like the reads here
        from cellctl.fleet import page, secrets  # psycopg: only for a cell in a fleet

        dsn = secrets.read("fleet.postgres", plant.dsn_file, plant.dsn_env, daemon.config_path.parent)
        app.include_router(page.router(page.connector(dsn)), prefix="/fleet")

    return app
