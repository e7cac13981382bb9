"""The operator routes of the HTTP API: what the web operator (drivers/operators/web.py) is waiting for.

    GET  /operator/request                     the pending request (null when none), with the backend
    GET  /operator/requests/{id}/frame.png     the frame a click request is for (?points=true: drawn over)
    POST /operator/requests/{id}/clicks        {"clicks": [{"model_index", "u", "v"}, ...]}
    POST /operator/requests/{id}/done          an instruction is done
    POST /operator/requests/{id}/decline       {"reason": "..."}: cannot do it (clicks: too few points seen)

The routes are the service's operator verbs (cellctl/service: operator_request,
operator_clicks, operator_done, operator_decline), which `cellctl operator` calls too.
Answers are commands: the bearer token (checked by api.py's middleware, as for every
POST) and the operator lock (`X-Cellctl-Lock` while someone holds it, else 423), each in
the audit log. An answer is checked whole before it is taken: a bad one gets 422 naming
each field and what is allowed, one for a request that is not pending (or of the other
kind) gets 409, and either way the request stays as it was. Each request posted and
ended is an `operator` event on /events (state waiting, answered, declined, withdrawn,
timed-out), with the live job's id; the job's progress (its record and a `progress`
event) carries `operator`: the request it waits for, or null.
"""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import Response
from pydantic import Field

from drivers.operators.web import OperatorRequest, desk_for

from cellctl.errors import InvalidRequest
from cellctl.http.contract import LOCK as Lock
from cellctl.http.contract import PNG, Body, client_of, errors
from cellctl.service import Caller

RequestId = PathParam(..., ge=1, le=2**62, description="operator request id")


class Click(Body):
    model_index: int = Field(..., ge=0, le=100_000, description="index of the model point clicked on the overlay")
    u: float = Field(..., allow_inf_nan=False, description="its image point, pixels (integer at pixel centres)")
    v: float = Field(..., allow_inf_nan=False)


class ClickAnswer(Body):
    clicks: list[Click] = Field(..., max_length=1000, description="model point / image point pairs")


class Decline(Body):
    reason: str = Field("", max_length=500, description="why it cannot be done (shown in the job's reason)")


def operator_router(daemon) -> APIRouter:
    """The routes, bound to the daemon; its event hub announces the desk's requests from now on."""
    desk = desk_for(daemon.store_dir)
    service = daemon.service

    def live_job() -> int | None:
        return daemon.worker.live_job

    def announce(state: str, data: dict) -> None:
        """An `operator` event, and the live job's progress (event and record) saying whether it waits for one."""
        job = live_job()
        event = dict(data, state=state, job=job)
        daemon.hub.publish("operator", event)
        progress = daemon.jobs.get(job).progress if job is not None else None
        if progress:  # the job has reported its steps: the same figures, with what it waits for
            progress = dict(progress, operator=event if state == "waiting" else None)
            daemon.jobs.set_progress(job, progress)
            daemon.hub.publish("progress", progress)

    desk.attach(announce)
    router = APIRouter(prefix="/operator", tags=["operator"])

    def caller(request: Request, lock: str | None) -> Caller:
        """As api.py's commands: the service checks the operator lock and audits the answer from here on.

        Called in the route, after FastAPI has checked the request: a malformed one gets 422 even while
        someone else holds the lock (a dependency would answer 423 first)."""
        request.state.audited = True
        return Caller(client_of(request), lock, f"{request.method} {request.url.path}")

    def body_fields(exc: InvalidRequest) -> InvalidRequest:
        """The service names an answer's fields (clicks.0.u); HTTP names them as its validation does (body.)."""
        problems = [dict(p, field=f"body.{p['field']}") for p in exc.problems or ()]
        return InvalidRequest("; ".join(f"{p['field']}: {p['problem']}" for p in problems) or str(exc),
                              problems or None)

    @router.get("/request", summary="the pending operator request (null when none is pending)")
    def pending():
        return service.operator_request()

    @router.get("/requests/{request_id}/frame.png", response_class=Response, responses={**PNG, **errors(404)},
                summary="the frame a click request is for (PNG); points=true draws the projected model points")
    def frame(request_id: int = RequestId, points: bool = Query(False, description="draw the model points"),
              width: int | None = Query(None, ge=64, le=10000, description="scale to this width")):
        import cv2
        import numpy as np

        req = desk.pending()
        if req is None or req.id != request_id or req.image is None:
            raise HTTPException(404, f"operator request {request_id} is not a pending click request")
        image = req.image
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
        if image.dtype != np.uint8:
            image = np.clip(image, 0, 255).astype(np.uint8)
        scale = 1.0 if width is None else width / image.shape[1]
        if width is not None:
            image = cv2.resize(image, (width, max(1, round(image.shape[0] * scale))), interpolation=cv2.INTER_AREA)
        if points:
            draw_points(image, req, scale)
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise HTTPException(500, "could not encode the frame")
        return Response(png.tobytes(), media_type="image/png",
                        headers={"X-Frame-Id": str(req.details.get("frame_id", "")), "Cache-Control": "no-store"})

    @router.post("/requests/{request_id}/clicks", summary="answer a click request with model/image point pairs",
                 responses=errors(409))
    def clicks(request: Request, body: ClickAnswer, request_id: int = RequestId, lock: str | None = Lock):
        try:
            return service.operator_clicks(caller(request, lock), request_id,
                                           [(c.model_index, c.u, c.v) for c in body.clicks])
        except InvalidRequest as exc:
            raise body_fields(exc) from None

    @router.post("/requests/{request_id}/done", summary="an instruction is done", responses=errors(409))
    def done(request: Request, request_id: int = RequestId, lock: str | None = Lock):
        return service.operator_done(caller(request, lock), request_id)

    @router.post("/requests/{request_id}/decline", summary="decline: it cannot be done (the job faults)",
                 responses=errors(409))
    def decline(request: Request, request_id: int = RequestId, body: Decline | None = None,
                lock: str | None = Lock):
        return service.operator_decline(caller(request, lock), request_id, (body or Decline()).reason)

    return router


def draw_points(image, req: OperatorRequest, scale: float = 1.0) -> None:
    """The model's edges and numbered points where the estimate projects them, in the object's colour."""
    import cv2

    colour = req.details.get("colour", "#40c8ff").lstrip("#")
    bgr = tuple(int(colour[i:i + 2], 16) for i in (4, 2, 0))
    pts = {p["index"]: (p["u"] * scale, p["v"] * scale) for p in req.details.get("model_points", ())}

    def at(k):
        u, v = pts[k]
        return round(u * 16), round(v * 16)

    for a, b in req.details.get("edges", ()):
        if a in pts and b in pts:
            cv2.line(image, at(a), at(b), bgr, 1, cv2.LINE_AA, shift=4)
    for k in pts:
        cv2.circle(image, at(k), 4 * 16, bgr, 2, cv2.LINE_AA, shift=4)
        u, v = pts[k]
        cv2.putText(image, str(k), (round(u) + 6, round(v) - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, bgr, 1, cv2.LINE_AA)
