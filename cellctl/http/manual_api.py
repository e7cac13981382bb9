"""The manual-motion routes of the HTTP API: jog, move-to, the dead-man heartbeat, stop, and the vacuum.

    GET  /manual                        the manual settings (speed cap, steps, axes, box, positions) and moves
    POST /manual/jog                    {"axis", "distance"?, "direction"?, "frame"?, "speed_pct"?}: a step, or
                                        held (no distance) until released or its heartbeat lapses
    POST /manual/move-to                {"pose": {...}} or {"position": NAME}, "speed_pct"?
    POST /manual/moves/{id}/alive       the dead-man heartbeat: send it more often than heartbeat_timeout_s
    POST /manual/moves/{id}/stop        stop that move now; POST /manual/stop: whichever is under way
    POST /gripper/grip, /gripper/release   the vacuum on or off

The routes are the service's verbs (cellctl/service/manual.py), which `cellctl jog|move-to|grip|release` call too.
Each is a command (the bearer token) for the holder of the operator lock only (X-Cellctl-Lock; else 423), checked
whole before anything moves (422 naming what and what is allowed), refused beside a job (409 naming it). A move's
progress and end are `manual` events on /events.
"""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Request
from fastapi import Path as PathParam
from pydantic import Field

from cellctl.http.contract import LOCK as Lock
from cellctl.http.contract import Body, client_of, errors
from cellctl.service import Caller

MotionId = PathParam(..., ge=1, le=2**62, description="manual move id")


class JogRequest(Body):
    axis: Literal["x", "y", "z", "rx", "ry", "rz"] = Field(..., description="x, y, z (mm) or rx, ry, rz (deg)")
    distance: float | None = Field(None, allow_inf_nan=False, description="a step (mm or deg, signed); none: held "
                                                                          "until released")
    direction: Literal[1, -1] = Field(1, description="a held jog's direction")
    frame: Literal["cell", "tool"] = Field("cell", description="the frame of the axis")
    speed_pct: float | None = Field(None, gt=0, le=100, description="% of the arm's speed; at most manual.speed_pct")


class PoseFields(Body):
    x_mm: float = Field(..., allow_inf_nan=False)
    y_mm: float = Field(..., allow_inf_nan=False)
    z_mm: float = Field(..., allow_inf_nan=False)
    alpha_deg: float = Field(0.0, ge=-360, le=360, description="the tool pointing down, turned by alpha")
    quaternion_wxyz: tuple[float, float, float, float] | None = Field(None, description="six-axis arms: w, x, y, z")


class MoveToRequest(Body):
    pose: PoseFields | None = Field(None, description="a typed pose")
    position: str | None = Field(None, max_length=64, description="or a named position (manual.positions)")
    speed_pct: float | None = Field(None, gt=0, le=100, description="% of the arm's speed; at most manual.speed_pct")


def manual_router(daemon) -> APIRouter:
    service = daemon.service
    router = APIRouter(tags=["manual"])

    def caller(request: Request, lock: str | None) -> Caller:
        request.state.audited = True  # the service audits it (a heartbeat: not at all)
        return Caller(client_of(request), lock, f"{request.method} {request.url.path}")

    @router.get("/manual", summary="the manual-motion settings (speed cap, steps, axes, box, named positions), the "
                                   "move under way and the last one")
    def manual():
        return service.manual()

    @router.post("/manual/jog", summary="jog: a step, or held (no distance) until released or its heartbeat lapses",
                 responses=errors(409))
    def jog(request: Request, body: JogRequest, lock: str | None = Lock):
        return service.jog(caller(request, lock), body.axis, body.distance, body.direction, body.frame,
                           body.speed_pct)

    @router.post("/manual/move-to", summary="move in a straight line to a typed pose or a named position",
                 responses=errors(404, 409))
    def move_to(request: Request, body: MoveToRequest, lock: str | None = Lock):
        pose = body.pose.model_dump(exclude_none=True) if body.pose is not None else None
        return service.move_to(caller(request, lock), pose, body.position, body.speed_pct)

    @router.post("/manual/moves/{motion_id}/alive", summary="the dead-man heartbeat of a manual move",
                 responses=errors(404))
    def alive(request: Request, motion_id: int = MotionId, lock: str | None = Lock):
        return service.manual_alive(caller(request, lock), motion_id)

    @router.post("/manual/moves/{motion_id}/stop", summary="stop this manual move now", responses=errors(404))
    def stop(request: Request, motion_id: int = MotionId, lock: str | None = Lock):
        return service.manual_stop(caller(request, lock), motion_id)

    @router.post("/manual/stop", summary="stop the manual move under way now")
    def stop_any(request: Request, lock: str | None = Lock):
        return service.manual_stop(caller(request, lock))

    @router.post("/gripper/grip", summary="vacuum on (by hand)", responses=errors(404, 409))
    def grip(request: Request, lock: str | None = Lock):
        return service.vacuum(caller(request, lock), True)

    @router.post("/gripper/release", summary="vacuum off (by hand)", responses=errors(404, 409))
    def release(request: Request, lock: str | None = Lock):
        return service.vacuum(caller(request, lock), False)

    return router
