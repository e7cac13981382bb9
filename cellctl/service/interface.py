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
        """cell, simulated, devices, arm_pose, job (live id or None), lock, cameras, store, disk (the store's
        filesystem: path, filesystem, free_mb, total_mb, min_free_mb, low)."""

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

    # -- the live camera view (needs the daemon; the work: cellctl/service/cameras.py) ----------------------
    def live_frame(self, camera: str, layers: tuple[str, ...] = ("features", "grid", "saturation"),
                   width: int | None = None, format: str = "jpeg") -> Blob:
        """A new frame of `camera`, taken now while no job uses the cell (a job owns the cameras: refused, Conflict
        naming the job; the `frame` verb gives a job's latest frame), drawn for a person: `layers` of
        "saturation" (saturated pixels in magenta), "features" (what find_features sees in this frame, the
        features the routines the camera serves measure), "grid" (the camera's active planar calibration's grid
        over its areas); scaled to `width` (never up); as JPEG (`format` "jpeg", the console's stream) or PNG
        ("png", a snapshot). headers: X-Frame-Id, X-Captured and X-Live-Stats, JSON of the raw frame's figures:
        width, height, full_scale, mean_pct, min, max, saturated (pixels at full scale), saturated_pct,
        histogram (64 bins over 0..full scale, fractions of the pixels), features ([{kind, u_px, v_px,
        diameter_px}] with the features layer), exposure_s, gain_db. Unknown camera: NotFound; a bad layer,
        width or format: InvalidRequest naming what is allowed; the camera failing: Unavailable."""

    def camera_settings(self, camera: str) -> dict:
        """The settings the camera changes live (exposure and gain, any backend; the keys are the cell file's
        options of its backend: exposure_s, gain_db, gain_raw, gain, iso): {"camera", "backend", "settings":
        {key: {"key", "label" ("exposure" or "gain"), "unit", "minimum", "maximum", "integer", "value" (on the
        camera now), "in_file" (the cell file's, None when it sets none), "changed"}}, "note"}. Read from the
        camera: refused (Conflict naming the job) while a job uses the cell."""

    def set_camera_settings(self, caller: Caller, camera: str, values: dict) -> dict:
        """Change {key: value} on the camera now (behind the operator lock, audited): each value checked against
        its range first (InvalidRequest naming the range; nothing changed), then sent. Lasts until the camera
        connects again (a reconnect; a simulated cell's job starts on a fresh world): `save_camera_settings`
        keeps it. Answers as `camera_settings`. Refused (Conflict naming the job) while a job uses the cell."""

    def save_camera_settings(self, caller: Caller, camera: str, confirm: bool = False) -> dict:
        """The camera's settings that differ from the cell file, written back to it: {"camera", "file", "changes":
        {key: [in the file, on the camera]}, "diff" (unified), "written", "message"}. Without `confirm` only the
        diff (nothing written, no lock). With it, behind the operator lock and audited: the file replaced
        atomically, only the changed keys' lines edited (comments and the rest kept). A camera entry the file
        takes from another (`extends:`) is refused (InvalidRequest naming that file); so is a layout the edit
        does not follow."""

    # -- manual motion, for the holder of the operator lock only (cellctl/service/manual.py) ----------------
    def manual(self) -> dict:
        """The manual-motion settings and state: speed_pct, speed_mm_s (the cap), max_step_mm, max_step_deg,
        heartbeat_timeout_s, segment_s, axes, frames, box (the workspace box), positions (named), gripper (whether
        the cell has one), current (the move under way, or None) and last (the last one ended)."""

    def jog(self, caller: Caller, axis: str, distance: float | None = None, direction: int = 1,
            frame: str = "cell", speed_pct: float | None = None) -> dict:
        """Jog along or about `axis` (x, y, z in mm; rx, ry, rz in deg; a four-axis arm: x, y, z, rz) of `frame`
        (cell or tool): a step of `distance`, or, without one, held toward `direction` (1 or -1) until released
        (`manual_stop`) or its heartbeat lapses (`manual_alive`, every move needs one more often than
        heartbeat_timeout_s). At `speed_pct` of the arm's speed, at most the manual cap. Checked whole before
        anything moves (InvalidRequest naming what and what is allowed); Conflict beside a job or another manual
        move. Returns the move as `manual` shows it ({"motion": id, "state": "moving", ...}); its end is a
        `manual` event and `manual()["last"]`."""

    def move_to(self, caller: Caller, pose: dict | None = None, position: str | None = None,
                speed_pct: float | None = None) -> dict:
        """Move in a straight line to a typed pose (x_mm, y_mm, z_mm, alpha_deg or quaternion_wxyz) or to a named
        position of the cell file (manual.positions), exactly one; checked and run as a jog step is."""

    def manual_alive(self, caller: Caller, motion_id: int) -> dict:
        """The dead-man heartbeat of a manual move: its client is still there (not audited)."""

    def manual_stop(self, caller: Caller, motion_id: int | None = None) -> dict:
        """Stop the manual move (the one given, or the current) now; the arm stands where it stopped."""

    def vacuum(self, caller: Caller, on: bool) -> dict:
        """Switch the vacuum on (grip) or off (release) by hand: {"vacuum", "object_detected", "vacuum_kpa",
        "gripping"}."""

    # -- the device self-test (the work: cellctl/service/commission.py) --------------------------------------
    def commission(self, caller: Caller, device: str | None = None, move: bool = False) -> dict:
        """Check each device of the cell (or only `device`), in order: its link (connects, version, latency), its
        readings (pose and joints, vacuum, a frame), with `move` a slow motion of the arm of 5 mm and back that each
        camera reports from its images (checked against the workspace box before it is sent), a grip with
        nothing held, and each camera's focus and exposure. {"cell", "simulated", "device", "moved", "checks":
        [{"device", "check", "result" (ok, problem, skipped, info), "figure", "finding" (what to fix)}],
        "problems" (how many), "findings" (the problems' findings, "device: ..."), "seconds"}. A device that does
        not connect is a finding. Without `move` the motion check is skipped (said so), not failed. A command
        (audited); with `move` for the holder of the operator lock only (LockHeld). Refused (Conflict naming the
        job) while a job runs or holds the cell; an unknown device is NotFound naming the devices."""

    # -- jobs -------------------------------------------------------------------------------
    def submit(self, caller: Caller, routine: str, params: dict | None = None, seed: int | None = None,
               save_images: bool = False) -> dict:
        """Queue a routine or a sequence; parameters are checked before it is queued. InsufficientStorage (507) while
        the store's filesystem has less free space than the cell file's store.min_free_mb."""

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

    # -- the store's backups (cellctl/stores/backup.py) ----------------------------------------------------------
    def backup_store(self, caller: Caller) -> dict:
        """Back the store up now, into the cell file's store.backup.to (default <store>-backups), keeping its
        store.backup.keep newest: the databases through SQLite's online backup API (consistent while a job runs),
        then the run folders. {"backup": its folder, and its manifest: taken, databases, files, bytes}.
        InsufficientStorage (507) when the copy would leave less than store.min_free_mb free there. Audited; not
        behind the operator lock. (A restore has no verb: it needs a store no daemon serves, `cellctl store
        restore`.)"""
