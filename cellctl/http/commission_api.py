"""The device self-test's route of the HTTP API.

    POST /cell/commission     {"device": NAME or null, "move": false}: check each device (or the one named), in
                              order: link, readings, (with move) the arm's 5 mm move and back that the cameras
                              report, a grip with nothing held, each camera's focus and exposure

The route is the service's `commission` verb (cellctl/service/commission.py), which `cellctl commission` calls
too. A command (the bearer token; 423 while another client holds the operator lock), audited; with "move": true
for the holder of the operator lock only (X-Cellctl-Lock; 423 when nobody holds it). Refused (409 naming the job)
while a job runs or holds the cell; an unknown device is 404 naming the devices. The answer is the table of
checks, each {device, check, result (ok, problem, skipped, info), figure, finding}, with the number of problems.
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from pydantic import Field, StrictBool

from cellctl.http.contract import LOCK as Lock
from cellctl.http.contract import Body, client_of, errors
from cellctl.service import Caller


class CommissionRequest(Body):
    device: str | None = Field(None, max_length=64, description="one device by name; default: every device")
    move: StrictBool = Field(False, description="the operator confirmed the arm's 5 mm move and back (else the "
                                                "motion check is skipped)")


def commission_router(daemon) -> APIRouter:
    service = daemon.service
    router = APIRouter(tags=["commission"])

    @router.post("/cell/commission", responses=errors(404, 409),
                 summary="the device self-test: each device's link, readings, motion (confirmed), grip, focus, "
                         "exposure, each finding with its fix")
    def commission(request: Request, body: CommissionRequest | None = None, lock: str | None = Lock):
        request.state.audited = True  # the service audits it from here on
        body = body or CommissionRequest()
        return service.commission(Caller(client_of(request), lock, f"{request.method} {request.url.path}"),
                                  body.device, body.move)

    return router
