"""The verbs of a cell: everything an operator, an engineer or the plant can ask of it.

Two implementations: `LocalService` (in the daemon's process, over the worker, the job
store and the calibration store; also over a calibration store alone, for the CLI
without a daemon) and `RemoteService` (the same verbs over the daemon's HTTP API).
Front ends (the HTTP API, the CLI, later OPC UA) translate arguments and errors and
call these; validation, the operator lock and the audit live behind them.

Values are plain JSON-able dicts, as the HTTP API serves them, so every front end
sees the same shapes. Commands take the `Caller` (who, and the operator lock id it
presents); reads need none. Refusals are `cellctl.errors.ServiceError`s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

ExportFormat = Literal["json", "opencv", "urdf"]  # urdf: an `arm` calibration only
JobFile = Literal["result.json", "report.md", "samples.csv", "plot"]


@dataclass(frozen=True)
class Caller:
    """Who sends a command ("user@host", shown in the audit) and the operator lock id it presents.

    `via`: the request as its front end received it ("POST /jobs/3/pause"), the audit's action;
    `credential`: how the front end authenticated it ("token")."""

    who: str
    lock: str | None = None
    via: str = ""
    credential: str = "token"


@dataclass(frozen=True)
class Export:
    """A calibration exported: the document's text, its media type and a file name for it."""

    text: str
    media_type: str
    filename: str


@dataclass(frozen=True)
class Blob:
    """A job's file or a camera's frame: bytes, media type, and headers worth passing on."""

    data: bytes
    media_type: str
    headers: dict[str, str]


