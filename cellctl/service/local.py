"""The cell's verbs in the process that owns the cell: over the worker, the job store, the calibration store.

The daemon builds one with every part (`LocalService.of_daemon`). The CLI without a daemon
builds one over a cell file's calibration store alone (`LocalService.of_store`): the
calibration verbs work, the verbs that need the running cell say so (Unavailable).

Every command checks the operator lock and is written to the audit log, accepted or refused.
"""

from __future__ import annotations

import json
import logging
import math
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from drivers.interfaces import Pose
from drivers.operators.web import (  # desk: the one of the daemon's store, which its web operator asks
    AnswerRefused,
    desk_for,
)

from calibration.errors import CalibrationError, UnknownName
from calibration.models.hand_eye_locate import HandEyeCamera, flange_from_values
from calibration.routines import is_sequence, judging_routine, routine_class, routine_names, runnable_names, sequences
from calibration.routines.base import ChecksTargets, Previews
from calibration.usage import OUTSIDE_REGION, CellCalibration
from calibration.vision.features import find_features

from cellctl.config import CellFile, arm_model_of
from cellctl.core.runs import preview_routine, routine_params, run_routine, run_sequence, sequence_summary
from cellctl.errors import Conflict, InvalidRequest, NotFound, ServiceError, Unavailable
from cellctl.service.auth import MAX_LOCK_TTL_S
from cellctl.service.export import ARM_TARGET, check_format, export_calibration
from cellctl.service.interface import Blob, Caller, Export, ExportFormat, JobFile
from cellctl.service.manual import ManualVerbs
from cellctl.stores.calibrations import Calibration, CalibrationStore
from cellctl.stores.client_certificates import ClientCertificates, parse_certificate, read_certificate
from cellctl.stores.client_certificates import thumbprint as thumbprint_of
from cellctl.stores.disk_space import is_disk_full, require_free, space
from cellctl.stores.jobs import DB_FILE, JobStore, finished_results, what_happened

FILE_TYPES = {"result.json": "application/json", "report.md": "text/markdown", "samples.csv": "text/csv",
              "plot": "image/png"}


MAX_SEED = 2**32 - 1  # a simulated world's seed (numpy's)
log = logging.getLogger("cellctl.service")

