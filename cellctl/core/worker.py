"""The one worker thread that runs jobs on the cell, and the cell it owns.

Jobs run one at a time through `run_routine` (or `run_sequence`), so a job in the
daemon is the same computation as `cellctl run`: same plan, same samples, same
result for the same seed.

Simulated cells: every job (and every resumption that re-enters the plan) starts on
a fresh world of the job's seed, exactly as `cellctl run` builds one; a resumption
replays the persisted steps on that world first (`collect(replay_sim=True)`) so the
world's state (arm, placed spheres, clock) is the uninterrupted run's. Real cells:
the devices connected at start-up are used as they are; a faulted device is only
reconnected when an operator asks (POST /cell/reconnect).
"""

from __future__ import annotations

import gc
import logging
import math
import threading
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from drivers.interfaces import DeviceError, DeviceState, MotionStopped

from calibration.errors import CalibrationError
from calibration.routines import is_sequence, routine_class, sequence
from calibration.routines.base import JudgesCalibrations

from cellctl.config import CellFile
from cellctl.core.cell import Cell
from cellctl.core.events import EventHub
from cellctl.core.orchestrator import Aborted, JobControl, Progress
from cellctl.core.runs import routine_params, run_routine, run_sequence, with_seed
from cellctl.errors import Conflict, InsufficientStorage, InvalidRequest, NotFound
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.disk_space import disk_full, is_disk_full
from cellctl.stores.jobs import Job, JobError, JobStore, folder_records, refusal
from cellctl.stores.run_folder import RunFolder

log = logging.getLogger("cellctl.core.worker")


class Suspended(Exception):
    """The job stops where it is and is kept paused (daemon shutting down)."""


@dataclass(frozen=True)
class StopRequest:
    """Why a live job is to stop: the one value the worker and its control act on.

    pause: at the next step boundary; pause-now: the arm stops now, the cut step is redone on
    resume; abort: the arm stops now, the samples are kept; shutdown: the daemon stops, the job
    is kept paused."""

    kind: Literal["pause", "pause-now", "abort", "shutdown"]
    reason: str


class DaemonControl(JobControl):
    """JobControl that knows why it stops (`request`) and whether the job is holding at a step boundary."""

    def __init__(self, on_hold):
        super().__init__()
        self._on_hold = on_hold
        self.request: StopRequest | None = None
        self.holding = False  # paused for real, at a step boundary (the job's state says "paused")

    def suspend(self, reason: str, stop=None) -> None:
        """Shutdown: no device command starts from now on, `stop` stops the cell, the job ends paused."""
        self.request = StopRequest("shutdown", reason)
        self.halt(stop)
        self._running.set()

    def _shutting_down(self) -> None:
        if self.request is not None and self.request.kind == "shutdown":
            raise Suspended(self.request.reason)

    def checkpoint(self) -> None:
        self._shutting_down()
        if self.paused:
            self._on_hold(self.request.reason if self.request else "paused")
        super().checkpoint()
        self._shutting_down()