class CellService(Protocol):
    # -- the cell ---------------------------------------------------------------------------
    def status(self) -> dict:
        """cell, simulated, devices, arm_pose, job (live id or None), lock, cameras, store."""

    def routines(self) -> dict:
        """{"routines": {name: {"params": JSON schema, "defaults": cell file's, "previews": whether `plan` shows
        its motion}}, "sequences": {...}}."""

    def plan(self, routine: str, params: dict | None = None) -> dict:
        """What a routine that plans its own motion (hand-eye) will do, before anything moves (read-only: no
        motion, no lock, no device asked): {"routine", "tables": [{"title", "columns", "rows", "note"}]}. A
        routine that plans no motion of its own is NotFound naming those that do; a region that cannot give the
        poses, or a bad parameter, is InvalidRequest saying why."""

    def reconnect(self, caller: Caller, device: str | None = None) -> dict:
        """Reconnect every device, or one; refused (Conflict) while a job is live."""

    def frame(self, camera: str) -> Blob:
        """The camera's latest frame as PNG: a new capture when idle, else the live job's latest."""

    # -- jobs -------------------------------------------------------------------------------
    def submit(self, caller: Caller, routine: str, params: dict | None = None, seed: int | None = None,
               save_images: bool = False) -> dict:
        """Queue a routine or a sequence; parameters are checked before it is queued."""

    def jobs(self, state: str | None = None, limit: int = 50) -> list[dict]:
        """Jobs, newest first."""

    def job(self, job_id: int) -> dict:
        """One job with its state history (and result when done)."""

    def pause(self, caller: Caller, job_id: int, immediate: bool = False) -> dict: ...

    def resume(self, caller: Caller, job_id: int) -> dict: ...

    def acknowledge(self, caller: Caller, job_id: int) -> dict: ...

    def abort(self, caller: Caller, job_id: int) -> dict: ...

    def result(self, job_id: int, item: str | None = None) -> dict:
        """result.json of a job; of a sequence its summary, or with `item` one routine's."""

    def job_file(self, job_id: int, name: JobFile, item: str | None = None) -> Blob:
        """report.md, samples.csv or the residual plot of a job (or of one item of a sequence)."""

    # -- calibrations -----------------------------------------------------------------------
    def calibrations(self, target: str | None = None) -> list[dict]:
        """Every calibration version (id, target, routine, version, created, active, cell, stats)."""

    def calibration(self, cal_id: int) -> dict:
        """One calibration with its model."""

    def activate(self, caller: Caller, cal_id: int) -> dict:
        """Make this version the active one of its target; refused while a job is live."""

    def deactivate(self, caller: Caller, cal_id: int) -> dict:
        """Take this version out of use (its target then has none: an `arm` calibration off, moves go by the
        controller's own table); refused while a job is live."""

    def export(self, cal_id: int, format: ExportFormat = "json") -> Export:
        """The calibration as a file: json or opencv (OpenCV FileStorage YAML) of any, urdf of an `arm`
        calibration (its calibrated kinematic table and tool); another target asked for urdf is InvalidRequest
        naming the formats it allows."""

    def locate(self, camera: str, u_px: float, v_px: float, arm_pose: tuple[float, float, float] | None = None,
               diameter_px: float | None = None, z_mm: float | None = None,
               flange: tuple[float, ...] | None = None) -> dict:
        """Where what `camera` sees at (u_px, v_px) is, from the active calibrations (read-only: no motion, no lock):
        {"camera", "u_px", "v_px", "x_mm", "y_mm", "sigma_um", "outside_calibrated_region", "warning",
        "calibration_id", "version", "health", "calibrations": {target: id}}. A pixel off the camera's image is
        refused (InvalidRequest naming the pixel and the image's size); an unknown camera is NotFound.

        x_mm, y_mm: the commanded robot position at alpha_cal that puts the nozzle there. sigma_um: the 1-σ
        per-axis uncertainty of that point from the camera calibration's covariance, sqrt(trace(C) / 2) of the
        located point's 2x2 covariance C (None if the calibration keeps none); the feature's own centroid noise
        is not in it. outside_calibrated_region: the pixel lies outside the hull of the pixels the calibration was
        fitted on (the map extrapolates; sigma_um has grown accordingly), None if the calibration keeps no hull
        (made before it was kept); warning: says so, else None. calibration_id, version: the camera's active
        calibration; health: its target's verdict ("ok", "drift" or "unchecked", as `health` gives it).
        `arm_pose` (x_mm, y_mm, alpha_deg): the arm's reported pose, for a camera that rides on it. `diameter_px`:
        a sphere's apparent diameter, for a calibration that corrects sphere heights (else ignored).

        A camera calibrated by `hand-eye` (a six-axis cell: target `hand-eye:<camera>`) answers in the base frame
        with x_mm, y_mm and z_mm on a plane: the board's (eye-in-hand), or the horizontal plane at height `z_mm`.
        sigma_um is then the 1-σ per axis in that plane from the calibration's covariance of X, Y and the
        intrinsics with the arm's accuracy. A camera on the wrist needs the flange pose: `flange` (x_mm, y_mm, z_mm,
        qw, qx, qy, qz, as the arm reports it), else the daemon reads the arm's pose now (refused beside a job)."""

    def features(self, camera: str) -> dict:
        """What `camera` sees now (a new capture when idle, else the live job's latest frame; needs the daemon):
        {"camera", "frame_id", "captured" (epoch s), "features": [{"kind" ("nozzle" or "sphere"), "u_px", "v_px",
        "x_mm", "y_mm", "sigma_um", "outside_calibrated_region", "diameter_px"}]}, located as `locate` does (spheres corrected for their height
        where the calibration does); x_mm, y_mm, sigma_um are None when the camera is not calibrated (or rides the
        arm while a job runs: its pose at the frame is not known)."""

    def health(self) -> dict:
        """Per target with an active calibration: that version, its last check, the verdict (ok, drift, or
        unchecked) and every check of the target, oldest first (time, calibration checked, drift, p-value)."""

    # -- the operator: what a routine waits for a person to do (operator: {backend: web}) -----------
    def operator_request(self) -> dict:
        """{"backend": the cell's operator backend, "answered_here": whether its requests are answered through
        this service (backend web), "request": the pending request or None, "last": the last one that ended
        (request, kind, instruction, outcome, ...) or None}. A request: id, kind (request, click_points,
        align_by_hand, mount_camera), answer_with ("clicks" or "confirm"), instruction, posted, timeout_s,
        expires_in_s, job, what it is about (camera, object, fixture, ...) and the API paths that answer it."""

    def operator_clicks(self, caller: Caller, request_id: int, clicks: list[tuple[int, float, float]]) -> dict:
        """Answer a click request with (model_index, u, v) pairs, checked whole (InvalidRequest naming each bad
        field; nothing taken). Refused (Conflict) for a request that is not pending or asks for a confirmation."""

    def operator_done(self, caller: Caller, request_id: int) -> dict:
        """An instruction is done. Refused (Conflict) for a request that is not pending or asks for clicks."""

    def operator_decline(self, caller: Caller, request_id: int, reason: str = "") -> dict:
        """It cannot be done (a click request: too few points seen): the job faults with the reason and can
        be resumed after acknowledging. Refused (Conflict) for a request that is not pending."""

    # -- who may command ----------------------------------------------------------------------
    def audit(self, limit: int = 200) -> list[dict]:
        """The audit log of commands, oldest first."""

    def lock_status(self) -> dict: ...

    def acquire_lock(self, caller: Caller, holder: str, ttl_s: float = 300.0) -> dict:
        """Take (or, presenting the current lock id, renew) the operator lock; the reply holds lock_id."""

    def release_lock(self, caller: Caller) -> dict:
        """Give the lock back (its holder only: the caller presents its lock id)."""

    def break_lock(self, caller: Caller, reason: str) -> dict:
        """Free a stale lock whoever holds it (any token holder), with a reason (InvalidRequest without one;
        Conflict when nobody holds it). Audited with who broke it, whose lock it was and why; the holder is told
        (a `lock` event, and its next command or renewal gets LockHeld saying by whom and why).
        Returns {"broken": {"holder", "by", "reason", "at"}, "lock": the status now}."""

    # -- the OPC UA server's client certificates (cellctl/stores/client_certificates.py) ---------------------------
    def opcua_certificates(self) -> dict:
        """{"trusted": [...], "rejected": [...], "trusted_dir", "rejected_dir"}: the client application certificates
        trusted on Sign / SignAndEncrypt channels (the cell file's opcua.trusted_clients and the store's
        opcua/trusted/) and those refused there (opcua/rejected/). Each: thumbprint (SHA-1, hex), subject,
        application_uri, not_after, expired, file, source ("cell file" or "store"); a rejected one its rejected_at;
        a file there that is no certificate only file, source and problem. Works without a daemon, on the store."""

    def trust_opcua_certificate(self, caller: Caller, thumbprint: str | None = None,
                                certificate: bytes | None = None) -> dict:
        """Trust a client certificate from its next session on (no restart): a rejected (or known) one by its
        thumbprint or a unique prefix of 8+ hex digits, or one given whole (PEM or DER); exactly one of the two.
        {"certificate": as listed, "already": it was trusted before}. Audited; not behind the operator lock (it
        moves nothing, and commands over OPC UA still need a user)."""
