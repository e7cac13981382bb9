"""The cell's verbs over a daemon's HTTP API: the same `CellService`, for a CLI on another terminal or PC.

Errors come back as the same `ServiceError`s the daemon raised (by status code), so a front end
cannot tell a remote cell from a local one, except that an unreachable daemon is `Unreachable`.
"""

from __future__ import annotations

import json
import ssl
from collections.abc import Iterator

import httpx

from cellctl.errors import (
    Conflict,
    InsufficientStorage,
    InvalidRequest,
    LockHeld,
    NotFound,
    ServiceError,
    Unavailable,
    Unreachable,
)
from cellctl.service.interface import Blob, Caller, Export, ExportFormat, JobFile

BY_STATUS = {404: NotFound, 409: Conflict, 422: InvalidRequest, 400: InvalidRequest, 423: LockHeld,
             503: Unavailable, 507: InsufficientStorage}
COMMISSION_TIMEOUT_S = 300.0  # the device self-test's answer (every device's link, frames, a slow move)
FILE_PATHS = {"report.md": "report", "samples.csv": "samples", "plot": "plot"}


def _trusting(ca: str) -> ssl.SSLContext:
    try:
        return ssl.create_default_context(cafile=ca)
    except (OSError, ssl.SSLError) as exc:
        raise InvalidRequest(f"ca: {ca} is not a readable PEM certificate ({exc})") from None