class CellHolder:
    """The daemon's cell: connected at start, device by device, so one bad device is reported, not fatal."""

    def __init__(self, config: CellFile, cell_text: str):
        self.config, self.cell_text = config, cell_text
        self.mutex = threading.RLock()
        self.errors: dict[str, str] = {}
        self.last_pose: dict | None = None
        self.cell = self._build(config)
        self.connect_all()

    @property
    def simulated(self) -> bool:
        return self.config.sim is not None

    def _build(self, config: CellFile) -> Cell:
        return Cell(config, self.cell_text)

    def named_devices(self):
        return self.cell.named_devices()

    def connect_all(self, only: str | None = None) -> dict[str, str]:
        """(Re)connect every device, or the one named; returns the errors by device. A simulated cell driven
        through real drivers first gets its protocol simulators (sim.servers), on its world."""
        with self.mutex:
            try:
                self.cell.start_sim_servers()
            except DeviceError as exc:  # its devices then say they cannot connect, each by name
                self.errors["sim.servers"] = str(exc)
                log.warning("protocol simulators did not start", extra={"error": str(exc)})
            else:
                self.errors.pop("sim.servers", None)
            for _kind, name, dev in self.named_devices():
                if only is not None and name != only:
                    continue
                try:
                    dev.close()  # a faulted link is dropped before it is made again
                except Exception:  # noqa: BLE001, S110 - closing is best effort; connect() reports the state
                    pass
                try:
                    dev.connect()
                    self.errors.pop(name, None)
                except Exception as exc:  # noqa: BLE001 - any failure is reported as the device's state
                    self.errors[name] = f"{type(exc).__name__}: {exc}"
                    log.warning("device did not connect", extra={"device": name, "error": self.errors[name]})
            return dict(self.errors)

    def fresh_sim(self, seed: int | None) -> Cell:
        """A new simulated world for a job (the `cellctl run` semantics); replaces the current cell."""
        with self.mutex:
            self.cell.close()
            self.cell = self._build(with_seed(self.config, seed))
            # the closed cell's protocol simulators (pymodbus, asyncio, their threads) leave reference cycles that
            # hold its world, tens of MB of images, until Python's rare full collection: a daemon that builds a
            # world per job grew by that much a job (tools/soak.py); collected here, its memory stays flat
            gc.collect()
            self.connect_all()
            return self.cell

    def not_ready(self) -> list[str]:
        return [f"{name} is {dev.state.value}" for _, name, dev in self.named_devices()
                if dev.state is not DeviceState.READY]

    def status(self) -> list[dict]:
        out = []
        for kind, name, dev in self.named_devices():
            backend = (self.config.cameras[name].backend if kind == "camera"
                       else getattr(self.config, kind).backend)
            entry = {"name": name, "kind": kind, "backend": backend, "state": dev.state.value}
            if name in self.errors:
                entry["error"] = self.errors[name]
            out.append(entry)
        return out

    def read_pose(self) -> dict | None:
        """Ask the arm for its pose (from the thread that may talk to it: the worker, or any when idle)."""
        arm = self.cell.arm
        if arm.state is not DeviceState.READY:
            return None
        try:
            p = arm.pose()
        except Exception:  # noqa: BLE001 - a status read must not fail the status page
            return None
        self.last_pose = {"x_mm": p.x * 1e3, "y_mm": p.y * 1e3, "z_mm": p.z * 1e3,
                          "alpha_deg": math.degrees(p.alpha), "read_at": time.time()}
        if p.orientation is not None:  # a six-axis arm's flange
            self.last_pose["orientation_wxyz"] = [float(v) for v in p.orientation]
        return self.last_pose

    def stop(self) -> None:
        try:
            self.cell.stop()
        except Exception:
            log.exception("stopping the cell")

    def close(self) -> None:
        with self.mutex:
            self.cell.close()


