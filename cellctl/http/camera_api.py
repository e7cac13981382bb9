"""The live camera view's routes of the HTTP API: a camera live, its exposure and gain, written back to the cell file.

    GET  /cameras/{name}/live.mjpg           the camera live (MJPEG: multipart/x-mixed-replace), while no job uses it
    GET  /cameras/{name}/live.jpg|.png       one live frame (PNG: `cellctl camera CAM --snapshot`)
    GET  /cameras/{name}/settings            exposure and gain: on the camera now, in the cell file, the ranges
    POST /cameras/{name}/settings            {"values": {"exposure_s": 0.004, ...}}: changed on the camera now
    POST /cameras/{name}/settings/save       {"confirm": false}: the cell file's diff; true: written

Why MJPEG and not frames over /events: the stream is one client's, on demand, and ends with it. A multipart
response is exactly that: each frame goes to the one client that asked for it at the rate it asked for; it ends
when the client goes away (the connection closes, the capture loop stops, the camera is left alone), and any
MJPEG viewer (a browser's <img>, VLC, curl) shows it. The event stream goes to every console and to the CLI
and the fleet, which would all carry every frame (a few hundred kB a second) and could not say when to stop.
Each part carries the frame's figures in a header (X-Live-Stats: its histogram, saturated share, mean level,
features), which the console reads by fetching the stream itself.

Each frame is a capture under `Worker.idle_cell`: a stream asked for while a job uses the camera is refused (409,
naming the job); a job that starts while a stream runs takes the cell at the next frame, and the stream then
ends with a last part (application/json, {"stopped": why, "status": 409}). The settings' writes are commands:
the bearer token, the operator lock (423), the audit; a value out of range gets 422 naming the range.
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any, Literal

from fastapi import APIRouter, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import Response, StreamingResponse
from pydantic import Field, StrictBool

from cellctl.errors import ServiceError
from cellctl.http.contract import LOCK as Lock
from cellctl.http.contract import Body, body, client_of, errors
from cellctl.service import Caller
from cellctl.service.cameras import LIVE_LAYERS

BOUNDARY = "cellctl-frame"
Camera = PathParam(..., max_length=64, description="a camera of the cell file")
LayersQuery = Query(list(LIVE_LAYERS), max_length=4, description="what to draw (repeat the key): saturation "
                    "(saturated pixels in magenta), features (found in this frame), grid (the active calibration's); "
                    "none: the frame alone")
Layer = Literal[(*LIVE_LAYERS, "none")]  # type: ignore[valid-type]
WidthQuery = Query(None, ge=64, le=10000, description="scale down to this width (px)")
LIVE_HEADERS = ("X-Frame-Id", "X-Captured", "X-Live-Stats")


class SettingsChange(Body):
    values: dict[str, Any] = Field(..., min_length=1, max_length=8, description="setting -> value, e.g. "
                                   '{"exposure_s": 0.004, "gain_db": 6}; the keys and ranges: GET .../settings')


class SettingsSave(Body):
    confirm: StrictBool = Field(False, description="false: only the diff; true: write the cell file")


def camera_router(daemon) -> APIRouter:
    service = daemon.service
    router = APIRouter(prefix="/cameras", tags=["cameras"])

    def caller(request: Request, lock: str | None) -> Caller:
        request.state.audited = True
        return Caller(client_of(request), lock, f"{request.method} {request.url.path}")

    def drawn(layers: list[str]) -> tuple[str, ...]:
        return tuple(layer for layer in layers if layer != "none")

    def one(name: str, layers: list[str], width: int | None, fmt: str) -> Response:
        blob = service.live_frame(name, drawn(layers), width, fmt)
        return Response(blob.data, media_type=blob.media_type,
                        headers=dict(blob.headers, **{"Cache-Control": "no-store"}))

    @router.get("/{name}/live.jpg", response_class=Response, summary="one live frame, drawn (JPEG); its figures in "
                "X-Live-Stats; refused while a job uses the camera",
                responses={**body("image/jpeg", "a JPEG image", {"type": "string", "format": "binary"}),
                           **errors(404, 409)})
    def live_jpeg(name: str = Camera, layers: list[Layer] = LayersQuery,  # type: ignore[valid-type]
                  width: int | None = WidthQuery):
        return one(name, layers, width, "jpeg")

    @router.get("/{name}/live.png", response_class=Response, summary="one live frame, drawn (PNG, full size unless "
                "width); its figures in X-Live-Stats; refused while a job uses the camera",
                responses={**body("image/png", "a PNG image", {"type": "string", "format": "binary"}),
                           **errors(404, 409)})
    def live_png(name: str = Camera, layers: list[Layer] = LayersQuery,  # type: ignore[valid-type]
                 width: int | None = WidthQuery):
        return one(name, layers, width, "png")

    @router.get("/{name}/live.mjpg", response_class=Response,
                summary="the camera live (MJPEG, multipart/x-mixed-replace) while no job uses it; each part's "
                        "X-Live-Stats holds its histogram and saturated share; ends when the client goes away or a "
                        "job starts",
                responses={**body(f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                                  "JPEG parts until the client leaves; a last application/json part says why it "
                                  "stopped"), **errors(404, 409)})
    async def live_stream(request: Request, name: str = Camera,
                          layers: list[Layer] = LayersQuery,  # type: ignore[valid-type]
                          width: int | None = Query(800, ge=64, le=4000, description="scale down to this width"),
                          fps: float = Query(4.0, ge=0.2, le=15, description="frames a second (at most)")):
        # the first frame before the answer: a refusal (unknown camera, a job using it) is a plain 404 / 409
        first = await asyncio.to_thread(service.live_frame, name, drawn(layers), width, "jpeg")

        def part(blob) -> bytes:
            head = [f"--{BOUNDARY}", f"Content-Type: {blob.media_type}", f"Content-Length: {len(blob.data)}"]
            head += [f"{k}: {blob.headers[k]}" for k in LIVE_HEADERS if k in blob.headers]
            return ("\r\n".join(head) + "\r\n\r\n").encode() + blob.data + b"\r\n"

        def last(why: str, status: int) -> bytes:
            data = json.dumps({"stopped": why, "status": status}).encode()
            return (f"--{BOUNDARY}\r\nContent-Type: application/json\r\nContent-Length: {len(data)}\r\n\r\n"
                    ).encode() + data + f"\r\n--{BOUNDARY}--\r\n".encode()

        async def stream():
            blob, period = first, 1.0 / fps
            while True:
                started = time.monotonic()
                yield part(blob)
                await asyncio.sleep(max(0.0, period - (time.monotonic() - started)))
                if await request.is_disconnected():
                    return  # the client went away: no more captures
                try:
                    blob = await asyncio.to_thread(service.live_frame, name, drawn(layers), width, "jpeg")
                except ServiceError as exc:  # a job took the cell (409), the camera failed (503)
                    yield last(str(exc), exc.status)
                    return

        return StreamingResponse(stream(), media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    @router.get("/{name}/settings", responses=errors(404, 409),
                summary="exposure and gain of a camera: on the camera now, in the cell file, and the ranges allowed")
    def settings(name: str = Camera):
        return service.camera_settings(name)

    @router.post("/{name}/settings", responses=errors(404, 409),
                 summary="change exposure and gain on the camera now (checked against their ranges; audited)")
    def change(request: Request, body: SettingsChange, name: str = Camera, lock: str | None = Lock):
        return service.set_camera_settings(caller(request, lock), name, body.values)

    @router.post("/{name}/settings/save", responses=errors(404, 409),
                 summary="the camera's changed settings written back to the cell file: the diff, or with confirm "
                         "the file written (atomically, only those keys' lines)")
    def save(request: Request, body: SettingsSave | None = None, name: str = Camera, lock: str | None = Lock):
        return service.save_camera_settings(caller(request, lock), name, (body or SettingsSave()).confirm)

    return router