class RemoteService:
    def __init__(self, url: str, token: str | None = None, timeout: float = 15.0, ca: str | None = None):
        """`ca`: a PEM certificate to trust for https:// (the daemon's own, pinned), instead of the system's CAs."""
        self.url = url.rstrip("/")
        self.http = httpx.Client(base_url=self.url, timeout=timeout, verify=_trusting(ca) if ca else True,
                                 headers={"Authorization": f"Bearer {token}"} if token else {})

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> "RemoteService":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- the wire ---------------------------------------------------------------------------

    def _request(self, method: str, path: str, caller: Caller | None = None, **kwargs) -> httpx.Response:
        headers = {}
        if caller is not None:
            headers["X-Cellctl-Client"] = caller.who
            if caller.lock:
                headers["X-Cellctl-Lock"] = caller.lock
        try:
            r = self.http.request(method, path, headers=headers, **kwargs)
        except httpx.HTTPError as exc:
            raise self._unreachable("cannot reach the daemon at", exc) from None
        if r.status_code >= 400:
            problems = None
            try:
                answer = r.json()
                detail, problems = answer.get("detail", r.text), answer.get("problems")
            except (ValueError, AttributeError):
                detail = r.text
            error = BY_STATUS.get(r.status_code, ServiceError)(f"{r.status_code}: {detail}", problems)
            error.status = r.status_code
            raise error
        return r

    def _unreachable(self, what: str, exc: httpx.HTTPError) -> Unreachable:
        if "CERTIFICATE_VERIFY_FAILED" in str(exc):  # say what to do, not only what OpenSSL saw
            return Unreachable(f"{what} {self.url}: its certificate is not trusted here ({exc}); pin the daemon's "
                               "certificate with --ca FILE or $CELLCTL_CA (it is <store>/tls/daemon.crt on the cell PC)")
        return Unreachable(f"{what} {self.url}: {exc}")

    def _get(self, path: str, **params):
        return self._request("GET", path, params={k: v for k, v in params.items() if v is not None}).json()

    def _post(self, caller: Caller, path: str, body: dict | None = None):
        return self._request("POST", path, caller, json=body).json()

    # -- the cell ---------------------------------------------------------------------------

    def status(self) -> dict:
        return self._get("/cell")

    def routines(self) -> dict:
        return self._get("/routines")

    def plan(self, routine: str, params: dict | None = None) -> dict:
        return self._get(f"/routines/{routine}/plan", params=json.dumps(params or {}))

    def reconnect(self, caller: Caller, device: str | None = None) -> dict:
        return self._post(caller, "/cell/reconnect", {"device": device})

    def frame(self, camera: str) -> Blob:
        r = self._request("GET", f"/cameras/{camera}/frame.png")
        return Blob(r.content, r.headers.get("content-type", "image/png"),
                    {k: r.headers[k] for k in ("X-Frame-Id", "X-Captured") if k in r.headers})

    # -- the live camera view -------------------------------------------------------------------

    def live_frame(self, camera: str, layers: tuple[str, ...] = ("features", "grid", "saturation"),
                   width: int | None = None, format: str = "jpeg") -> Blob:
        params = {"layers": list(layers) or ["none"], **({"width": width} if width is not None else {})}
        r = self._request("GET", f"/cameras/{camera}/live.{'png' if format == 'png' else 'jpg'}", params=params)
        return Blob(r.content, r.headers.get("content-type", "image/jpeg"),
                    {k: r.headers[k] for k in ("X-Frame-Id", "X-Captured", "X-Live-Stats") if k in r.headers})

    def camera_settings(self, camera: str) -> dict:
        return self._get(f"/cameras/{camera}/settings")

    def set_camera_settings(self, caller: Caller, camera: str, values: dict) -> dict:
        return self._post(caller, f"/cameras/{camera}/settings", {"values": values})

    def save_camera_settings(self, caller: Caller, camera: str, confirm: bool = False) -> dict:
        return self._post(caller, f"/cameras/{camera}/settings/save", {"confirm": confirm})

    # -- the device self-test --------------------------------------------------------------------

    def commission(self, caller: Caller, device: str | None = None, move: bool = False) -> dict:
        # a camera's frame and a slow move take their time on a real cell: more than one request's time-out
        return self._request("POST", "/cell/commission", caller, json={"device": device, "move": move},
                             timeout=COMMISSION_TIMEOUT_S).json()

    # -- jobs -------------------------------------------------------------------------------

    def submit(self, caller: Caller, routine: str, params: dict | None = None, seed: int | None = None,
               save_images: bool = False) -> dict:
        body = {"routine": routine, "params": params or {}}
        if seed is not None:
            body["seed"] = seed
        if save_images:  # only when asked: a daemon from before it refuses the field
            body["save_images"] = True
        return self._post(caller, "/jobs", body)

    def jobs(self, state: str | None = None, limit: int = 50) -> list[dict]:
        return self._get("/jobs", state=state, limit=limit)["jobs"]

    def job(self, job_id: int) -> dict:
        return self._get(f"/jobs/{job_id}")

    def pause(self, caller: Caller, job_id: int, immediate: bool = False) -> dict:
        return self._post(caller, f"/jobs/{job_id}/pause", {"mode": "immediate" if immediate else "deferred"})

    def resume(self, caller: Caller, job_id: int) -> dict:
        return self._post(caller, f"/jobs/{job_id}/resume")

    def acknowledge(self, caller: Caller, job_id: int) -> dict:
        return self._post(caller, f"/jobs/{job_id}/ack")

    def abort(self, caller: Caller, job_id: int) -> dict:
        return self._post(caller, f"/jobs/{job_id}/abort")

    def result(self, job_id: int, item: str | None = None) -> dict:
        return self._get(f"/jobs/{job_id}/result", item=item)

    def job_file(self, job_id: int, name: JobFile, item: str | None = None) -> Blob:
        if name == "result.json":
            return Blob(json.dumps(self.result(job_id, item)).encode(), "application/json", {})
        if name not in FILE_PATHS:
            raise InvalidRequest(f"file: {name!r}; allowed: result.json, {', '.join(FILE_PATHS)}")
        r = self._request("GET", f"/jobs/{job_id}/{FILE_PATHS[name]}", params={"item": item} if item else None)
        return Blob(r.content, r.headers.get("content-type", ""), {})

    def events(self, job: int | None = None, since: int | None = None) -> Iterator[tuple[str, dict]]:
        """(kind, data) from the daemon's server-sent event stream, as they come."""
        params = {k: v for k, v in (("job", job), ("since", since)) if v is not None}
        try:
            with self.http.stream("GET", "/events", params=params, timeout=httpx.Timeout(15.0, read=60.0)) as stream:
                kind = "message"
                for line in stream.iter_lines():
                    if line.startswith("event: "):
                        kind = line[7:]
                    elif line.startswith("data: "):
                        yield kind, json.loads(line[6:])
        except httpx.HTTPError as exc:
            raise self._unreachable("the event stream broke from", exc) from None

    # -- calibrations -------------------------------------------------------------------------

    def calibrations(self, target: str | None = None) -> list[dict]:
        return self._get("/calibrations", target=target)["calibrations"]

    def calibration(self, cal_id: int) -> dict:
        return self._get(f"/calibrations/{cal_id}")

    def activate(self, caller: Caller, cal_id: int) -> dict:
        return self._post(caller, f"/calibrations/{cal_id}/activate")

    def deactivate(self, caller: Caller, cal_id: int) -> dict:
        return self._post(caller, f"/calibrations/{cal_id}/deactivate")

    def export(self, cal_id: int, format: ExportFormat = "json") -> Export:
        r = self._request("GET", f"/calibrations/{cal_id}/export", params={"format": format})
        disposition = r.headers.get("content-disposition", "")
        filename = disposition.partition('filename="')[2].rstrip('"') or f"calibration-{cal_id}"
        return Export(r.text, r.headers.get("content-type", "").split(";")[0], filename)

    def locate(self, camera: str, u_px: float, v_px: float, arm_pose: tuple[float, float, float] | None = None,
               diameter_px: float | None = None, z_mm: float | None = None,
               flange: tuple[float, ...] | None = None) -> dict:
        params = {"camera": camera, "u_px": u_px, "v_px": v_px, "diameter_px": diameter_px, "z_mm": z_mm}
        if arm_pose is not None:
            params.update(zip(("arm_x_mm", "arm_y_mm", "arm_alpha_deg"), arm_pose))
        if flange is not None:
            params["flange"] = ",".join(repr(float(v)) for v in flange)
        return self._get("/locate", **params)

    def features(self, camera: str) -> dict:
        return self._get(f"/cameras/{camera}/features")

    def health(self) -> dict:
        return self._get("/health/calibrations")

    # -- the operator -----------------------------------------------------------------------------

    def operator_request(self) -> dict:
        return self._get("/operator/request")

    def operator_clicks(self, caller: Caller, request_id: int, clicks: list[tuple[int, float, float]]) -> dict:
        body = {"clicks": [{"model_index": int(k), "u": float(u), "v": float(v)} for k, u, v in clicks]}
        return self._post(caller, f"/operator/requests/{request_id}/clicks", body)

    # -- manual motion --------------------------------------------------------------------------
    def manual(self) -> dict:
        return self._get("/manual")

    def jog(self, caller: Caller, axis: str, distance: float | None = None, direction: int = 1,
            frame: str = "cell", speed_pct: float | None = None) -> dict:
        return self._post(caller, "/manual/jog", {"axis": axis, "distance": distance, "direction": direction,
                                                  "frame": frame, "speed_pct": speed_pct})

    def move_to(self, caller: Caller, pose: dict | None = None, position: str | None = None,
                speed_pct: float | None = None) -> dict:
        return self._post(caller, "/manual/move-to", {"pose": pose, "position": position, "speed_pct": speed_pct})

    def manual_alive(self, caller: Caller, motion_id: int) -> dict:
        return self._post(caller, f"/manual/moves/{motion_id}/alive")

    def manual_stop(self, caller: Caller, motion_id: int | None = None) -> dict:
        return self._post(caller, f"/manual/moves/{motion_id}/stop" if motion_id else "/manual/stop")

    def vacuum(self, caller: Caller, on: bool) -> dict:
        return self._post(caller, "/gripper/grip" if on else "/gripper/release")

    def operator_done(self, caller: Caller, request_id: int) -> dict:
        return self._post(caller, f"/operator/requests/{request_id}/done")

    def operator_decline(self, caller: Caller, request_id: int, reason: str = "") -> dict:
        return self._post(caller, f"/operator/requests/{request_id}/decline", {"reason": reason})

    # -- who may command ----------------------------------------------------------------------

    def audit(self, limit: int = 200) -> list[dict]:
        return self._get("/audit", limit=limit)["audit"]

    def lock_status(self) -> dict:
        return self._get("/lock")

    def acquire_lock(self, caller: Caller, holder: str, ttl_s: float = 300.0) -> dict:
        return self._post(caller, "/lock", {"holder": holder, "ttl_s": ttl_s})

    def release_lock(self, caller: Caller) -> dict:
        return self._request("DELETE", "/lock", caller).json()

    def break_lock(self, caller: Caller, reason: str) -> dict:
        return self._post(caller, "/lock/break", {"reason": reason})

    # -- the OPC UA server's client certificates ----------------------------------------------------------

    def opcua_certificates(self) -> dict:
        return self._get("/opcua/certificates")

    def trust_opcua_certificate(self, caller: Caller, thumbprint: str | None = None,
                                certificate: bytes | None = None) -> dict:
        body = {"thumbprint": thumbprint}
        if certificate is not None:  # as PEM text: JSON carries no bytes (DER becomes PEM)
            body["certificate_pem"] = (certificate.decode("utf-8", "replace") if b"-----BEGIN" in certificate
                                       else ssl.DER_cert_to_PEM_cert(certificate))
        return self._post(caller, "/opcua/certificates/trust", body)

    def backup_store(self, caller: Caller) -> dict:
        return self._post(caller, "/store/backup")