class LocalService(ManualVerbs):  # the manual-motion verbs: cellctl/service/manual.py
    def __init__(self, config: CellFile, calstore: CalibrationStore, *, jobs=None, worker=None, lock=None, hub=None,
                 store_dir: Path | None = None, desk=None, audit_log: JobStore | None = None, cell_text: str = ""):
        self.config, self.calstore = config, calstore
        self._jobs, self._worker, self._lock, self._hub = jobs, worker, lock, hub
        self._audit_log = audit_log if audit_log is not None else jobs  # the daemon's job store keeps the audit
        self._own_audit_log = False  # opened here (a store without its daemon), closed by close()
        self._cell_text = cell_text  # the cell file as written, kept with what a run here stores
        self._desk = desk  # the web operator's requests (drivers/operators/web.py: OperatorDesk)
        self.store_dir = store_dir or calstore.path
        self.schedule = None  # the daemon's calibration checks on a schedule, if the cell file asks for them
        self._live = None  # the live camera view (cellctl/service/cameras.py), the daemon's only

    @classmethod
    def of_daemon(cls, daemon) -> "LocalService":
        service = cls(daemon.config, daemon.calstore, jobs=daemon.jobs, worker=daemon.worker, lock=daemon.lock,
                      hub=daemon.hub, store_dir=daemon.store_dir, desk=desk_for(daemon.store_dir))
        from cellctl.service.cameras import LiveCameras  # the live camera view's work

        service._live = LiveCameras(daemon.config, daemon.worker, daemon.calstore, daemon.config_path)
        return service

    @classmethod
    def of_store(cls, config: CellFile, calstore: CalibrationStore, cell_text: str = "") -> "LocalService":
        """The service on a cell file's store, no daemon: for the process that owns the store (cellctl run, a local
        activate). Its commands are audited in the store's audit log, as the daemon's are."""
        return cls(config, calstore, cell_text=cell_text)

    def close(self) -> None:
        if self._own_audit_log:
            self._audit_log.close()
            self._audit_log, self._own_audit_log = None, False

    # -- parts that only the daemon has ------------------------------------------------------

    def _needs_daemon(self, what: str):
        raise Unavailable(f"{what} needs the cell daemon (cellctl serve): give --url or set CELLCTL_URL")

    @property
    def worker(self):
        return self._worker if self._worker is not None else self._needs_daemon("this")

    @property
    def jobs_store(self):
        return self._jobs if self._jobs is not None else self._needs_daemon("the job list")

    # -- commands: lock, then the work, then the audit ----------------------------------------

    @contextmanager
    def _command(self, caller: Caller, verb: str, target: str, detail: Any = "", check_lock: bool = True):
        """Yields the audit entry, whose target the work may make precise (a new job's id)."""
        entry = {"target": target, "outcome": "ok"}
        try:
            if check_lock and self._lock is not None:
                self._lock.check(caller.lock)
            yield entry
        except ServiceError as exc:
            entry["outcome"] = refused_outcome(exc)
            raise
        except KeyboardInterrupt:  # a run in this process, stopped at the terminal
            entry["outcome"] = "interrupted"
            raise
        except Exception:
            entry["outcome"] = "failed"
            raise
        finally:
            self._audit(caller, verb, entry["target"], detail, entry["outcome"])

    def record_refusal(self, caller: Caller, verb: str, target: str, exc: ServiceError, detail: Any = "") -> None:
        """A command its front end refused before it reached a verb here (an argument it could not translate),
        audited as the verbs audit their own refusals."""
        self._audit(caller, verb, target, detail, refused_outcome(exc))

    def _audit(self, caller: Caller, verb: str, target: str, detail: Any, outcome: str) -> None:
        if self._audit_log is None:  # no daemon: the store's own audit log, opened by the first command (only the
            # store's owner commands; a reader beside a daemon never opens it)
            self._audit_log = JobStore(self.store_dir / DB_FILE, replicate=bool(self.config and self.config.fleet))
            self._own_audit_log = True
        text = detail if isinstance(detail, str) else json.dumps(detail, default=str)
        try:
            self._audit_log.audit(caller.credential, caller.who, caller.via or verb, target, text, outcome)
        except Exception as exc:
            if not (is_disk_full(exc) and outcome.startswith("refused")):
                raise
            # a full disk must not hide the refusal's own reason (it is often the full disk): the journal keeps it
            log.error("the audit could not record a refusal: the disk is full",
                      extra={"who": caller.who, "verb": verb, "target": target, "outcome": outcome})

    # -- the cell -------------------------------------------------------------------------------

    def status(self) -> dict:
        worker = self.worker
        return {"cell": self.config.cell.name, "simulated": worker.cells.simulated,
                "devices": worker.cells.status(), "arm_pose": worker.idle_pose(), "job": worker.live_job,
                "lock": self._lock.status(), "cameras": sorted(self.config.cameras), "store": str(self.store_dir),
                "disk": space(self.store_dir).to_dict(self.config.store.min_free_mb),
                "health_schedule": self.schedule.status() if self.schedule is not None else None}

    def routines(self) -> dict:
        out = {name: {"params": routine_class(name).Params.model_json_schema(),
                      "defaults": self.config.routines.get(name, {}),
                      "previews": issubclass(routine_class(name), Previews)} for name in routine_names()}
        return {"routines": out, "sequences": {name: list(seq.names) for name, seq in sequences().items()},
                "judge": judging_routine()}

    def plan(self, routine: str, params: dict | None = None) -> dict:
        bad = non_finite(params or {}, "params")
        if bad:
            raise InvalidRequest(f"{bad}: must be a finite number (NaN and Infinity are not allowed)")
        try:
            return {"routine": routine, "tables": preview_routine(routine, self.config, params or {})}
        except UnknownName as exc:
            raise NotFound(str(exc)) from None
        except CalibrationError as exc:
            raise InvalidRequest(str(exc)) from None

    def reconnect(self, caller: Caller, device: str | None = None) -> dict:
        with self._command(caller, "reconnect", device or "all"):
            errors = self.worker.reconnect(device)
            return {"devices": self.worker.cells.status(), "errors": errors}

    def _check_camera(self, camera: str) -> None:
        if camera not in self.config.cameras:
            raise NotFound(f"no camera {camera!r}; cameras: {', '.join(sorted(self.config.cameras))}")

    def latest_frame(self, camera: str):
        """(time, Frame) of `camera`, for front ends that draw on it (the console's overlay)."""
        self._check_camera(camera)
        return self.worker.latest_frame(camera)

    def frame(self, camera: str) -> Blob:
        import cv2

        stamp, frame = self.latest_frame(camera)
        ok, png = cv2.imencode(".png", frame.image)
        if not ok:
            raise ServiceError(f"camera {camera}: could not encode the frame as PNG")
        return Blob(png.tobytes(), "image/png", frame_headers(stamp, frame))

    def features(self, camera: str) -> dict:
        stamp, frame = self.latest_frame(camera)
        models = self.calstore.active_models()
        cal = CellCalibration(models)
        pose = None
        if cal.rides_arm(camera) and self.worker.live_job is None:
            # the frame was just taken (idle): the arm stands where it is now. Beside a job its pose at the frame
            # is not known, and the camera's features are not located
            now = self.worker.idle_pose()
            pose = Pose(now["x_mm"] * 1e-3, now["y_mm"] * 1e-3, 0.0, math.radians(now["alpha_deg"])) if now else None
        out = []
        for f in find_features(frame.image):
            b = f.blob
            where = {"x_mm": None, "y_mm": None, "sigma_um": None, "outside_calibrated_region": None}
            try:
                xy, sigma = cal.locate_with_sigma(camera, [(b.u, b.v)], pose,
                                                  b.diameter_px if f.kind == "sphere" else None)
                inside = cal.in_calibrated_region(camera, [(b.u, b.v)])
            except CalibrationError:  # the camera is not calibrated (or rides the arm, its pose unknown)
                pass
            else:
                where = dict(located_fields(xy[0], sigma[0]),
                             outside_calibrated_region=None if inside is None else bool(not inside[0]))
            out.append({"kind": f.kind, "u_px": b.u, "v_px": b.v, **where, "diameter_px": b.diameter_px})
        return {"camera": camera, "frame_id": frame.frame_id, "captured": stamp, "features": out}

    # -- the live camera view (the work: cellctl/service/cameras.py) ------------------------------------

    @property
    def live(self):
        return self._live if self._live is not None else self._needs_daemon("the live camera view")

    def live_frame(self, camera: str, layers: tuple[str, ...] = ("features", "grid", "saturation"),
                   width: int | None = None, format: str = "jpeg") -> Blob:
        from cellctl.service.cameras import LIVE_LAYERS

        self._check_camera(camera)
        bad = [layer for layer in layers if layer not in LIVE_LAYERS]
        if bad:
            raise InvalidRequest(f"layers: {', '.join(bad)}; allowed: {', '.join(LIVE_LAYERS)}")
        if format not in ("jpeg", "png"):
            raise InvalidRequest(f"format: {format!r}; allowed: jpeg, png")
        if width is not None and not 64 <= width <= 10000:
            raise InvalidRequest(f"width: {width}; allowed: 64 to 10000 px, or none (full size)")
        data, live = self.live.picture(camera, set(layers), width, format)
        stats = dict(live.stats, exposure_s=live.frame.exposure_s, gain_db=live.frame.meta.get("gain_db"))
        return Blob(data, "image/png" if format == "png" else "image/jpeg",
                    dict(frame_headers(live.captured, live.frame), **{"X-Live-Stats": json.dumps(stats)}))

    def camera_settings(self, camera: str) -> dict:
        self._check_camera(camera)
        return self.live.settings(camera)

    def set_camera_settings(self, caller: Caller, camera: str, values: dict) -> dict:
        with self._command(caller, "camera settings", f"camera {camera}", values):
            self._check_camera(camera)
            return self.live.set_settings(camera, dict(values))

    def save_camera_settings(self, caller: Caller, camera: str, confirm: bool = False) -> dict:
        self._check_camera(camera)
        if not confirm:  # the diff only: nothing changes, so no lock
            return self.live.save(camera, False)
        with self._command(caller, "camera save", f"camera {camera}", {"confirm": True}) as entry:
            answer = self.live.save(camera, True)
            entry["target"] = f"camera {camera} in {answer['file']}"
            return answer

    # -- the device self-test (the work: cellctl/service/commission.py) --------------------------------

    def commission(self, caller: Caller, device: str | None = None, move: bool = False) -> dict:
        from cellctl.service.commission import check_device, commission, motion_detail

        worker = self.worker  # the daemon's cell (without one: commission_here, on a cell this process owns)
        detail = {"device": device, "move": move, **(motion_detail() if move else {})}
        with self._command(caller, "commission", device or "all devices", detail, check_lock=not move):
            check_device(worker.cells.cell, self.config, device)
            if move:  # the arm moves: for the holder of the operator lock only
                self._lock.check_held(caller.lock, "the self-test's motion (commission with move)")
            with worker.idle_cell("wait until it has ended (or abort it) before the self-test") as cell:
                answer = commission(cell, self.config, device=device, move=move, errors=worker.cells.errors,
                                    calibrations=self.calstore.active_models())
                for _kind, name, dev in worker.cells.named_devices():  # what the link checks connected
                    if dev.state.value == "ready":
                        worker.cells.errors.pop(name, None)
                worker.cells.last_pose = None
            if self._hub is not None:
                self._hub.publish("commission", {"device": device, "moved": move, "problems": answer["problems"]})
            return answer

    def commission_here(self, caller: Caller, cell, device: str | None = None, move: bool = False,
                        errors: dict | None = None) -> dict:
        """The self-test on a cell this process owns (cellctl commission without a daemon): audited in the store's
        audit log as the daemon's; no lock (no daemon)."""
        from cellctl.service.commission import check_device, commission, motion_detail

        detail = {"device": device, "move": move, **(motion_detail() if move else {})}
        with self._command(caller, "commission", device or "all devices", detail, check_lock=False):
            check_device(cell, self.config, device)
            return commission(cell, self.config, device=device, move=move, errors=errors,
                              calibrations=self.calstore.active_models())

    # -- jobs -------------------------------------------------------------------------------------

    def submit(self, caller: Caller, routine: str, params: dict | None = None, seed: int | None = None,
               save_images: bool = False) -> dict:
        params = dict(params or {})
        detail = {"routine": routine, "params": params, "seed": seed, "save_images": save_images}
        with self._command(caller, "submit", routine, detail) as entry:
            self._check_job(routine, params, seed)
            self._require_space("a new job" + (" that saves its images" if save_images else ""))
            job = self.jobs_store.submit(routine, params, seed, caller.who, save_images=save_images)
            entry["target"] = f"job {job.id}"
            self._hub.publish("state", {"job": job.id, "state": job.state, "reason": "submitted"})
            self.worker.wake()
            return job.to_dict()

    def run_here(self, caller: Caller, routine: str, params: dict | None, seed: int | None, out: Path, *,
                 resume: bool = False, save_images: bool = False, on_progress=None, on_step=None) -> dict:
        """A routine or sequence run in this process, on the cell this process owns (cellctl run without a daemon):
        checked as `submit` checks a job, audited as the daemon audits one. A routine's result, or a sequence's
        {"summary", "results"}. `on_progress`: a routine's progress; `on_step(item)`: each of a sequence's."""
        params = dict(params or {})
        detail = {"routine": routine, "params": params, "seed": seed, "save_images": save_images, "out": str(out)}
        with self._command(caller, "run", routine, detail, check_lock=False):  # no daemon here, so no lock
            self._check_job(routine, params, seed)
            self._require_space(("resuming a run" if resume else "a new run")
                                + (" that saves its images" if save_images else ""))
            if is_sequence(routine):
                return run_sequence(routine, self.config, self._cell_text, out, seed=seed, resume=resume,
                                    store=self.calstore, on_step=on_step, save_images=save_images)
            return run_routine(routine, self.config, self._cell_text, out, seed=seed, overrides=params, resume=resume,
                               save_images=save_images, store=self.calstore, on_progress=on_progress)

    def _require_space(self, what: str) -> None:
        """InsufficientStorage (507) while the store's filesystem has less free than the cell file's
        store.min_free_mb (cellctl/stores/disk_space.py)."""
        require_free(self.store_dir, self.config.store.min_free_mb, what)

    def _check_job(self, routine: str, params: dict, seed: int | None) -> None:
        names = runnable_names()
        if routine not in names:
            raise InvalidRequest(f"routine: {routine!r} is not a routine; allowed: {', '.join(names)}")
        bad = non_finite(params, "params")
        if bad:
            raise InvalidRequest(f"{bad}: must be a finite number (NaN and Infinity are not allowed)")
        if seed is not None and not 0 <= seed <= MAX_SEED:
            raise InvalidRequest(f"seed: {seed}; allowed: a simulation seed from 0 to {MAX_SEED}, or none")
        if seed is not None and self.config.sim is None:
            raise InvalidRequest("seed: the simulation seed applies to simulated cells only; this cell has no 'sim:' section")
        if is_sequence(routine):
            if params:
                raise InvalidRequest(f"params: {routine} is a sequence; set each routine's parameters in the cell file")
        else:
            self._check_targets(routine_class(routine)(), params)

    def _check_targets(self, routine, overrides: dict) -> None:
        """A routine that places things (ChecksTargets) checks its targets against the areas, the arm's limits and the
        active calibrations here, so a job that could not run is never queued."""
        params = routine_params(routine, self.config, overrides)
        if isinstance(routine, ChecksTargets):
            try:
                routine.check_targets(params, self.config.areas_by_name(), self.calstore.active_models(),
                                      self.config.arm.options.get("limits"))
            except CalibrationError as exc:
                raise InvalidRequest(f"{routine.name}: {exc}") from None

    def jobs(self, state: str | None = None, limit: int = 50) -> list[dict]:
        return [j.to_dict() for j in self.jobs_store.list(state, limit)]

    def job(self, job_id: int) -> dict:
        job = self.jobs_store.get(job_id)
        return dict(job.to_dict(with_result=True), history=self.jobs_store.history(job_id))

    # a job command answers with the job and what it did ("message"): a stop asked of a running job takes effect
    # at a step boundary or when the arm has stopped, so the state alone would still say "running"

    def pause(self, caller: Caller, job_id: int, immediate: bool = False) -> dict:
        with self._command(caller, "pause", f"job {job_id}", {"mode": "immediate" if immediate else "deferred"}):
            return answered(*self.worker.pause(job_id, immediate, caller.who))

    def resume(self, caller: Caller, job_id: int) -> dict:
        with self._command(caller, "resume", f"job {job_id}"):
            self.jobs_store.get(job_id)  # an unknown job is a 404 first
            self._require_space(f"resuming job {job_id}")
            return answered(*self.worker.resume(job_id, caller.who))

    def acknowledge(self, caller: Caller, job_id: int) -> dict:
        with self._command(caller, "acknowledge", f"job {job_id}"):
            return answered(*self.worker.acknowledge(job_id, caller.who))

    def abort(self, caller: Caller, job_id: int) -> dict:
        with self._command(caller, "abort", f"job {job_id}"):
            return answered(*self.worker.abort(job_id, caller.who))

    def _job_path(self, job_id: int, name: str, item: str | None) -> Path:
        job = self.jobs_store.get(job_id)
        folder = Path(job.run_dir)
        if item is not None:
            if not is_sequence(job.routine):
                raise NotFound(f"item: job {job_id} runs {job.routine}, not a sequence: it has no items")
            try:
                folder = folder / sequences()[job.routine].folder(item)
            except UnknownName as exc:
                raise NotFound(str(exc)) from None
        path = folder / name
        if not path.is_file():
            whose = f"its routine {item}" if item is not None else "it"
            raise NotFound(f"{what_happened(job)}: {whose} has no {name} (a routine writes its result files when "
                           "it finishes)")
        return path

    def result(self, job_id: int, item: str | None = None) -> dict:
        """result.json; of a sequence that did not finish (aborted, faulted, paused, still running), the summary of
        the routines that did, marked `"complete": false`, with what happened and the routines not finished."""
        job = self.jobs_store.get(job_id)
        sequence = sequences().get(job.routine)
        items = sequence.names if sequence is not None else None
        if item is None and items is not None and not (Path(job.run_dir) / "result.json").is_file():
            finished = finished_results(job)
            return dict(sequence_summary(job.routine, self.config.cell.name, job.seed, finished), complete=False,
                        state=job.state, reason=job.reason, message=what_happened(job),
                        not_finished=[i for i in items if i not in finished])
        return json.loads(self._job_path(job_id, "result.json", item).read_text())

    def job_file(self, job_id: int, name: JobFile, item: str | None = None) -> Blob:
        if name not in FILE_TYPES:
            raise InvalidRequest(f"file: {name!r}; allowed: {', '.join(FILE_TYPES)}")
        if name == "plot":
            plot = (self.result(job_id, item).get("files") or {}).get("plot")
            if not plot:
                raise NotFound(f"job {job_id} has no plot")
            return Blob(self._job_path(job_id, plot, item).read_bytes(), FILE_TYPES[name], {})
        return Blob(self._job_path(job_id, name, item).read_bytes(), FILE_TYPES[name], {})

    # -- calibrations -------------------------------------------------------------------------

    def calibrations(self, target: str | None = None) -> list[dict]:
        return [calibration_summary(c) for c in self.calstore.list(target)]

    def calibration(self, cal_id: int) -> dict:
        c = self.calstore.get(cal_id)
        return dict(calibration_summary(c), model=c.model, run_dir=c.run_dir)

    def activate(self, caller: Caller, cal_id: int) -> dict:
        with self._command(caller, "activate", f"calibration {cal_id}"):
            if self.config is not None:
                refuse_a_foreign_arm(self.calstore.get(cal_id), self.config)
            cal = self._worker.activate(cal_id) if self._worker is not None else self.calstore.activate(cal_id)
            return calibration_summary(cal)

    def deactivate(self, caller: Caller, cal_id: int) -> dict:
        with self._command(caller, "deactivate", f"calibration {cal_id}"):
            cal = self._worker.deactivate(cal_id) if self._worker is not None else self.calstore.deactivate(cal_id)
            return calibration_summary(cal)

    def export(self, cal_id: int, format: ExportFormat = "json") -> Export:
        check_format(format)
        return export_calibration(self.calstore.get(cal_id), format)

    def locate(self, camera: str, u_px: float, v_px: float, arm_pose: tuple[float, float, float] | None = None,
               diameter_px: float | None = None, z_mm: float | None = None,
               flange: tuple[float, ...] | None = None) -> dict:
        pose = None
        if arm_pose is not None:
            x, y, alpha = arm_pose
            pose = Pose(x * 1e-3, y * 1e-3, 0.0, math.radians(alpha))
        if not (math.isfinite(u_px) and math.isfinite(v_px)):
            raise InvalidRequest(f"u_px, v_px: {u_px}, {v_px}; allowed: finite pixel coordinates")
        if diameter_px is not None and not (math.isfinite(diameter_px) and diameter_px > 0):
            raise InvalidRequest(f"diameter_px: {diameter_px!r}; allowed: a positive number of pixels")
        self._check_camera(camera)
        models = self.calstore.active_models()
        if camera not in models and f"hand-eye:{camera}" in models:
            return self._locate_hand_eye(camera, u_px, v_px, models, z_mm, flange)
        cal = CellCalibration(models)
        try:
            cal.check_on_image(camera, [(u_px, v_px)])  # off the image the map still answers, with nonsense
            xy, sigma = cal.locate_with_sigma(camera, [(u_px, v_px)], pose, diameter_px)
            inside = cal.in_calibrated_region(camera, [(u_px, v_px)])
        except CalibrationError as exc:
            raise InvalidRequest(str(exc)) from None
        return {"camera": camera, "u_px": u_px, "v_px": v_px, **located_fields(xy[0], sigma[0]),
                **region_fields(inside), **self._calibration_used(camera, models)}

    def _locate_hand_eye(self, camera: str, u_px: float, v_px: float, models: dict, z_mm, flange) -> dict:
        target = f"hand-eye:{camera}"
        if z_mm is not None and not math.isfinite(z_mm):
            raise InvalidRequest(f"z_mm: {z_mm}; allowed: a finite height in mm (base frame)")
        try:
            located = HandEyeCamera(models[target])
            T = None
            if located.rides_arm:
                T = self._flange_now() if flange is None else flange_from_values(flange)
            xyz, sigma = located.locate([(u_px, v_px)], T, None if z_mm is None else z_mm * 1e-3)
        except CalibrationError as exc:
            raise InvalidRequest(str(exc)) from None
        return {"camera": camera, "u_px": u_px, "v_px": v_px, **located_fields(xyz[0], sigma[0]),
                "z_mm": float(xyz[0][2] * 1e3), "plane": "board" if z_mm is None else f"z = {z_mm:g} mm",
                "outside_calibrated_region": None, "warning": None, **self._calibration_used(target, models)}

    def _flange_now(self) -> np.ndarray:
        """The flange pose the arm reports now (idle only: beside a job it is not known at the frame)."""
        if self._worker is None:
            self._needs_daemon("locating with a camera on the wrist without the flange pose (--flange)")
        if self.worker.live_job is not None:
            raise InvalidRequest("a job is moving the arm: give the flange pose the frame was taken at (flange)")
        now = self.worker.idle_pose()
        if not now or now.get("orientation_wxyz") is None:
            raise InvalidRequest("the arm does not report a six-axis flange pose: give it (flange)")
        return flange_from_values((now["x_mm"], now["y_mm"], now["z_mm"], *now["orientation_wxyz"]))

    def _calibration_used(self, camera: str, models: dict) -> dict:
        """The active calibration of `camera` (id, version, health verdict) and the ids of every active one."""
        health = self.calstore.health().get(camera, {})
        return {"calibration_id": models[camera].get("calibration_id"),
                "version": (health.get("active") or {}).get("version"), "health": health.get("verdict", "unchecked"),
                "calibrations": {t: m.get("calibration_id") for t, m in models.items()}}

    def health(self) -> dict:
        return {"targets": self.calstore.health()}

    # -- the operator -----------------------------------------------------------------------------

    @property
    def desk(self):
        return self._desk if self._desk is not None else self._needs_daemon("operator requests")

    def operator_request(self) -> dict:
        desk = self.desk
        req, last = desk.pending(), desk.last
        backend = self.config.operator.backend
        return {"backend": backend, "answered_here": backend == "web",
                "request": dict(req.public(), job=self.worker.live_job) if req is not None else None,
                "last": last.summary() if last is not None else None}

    def operator_clicks(self, caller: Caller, request_id: int, clicks: list[tuple[int, float, float]]) -> dict:
        clicks = [(int(k), float(u), float(v)) for k, u, v in clicks]
        with self._command(caller, "operator clicks", f"operator request {request_id}", f"{len(clicks)} pairs"):
            req = self._answer(lambda desk: desk.answer_clicks(request_id, clicks, caller.who))
            return {"request": request_id, "outcome": req.outcome, "pairs": len(req.answer),
                    "job": self.worker.live_job}

    def operator_done(self, caller: Caller, request_id: int) -> dict:
        with self._command(caller, "operator done", f"operator request {request_id}"):
            req = self._answer(lambda desk: desk.confirm(request_id, caller.who))
            return {"request": request_id, "outcome": req.outcome, "job": self.worker.live_job}

    def operator_decline(self, caller: Caller, request_id: int, reason: str = "") -> dict:
        with self._command(caller, "operator decline", f"operator request {request_id}", reason):
            req = self._answer(lambda desk: desk.decline(request_id, caller.who, reason))
            return {"request": request_id, "outcome": req.outcome, "job": self.worker.live_job}

    def _answer(self, answer):
        """The desk's answer; a request that is not pending on a cell whose operator is not answered here says so."""
        try:
            return answer(self.desk)
        except AnswerRefused as exc:
            if not exc.not_pending:
                raise InvalidRequest(str(exc), [{"field": f, "problem": p} for f, p in exc.problems]) from None
            backend = self.config.operator.backend
            note = "" if backend == "web" else (f"; this cell's operator is backend {backend!r}, which is not "
                                                "answered here (operator: {backend: web} in the cell file)")
            raise Conflict(str(exc) + note, [{"field": f, "problem": p + note} for f, p in exc.problems]) from None

    # -- who may command ----------------------------------------------------------------------

    def audit(self, limit: int = 200) -> list[dict]:
        return self.jobs_store.audit_log(limit)

    def lock_status(self) -> dict:
        return self._lock.status() if self._lock is not None else self._needs_daemon("the operator lock")

    def acquire_lock(self, caller: Caller, holder: str, ttl_s: float = 300.0) -> dict:
        if self._lock is None:
            self._needs_daemon("the operator lock")
        with self._command(caller, "lock", "lock", {"holder": holder, "ttl_s": ttl_s}, check_lock=False):
            if not (math.isfinite(ttl_s) and 0 < ttl_s <= MAX_LOCK_TTL_S):
                raise InvalidRequest(f"ttl_s: {ttl_s}; allowed: seconds > 0, at most {MAX_LOCK_TTL_S:.0f} (a day)")
            info = self._lock.acquire(holder, ttl_s, caller.lock)
            if info.lock_id != caller.lock:  # taken, not renewed: the others' consoles show the new holder
                self._lock_event("taken", holder=info.holder)
            return dict(self._lock.describe(info), lock_id=info.lock_id)

    def release_lock(self, caller: Caller) -> dict:
        if self._lock is None:
            self._needs_daemon("the operator lock")
        with self._command(caller, "unlock", "lock", check_lock=False):
            held = self._lock.status()
            self._lock.release(caller.lock)
            if held.get("held"):
                self._lock_event("released", holder=held["holder"])
            return self._lock.status()

    def break_lock(self, caller: Caller, reason: str) -> dict:
        if self._lock is None:
            self._needs_daemon("the operator lock")
        reason = (reason or "").strip()
        with self._command(caller, "break lock", "lock", reason, check_lock=False) as entry:
            if not reason:
                raise InvalidRequest("reason: required: say why you break the lock (its holder is told, and the "
                                     "audit keeps it)")
            if len(reason) > 500:
                raise InvalidRequest(f"reason: {len(reason)} characters; allowed: at most 500")
            broken = self._lock.break_lock(caller.who, reason)
            entry["target"] = f"lock of {broken.holder}"
            self._lock_event("broken", **broken.public())
            return {"broken": broken.public(), "lock": self._lock.status()}

    def _lock_event(self, state: str, **data) -> None:
        """A `lock` event (never the lock id: the stream is open to every reader)."""
        if self._hub is not None:
            self._hub.publish("lock", dict(data, state=state))

    # -- the OPC UA server's client certificates: files in the store, read by the server at each session --------

    def _client_certificates(self):
        pinned_by_file = self.config.opcua.trusted_clients if self.config else ()  # `cellctl opcua --store` alone
        pinned = {p: read_certificate(p, "opcua.trusted_clients") for p in pinned_by_file}
        return ClientCertificates(self.store_dir / "opcua", pinned)

    def opcua_certificates(self) -> dict:
        return self._client_certificates().listing()

    def trust_opcua_certificate(self, caller: Caller, thumbprint: str | None = None,
                                certificate: bytes | None = None) -> dict:
        detail = {"thumbprint": thumbprint} if certificate is None else {"certificate_bytes": len(certificate)}
        # not behind the operator lock: it moves nothing, and an OPC UA client still needs a user to command
        with self._command(caller, "opcua trust", "opc ua certificate", detail, check_lock=False) as entry:
            if (thumbprint is None) == (certificate is None):
                raise InvalidRequest("give a certificate's thumbprint or the certificate itself (PEM or DER), "
                                     "one of the two")
            certificates = self._client_certificates()
            der = certificates.find(thumbprint) if certificate is None else parse_certificate(certificate,
                                                                                                "certificate")
            entry["target"] = f"opc ua certificate {thumbprint_of(der)}"
            return certificates.trust(der)

    def backup_store(self, caller: Caller) -> dict:
        from cellctl.stores.backup import backup, default_backups, read_manifest

        settings = self.config.store.backup if self.config else None
        to = settings.folder(self.store_dir) if settings else default_backups(self.store_dir)
        # not behind the operator lock: it moves nothing and changes nothing the cell serves
        with self._command(caller, "store backup", str(to), check_lock=False) as entry:
            made = backup(self.store_dir, to, self.config.cell.name if self.config else "",
                          keep=settings.keep if settings else None,
                          min_free_mb=self.config.store.min_free_mb if self.config else 0.0)
            entry["target"] = str(made)
            return {"backup": str(made), **read_manifest(made)}