class Worker:
    """Runs the queued jobs one at a time, and owns what a live job touches: the cell, its frames, its state.

    Everything the front ends ask of the cell goes through the intent methods below (pause, resume,
    acknowledge, abort; idle_pose, reconnect, latest_frame, activate), each under the worker's own lock,
    so "which job is live" and what may be done beside it change together."""

    def __init__(self, jobs: JobStore, cells: CellHolder, calstore: CalibrationStore, hub: EventHub):
        self.jobs, self.cells, self.calstore, self.hub = jobs, cells, calstore, hub
        self._guard = threading.RLock()  # "which job is live" and its control change together
        self.current: tuple[int, DaemonControl] | None = None
        self.frames: dict[str, tuple[float, object]] = {}
        self.steps: dict[str, tuple[int, str, dict]] = {}  # camera -> (job, run folder, last row of its latest step)
        self.manual: str | None = None  # a manual move in progress (core/manual.py): who and what; no job starts
        self._waiting_for_disk: int | None = None  # the queued job that could not start on a full disk (logged once)
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="cellctl-worker", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def live_job(self) -> int | None:
        current = self.current
        return current[0] if current is not None else None

    def shutdown(self, reason: str, timeout: float = 10.0) -> None:
        """Stop the arm, pause the live job (recorded), end the thread."""
        self._stopping.set()
        with self._guard:
            if self.current is not None:
                self.current[1].suspend(reason, self.cells.stop)
            elif self.manual is not None:  # a manual move: the arm stops now (its heartbeats end with the server)
                self.cells.stop()
        self._wake.set()
        self._thread.join(timeout)

    # -- what the cell may do beside (or instead of) a job ------------------------------------

    def _refuse_while_live(self, what: str) -> None:
        if self.current is not None:
            raise JobError(f"job {self.current[0]} is using the cell; {what}")
        if self.manual is not None:
            raise JobError(f"{self.manual} is moving the arm; {what}")

    @contextmanager
    def manual_claim(self, who: str, what: str):
        """The arm for a manual move (a jog, a move-to, the vacuum) while no job runs or holds the cell: refused
        (Conflict) beside a live job or another manual move. No job starts until the move has ended. Unlike
        `idle_cell` the guard is not held meanwhile, so status reads and camera frames go on during the move."""
        with self._guard:
            if self.current is not None:
                job = self.jobs.get(self.current[0])
                raise Conflict(f"job {job.id} ({job.routine}, {job.state}) is using the cell: no manual motion "
                               "beside it; wait until it ends, or abort it")
            if self.manual is not None:
                raise Conflict(f"{self.manual} is moving the arm: stop it first")
            self.manual = f"a manual {what} by {who}"
        try:
            yield self.cells.cell
        finally:
            with self._guard:
                self.manual = None
            self._wake.set()  # a job queued meanwhile starts now

    @contextmanager
    def idle_cell(self, what: str, beside_manual: bool = False):
        """The cell, for a front end's own use of its devices (a manual move, a live frame, a device self-test),
        while no job runs or holds it: refused (Conflict naming the job and `what` to do) beside a live or held
        job, or beside a manual move unless `beside_manual` (a camera frame while the arm is jogged). No job starts
        until the block ends, and the devices are used from this thread only meanwhile."""
        with self._guard:
            if self.current is not None:
                job = self.jobs.get(self.current[0])
                raise Conflict(f"job {job.id} ({job.routine}, {job.state}) is using the cell; {what}")
            if self.manual is not None and not beside_manual:
                raise Conflict(f"{self.manual} is moving the arm; {what}")
            with self.cells.mutex:
                yield self.cells.cell

    def idle_pose(self) -> dict | None:
        """The arm's reported pose: asked now when idle, else as the worker last read it (with its time).
        Never asked beside a job: drivers are used from one thread at a time."""
        with self._guard:
            if self.current is not None or self.manual is not None:
                return self.cells.last_pose
            with self.cells.mutex:
                return self.cells.read_pose()

    def reconnect(self, device: str | None = None) -> dict[str, str]:
        """(Re)connect every device, or the one named; returns the errors by device."""
        names = [name for _, name, _ in self.cells.named_devices()]
        if device is not None and device not in names:
            raise InvalidRequest(f"device: {device!r} is not a device of this cell (devices: {', '.join(names)})")
        with self._guard:
            self._refuse_while_live("pause or abort it and wait until it has stopped before reconnecting")
            return self.cells.connect_all(device)

    def latest_frame(self, camera: str) -> tuple[float, object]:
        """(time, frame): a new capture when the cell is idle, else the live job's latest frame of `camera`."""
        with self._guard:  # held: no job starts while we capture
            seen = self.frames.get(camera)
            if self.current is not None or self.cells.not_ready():
                # a live job owns the cell: never capture beside it (in simulation that would change its world)
                if seen is None:
                    raise NotFound(f"camera {camera} has taken no frame in this job yet")
                return seen
            with self.cells.mutex:
                frame = self.cells.cell.cameras[camera].capture()
            seen = self.frames[camera] = (time.time(), frame)
            return seen

    def activate(self, cal_id: int):
        """Make a calibration version active; refused while a job is live (it reads the active ones)."""
        self.calstore.get(cal_id)
        with self._guard:
            self._refuse_while_live("it reads the active calibrations: activate when it is done")
            return self.calstore.activate(cal_id)

    def deactivate(self, cal_id: int):
        """Take a calibration version out of use; refused while a job is live, as activate is."""
        self.calstore.get(cal_id)
        with self._guard:
            self._refuse_while_live("it reads the active calibrations: deactivate when it is done")
            return self.calstore.deactivate(cal_id)

    # -- commands on jobs ------------------------------------------------------------------

    def _control_of(self, job_id: int) -> DaemonControl | None:
        cur = self.current
        return cur[1] if cur is not None and cur[0] == job_id else None

    # Each returns the job and what the command did, in words: a stop asked of a live job takes effect later, so
    # the job's state alone (still "running") would not say it.

    def pause(self, job_id: int, immediate: bool, who: str) -> tuple[Job, str]:
        with self._guard:
            control = self._control_of(job_id)
            if control is None:
                job = self.jobs.transition(job_id, "paused", f"paused by {who} before it ran", who,
                                           allowed_from={"queued"}, command="pause")
                self._publish_state(job)
                return job, "paused before it started; resume it to queue it again"
            if control.request is not None:
                raise refusal(self.jobs.get(job_id), "pause")
            how = "immediate" if immediate else "at the step boundary"
            control.request = StopRequest("pause-now" if immediate else "pause", f"paused by {who} ({how})")
            control.pause()
            if immediate:
                # the arm stops now and no further device command starts, even inside the step;
                # a step cut short is redone on resume
                control.halt(self.cells.stop)
            job = self.jobs.get(job_id)
            if job.state == "paused":
                return job, "paused"
            return job, ("the arm is stopped now; the job pauses, and the step cut short is redone on resume"
                         if immediate else "pause requested: it pauses at the next step boundary")

    def resume(self, job_id: int, who: str) -> tuple[Job, str]:
        with self._guard:
            control = self._control_of(job_id)
            if control is not None and control.holding:
                control.holding = False
                job = self.jobs.transition(job_id, "running", f"resumed by {who}", who, allowed_from={"paused"},
                                           command="resume")
                control.request = None
                control.resume()  # also lifts the halt of an immediate pause that ended at a step boundary
                said = "resumed: running again"
            elif control is not None and control.request is not None and control.request.kind == "pause":
                control.request = None
                control.resume()  # a deferred pause not yet reached is called off
                return self.jobs.get(job_id), "the pause it had not reached yet is called off: it runs on"
            elif control is not None:
                raise refusal(self.jobs.get(job_id), "resume", "stopping" if control.paused else "running")
            else:
                job = self.jobs.get(job_id)
                if job.state == "faulted" or (job.state == "paused" and not job.acknowledged):
                    raise refusal(job, "resume")
                job = self.jobs.transition(job_id, "queued", f"resumed by {who}", who, allowed_from={"paused"},
                                           command="resume")
                self._wake.set()
                said = "resumed: queued, it runs when the cell is free (on from the samples it kept)"
            self._publish_state(job)
            return job, said

    def acknowledge(self, job_id: int, who: str) -> tuple[Job, str]:
        with self._guard:
            job = self.jobs.transition(job_id, "paused", f"fault acknowledged by {who}; resume to continue", who,
                                       allowed_from={"faulted"}, acknowledged=True, command="acknowledge")
            self._publish_state(job)
            return job, "fault acknowledged: it is paused and nothing moves; resume it to continue"

    def abort(self, job_id: int, who: str) -> tuple[Job, str]:
        with self._guard:
            control = self._control_of(job_id)
            if control is None:
                job = self.jobs.transition(job_id, "aborted", f"aborted by {who}; samples kept", who, command="abort")
                self._publish_state(job)
                return job, "aborted; its samples are kept"
            control.request = StopRequest("abort", f"aborted by {who}")
            control.abort()
            control.halt(self.cells.stop)  # arm stopped now, nothing more starts; the samples so far are kept
            return self.jobs.get(job_id), "the arm is stopped now; the job ends aborted, its samples kept"

    # -- the thread -------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            if self._stopping.is_set():
                break
            with self._guard:
                job = self.jobs.next_queued() if self.manual is None else None  # a manual move ends first
                if job is None:
                    continue
                control = DaemonControl(lambda reason, job_id=job.id: self._hold(job_id, reason))
                try:
                    job = self.jobs.transition(job.id, "running", "started" if not job.progress else "resumed",
                                               "daemon", allowed_from={"queued"})
                except JobError:
                    continue
                except Exception as exc:
                    if not is_disk_full(exc):
                        raise
                    # the job stays queued and is tried again (new jobs and resumptions are refused meanwhile);
                    # said once, not at every try (twice a second)
                    if self._waiting_for_disk != job.id:
                        log.error("a queued job cannot start: the disk is full", extra={"job": job.id})
                        self._waiting_for_disk = job.id
                    continue
                self._waiting_for_disk = None
                self.current = (job.id, control)
            self._publish_state(job)
            try:
                self._run(job, control)
            except Exception:
                log.exception("worker: recording the end of a job failed", extra={"job": job.id})
            finally:
                with self._guard:
                    self.current = None

    def _hold(self, job_id: int, reason: str) -> None:
        with self._guard:
            control = self._control_of(job_id)
            if control is None or control.holding:
                return
            job = self.jobs.transition(job_id, "paused", reason, "daemon", allowed_from={"running"})
            control.holding = True
        self._publish_state(job)

    def _run(self, job: Job, control: DaemonControl) -> None:
        run_dir = Path(job.run_dir)
        t_wall = time.monotonic()
        state, reason, result = "done", "finished", None
        try:
            if job.progress and self.jobs.outbox.enabled and any(
                    e["to"] == "faulted" and e["reason"].startswith("DiskFull") for e in self.jobs.history(job.id)):
                # a step can reach the run folder and not its record (the disk filled in between): sent again,
                # the plant keeps each once
                self.jobs.resend(job.id, *folder_records(job))
            problems = self.cells.not_ready()
            if problems:
                raise DeviceError("; ".join(problems) + ": reconnect (POST /cell/reconnect), then resume")
            if is_sequence(job.routine):
                result = self._run_sequence(job, control, run_dir)
            else:
                resume = RunFolder(run_dir).exists()
                cell = self.cells.fresh_sim(job.seed) if self.cells.simulated else self.cells.cell
                result = run_routine(job.routine, self.cells.config, self.cells.cell_text, run_dir, seed=job.seed,
                                     overrides=job.params, resume=resume, save_images=job.save_images,
                                     control=control, store=self.calstore,
                                     on_progress=self._progress_for(job, None), cell=cell, replay_sim=True)
        except Suspended as exc:
            state, reason = "paused", str(exc)
        except Aborted:
            state, reason = "aborted", (control.request.reason if control.request else "aborted") + "; samples kept"
        except MotionStopped as exc:
            state, reason = _stopped(control.request, exc)
        except DeviceError as exc:
            state, reason = "faulted", f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # noqa: BLE001 - any failure ends the job as faulted, with its reason
            if is_disk_full(exc):  # the reserve is freed first, so that the fault can be recorded
                exc = disk_full(self.jobs.path.parent, exc)
            state, reason = "faulted", f"{type(exc).__name__}: {exc}"
            if isinstance(exc, (CalibrationError, InsufficientStorage)):
                # a fault of the cell or its data, said in its reason (no sphere picked, a full disk): not a bug
                log.warning("job faulted", extra={"job": job.id, "reason": reason})
            else:
                log.error("job failed", extra={"job": job.id, "trace": traceback.format_exc()})
        if state == "faulted":
            self.cells.stop()
        with self._guard:
            if self.jobs.get(job.id).state != state:  # a held pause that ends in shutdown is paused already
                job = self.jobs.transition(job.id, state, reason, "daemon", acknowledged=(state != "faulted"),
                                           result=result)
            job = self.jobs.get(job.id)
            # no longer live, in the same step as the state change: a command that sees the new state
            # (ack, resume) must not find the job still "current"
            self.current = None
        log.info("job ended", extra={"job": job.id, "state": state, "reason": reason,
                                     "wall_s": round(time.monotonic() - t_wall, 3)})
        self._publish_state(job)
        alarm = self._alarm(job, result)
        if alarm is not None:  # a judge of the calibrations found them wanting: the console raises an alarm
            self.hub.publish("health", {"job": job.id, **alarm})

    @staticmethod
    def _alarm(job: Job, result: dict | None) -> dict | None:
        if not result or is_sequence(job.routine):
            return None
        routine = routine_class(job.routine)()
        return routine.alarm(result) if isinstance(routine, JudgesCalibrations) else None

    def _run_sequence(self, job: Job, control: DaemonControl, run_dir: Path) -> dict:
        resume = run_dir.exists() and any(run_dir.glob("[0-9][0-9]-*"))

        def cell_factory():
            return self.cells.fresh_sim(job.seed) if self.cells.simulated else self.cells.cell

        done = run_sequence(job.routine, self.cells.config, self.cells.cell_text, run_dir, seed=job.seed,
                            resume=resume, store=self.calstore, on_step=lambda item: self._progress_for(job, item),
                            control=control, replay_sim=True, cell_factory=cell_factory,
                            save_images=job.save_images,
                            on_item_done=lambda item, result: self.jobs.record_result(job.id, item, result))
        return done["summary"]

    # -- progress ----------------------------------------------------------------------

    def _progress_for(self, job: Job, item: str | None):
        routine_name = (item or job.routine).partition(".")[0]
        first: dict = {}
        residual = _RunningResidual(routine_name, job, self.cells.config, item)
        fleet = self.cells.config.fleet
        interval = fleet.mqtt.progress_interval_s if fleet is not None and fleet.mqtt is not None else 2.0
        announced = [-math.inf]

        def on_progress(p: Progress) -> None:
            if not first:
                first.update(done=p.done, cell=p.cell_time_s)
            for frame in p.frames:
                self.frames[frame.camera_id] = (time.time(), frame)
            if p.row:  # what the console's overlay marks as this step's features
                folder = str(Path(job.run_dir) / _folder_of(job, item))
                for cam in {p.row.get("camera")} - {None, ""} or {f.camera_id for f in p.frames}:
                    self.steps[cam] = (job.id, folder, dict(p.row))
            self.cells.read_pose()  # the worker owns the arm while the job runs: the API shows this copy
            ran = p.done - first["done"]
            rate = (p.cell_time_s - first["cell"]) / ran if ran > 0 else None
            info = {"job": job.id, "routine": job.routine, "item": item, "step": p.done, "total": p.total,
                    "cell_time_s": p.cell_time_s,
                    "eta_cell_s": rate * (p.total - p.done) if rate is not None else None,
                    "residual_um": residual.update(p, Path(job.run_dir) / _folder_of(job, item))}
            if p.step is None:
                self.jobs.set_progress(job.id, info)
            else:  # the step's samples go to the plant with its progress (the event stream's, now and then)
                announce = p.done == p.total or time.monotonic() >= announced[0] + interval
                self.jobs.record_step(job.id, item, p.step, list(p.rows), info, announce)
                if announce:
                    announced[0] = time.monotonic()
            self.hub.publish("progress", info)

        return on_progress

    def _publish_state(self, job: Job) -> None:
        log.info("job state", extra={"job": job.id, "state": job.state, "reason": job.reason})
        self.hub.publish("state", {"job": job.id, "state": job.state, "reason": job.reason})
        live = self.live_job
        try:
            self.jobs.record_cell("idle" if live is None else self.jobs.get(live).state, live)
        except Exception as exc:
            if not is_disk_full(exc):
                raise
            # the plant's view of the cell (the newest wins) waits for the next change; the job's state is kept
            log.warning("the cell's state was not recorded for the plant: the disk is full", extra={"job": job.id})