AUDIT_REASON_CHARS = 400  # a refusal's reason in the audit: enough for any message of ours, not for an echoed flood


def refused_outcome(exc: ServiceError) -> str:
    """The audit's outcome of a refusal: its status and its reason, on one line ("refused 409: job 4 was ...")."""
    reason = " ".join(str(exc).split())
    if len(reason) > AUDIT_REASON_CHARS:
        reason = reason[:AUDIT_REASON_CHARS - 1] + "…"
    return f"refused {exc.status}: {reason}" if reason else f"refused {exc.status}"


def answered(job, said: str) -> dict:
    """A job command's answer: the job, and what the command did in words."""
    return dict(job.to_dict(), message=f"job {job.id}: {said}")


def refuse_a_foreign_arm(c: Calibration, config: CellFile) -> None:
    """Conflict if `c` is an `arm` calibration (an arm's own geometry) this cell's arm cannot take: one of another
    cell (another arm, however alike), or of another arm model than this cell's. Other targets are not checked."""
    if c.target != ARM_TARGET:
        return
    cell_model = arm_model_of(config)
    how = ("" if cell_model is not None else
           f"; this cell file does not state its arm's model (arm backend {config.arm.backend!r}): give it as arm.model "
           "(e.g. model: ur5e, or model: irb120) so that an arm calibration's model is checked too")
    if c.cell != config.cell.name:
        raise Conflict(f"calibration {c.id} is the arm of cell {c.cell or '(none)'!r}, and this cell is "
                       f"{config.cell.name!r}: an arm calibration is this one arm's geometry, so it is activated only "
                       f"on the cell that made it; calibrate this cell's arm here (routine arm-kinematics){how}")
    if cell_model is None:
        return
    cal_model = c.model.get("arm_model") if isinstance(c.model, dict) else None
    if cal_model != cell_model:
        made = f"a {cal_model!r} arm" if cal_model else "an arm of no stated model (its model has no arm_model)"
        raise Conflict(f"calibration {c.id} calibrated {made}, and this cell's arm is a {cell_model!r} (arm backend "
                       f"{config.arm.backend!r}): activate only an arm calibration of a {cell_model!r} arm, or "
                       "calibrate this arm (routine arm-kinematics)")