def _stopped(request: StopRequest | None, exc: MotionStopped) -> tuple[str, str]:
    """The job's end state and reason when a motion was stopped: by our own request, or by the cell."""
    if request is None:
        return "faulted", f"MotionStopped: {exc}"
    if request.kind == "abort":
        return "aborted", request.reason + " (arm stopped); samples kept"
    return "paused", request.reason + "; the step cut short is redone on resume"


def _folder_of(job: Job, item: str | None) -> str:
    return "." if item is None else sequence(job.routine).folder(item)


class _RunningResidual:
    """The routine's own fit on the samples so far, about ten times a run: the residual (µm) as it settles.

    The fit is a pure function of the persisted samples, so it cannot change what the job measures."""

    def __init__(self, routine: str, job: Job, config: CellFile, item: str | None):
        self.routine = routine_class(routine)()
        overrides = dict(job.params) if item is None else ({"area": item.partition(".")[2]} if "." in item else {})
        try:
            self.params = routine_params(self.routine, config, overrides)
        except Exception:  # noqa: BLE001 - no params, no residual
            self.params = None
        self.last: float | None = None
        self.next_at = 0

    def update(self, p: Progress, folder: Path) -> float | None:
        if self.params is None or p.done < max(self.next_at, 4):
            return self.last
        self.next_at = p.done + max(p.total // 10, 1)
        try:
            samples = RunFolder(folder).samples()
            stats = self.routine.fit(samples, self.params, None).stats
            value = (stats.get("calibration") or {}).get("mean_um")
            self.last = float(value) if value is not None else self.last
        except Exception:  # noqa: BLE001, S110 - too few samples for this routine's fit yet
            pass
        return self.last