def calibration_summary(c: Calibration) -> dict:
    return {"id": c.id, "target": c.target, "routine": c.routine, "version": c.version, "created": c.created,
            "active": c.active, "cell": c.cell, "stats": c.result.get("stats", {})}


def located_fields(xy, sigma) -> dict:
    """x_mm, y_mm and sigma_um (1-σ per axis, None if the calibration keeps no covariance) of a located point (m)."""
    return {"x_mm": float(xy[0] * 1e3), "y_mm": float(xy[1] * 1e3),
            "sigma_um": float(sigma * 1e6) if math.isfinite(sigma) else None}


def region_fields(inside) -> dict:
    """outside_calibrated_region (None: unknown, the calibration keeps no region) and its warning (None inside)."""
    outside = None if inside is None else bool(not inside[0])
    return {"outside_calibrated_region": outside, "warning": OUTSIDE_REGION if outside else None}


def frame_headers(stamp: float, frame) -> dict[str, str]:
    return {"X-Frame-Id": str(frame.frame_id), "X-Captured": f"{stamp:.3f}"}


def non_finite(value: Any, where: str) -> str | None:
    """The path of the first non-finite float in `value` (dicts and lists walked), else None: JSON as
    Python reads it accepts NaN, Infinity (and 1e999), and no routine parameter may be one."""
    if isinstance(value, float):
        return None if math.isfinite(value) else where
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = non_finite(item, f"{where}.{key}")
        if found:
            return found
    return None
