"""Runs a routine on a cell: plan -> collect (every sample persisted) -> fit -> verify.

Pause and abort take effect between steps, where the arm is settled (with a step's measurement overlapping
the next move, also between that move and its capture). An
immediate stop (`JobControl.halt`: immediate pause, abort, shutdown) also takes
effect inside a step: from then on no device command starts (the routine sees
every device through a guard that checks the latch before each command), and the
cell's stop is sent again until a command let through just before the latch has
returned. This sits above the drivers, so it holds for every backend, whatever
its own `stop()` does when nothing is moving. A run resumes by skipping the steps
whose samples are already in its folder; motion never restarts by itself:
resuming is always an explicit call.

A routine with an accuracy target (`TargetsAccuracy`) is asked after each of its
calibration steps whether the samples so far meet it; once they do, the rest of its
calibration budget is skipped and its verification steps run. The answer depends on
the samples alone, so a resumed run (persisted samples judged in plan order) and a
replayed one stop at the same step.

A routine whose steps split (`Pipelines`: approach, capture, measure) has each step's measurement, and the
target's refit on it, processed in a worker thread while the arm makes the next step's approach; the step is
persisted, in plan order, before the next one is captured, and before a pause, an abort or a fault of that approach
takes effect. When it meets the target, the next budget step has been approached already: that step is not
captured, and a replayed run makes that approach too (the same rule, from the persisted samples).

An operator who is a person (the web console's, a terminal's: `RecordsAnswers`) is
never asked twice: what they answered in a step is persisted with the step's rows (the
column `operator`, JSON, on its first row), and a resumed run takes it from there.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Protocol, runtime_checkable

from drivers.interfaces import MotionStopped

from calibration.routines.base import Devices, Params, Pipelines, Step, StepResult, TargetsAccuracy

from cellctl.core.cell import Cell
from cellctl.stores.run_folder import RunFolder, RunFolderError, csv_cell, to_jsonable


class Aborted(Exception):
    """The operator aborted the run; the samples collected so far are kept."""


class Halted(MotionStopped):
    """A device command refused before it started: the job was told to stop now."""


RESTOP_INTERVAL_S = 0.05
RESTOP_FOR_S = 2.0


class JobControl:
    """Thread-safe pause / resume / abort, honoured at step boundaries; `halt` stops inside a step too."""

    def __init__(self):
        self._running = threading.Event()
        self._running.set()
        self._abort = threading.Event()
        self._halt = threading.Event()
        self._commands = threading.Lock()  # a command's latch check and a halt never interleave
        self._in_flight = 0  # device commands started and not yet returned

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        with self._commands:
            self._halt.clear()  # the explicit resume is the only thing that lifts an immediate stop
        self._running.set()

    def halt(self, stop: Callable[[], None] | None = None) -> None:
        """Stop now: no device command starts from here on (`Halted`), and `stop` (the cell's) is called.

        A command that passed the latch just before may reach its driver after this first stop (a
        driver's stop acts on the motion under way, if any): while such a command is in flight and the
        halt holds, `stop` is sent again every 50 ms (for at most 2 s)."""
        with self._commands:
            self._halt.set()
            busy = self._in_flight > 0
            if stop is not None:
                stop()
        if stop is not None and busy:
            threading.Thread(target=self._restop, args=(stop,), name="cellctl-restop", daemon=True).start()

    def _restop(self, stop: Callable[[], None]) -> None:
        deadline = time.monotonic() + RESTOP_FOR_S
        while time.monotonic() < deadline:
            time.sleep(RESTOP_INTERVAL_S)
            with self._commands:  # under the lock: a resume in between lifts the halt before any new command
                if not (self._halt.is_set() and self._in_flight > 0):
                    return
                stop()

    @property
    def halted(self) -> bool:
        return self._halt.is_set()

    def command(self, device: str, name: str, call: Callable, *args, **kwargs):
        """Run one device command unless the job was halted (then `Halted`, and nothing is sent)."""
        with self._commands:
            if self._halt.is_set():
                raise Halted(f"{device}: {name} not started: the job was told to stop now "
                             "(immediate pause, abort or shutdown)")
            self._in_flight += 1
        try:
            return call(*args, **kwargs)
        finally:
            with self._commands:
                self._in_flight -= 1

    def abort(self) -> None:
        self._abort.set()
        self._running.set()

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def checkpoint(self) -> None:
        while not self._running.wait(0.1):
            pass
        if self._abort.is_set():
            raise Aborted("aborted by the operator between steps")


# what a routine may still ask a device after a halt: reads and the stop itself
_QUERIES = frozenset({"pose", "joints", "status", "stop"})


class _GuardedDevice:
    """A device as a routine sees it inside `collect`: every command goes through `JobControl.command`."""

    def __init__(self, device, control: JobControl):
        self._device, self._control = device, control

    def __getattr__(self, name: str):
        attr = getattr(self._device, name)
        if name.startswith("_") or name in _QUERIES or not callable(attr):
            return attr
        label = str(getattr(self._device, "name", type(self._device).__name__))

        def guarded(*args, **kwargs):
            return self._control.command(label, name, attr, *args, **kwargs)

        return guarded


def guarded_devices(devices: Devices, control: JobControl) -> Devices:
    """The same devices, each command refused once `control` is halted (the calibrations are shared)."""
    def wrap(device):
        return None if device is None else _GuardedDevice(device, control)

    return dataclasses.replace(devices, arm=wrap(devices.arm), gripper=wrap(devices.gripper),
                               operator=wrap(devices.operator),
                               cameras={n: wrap(c) for n, c in devices.cameras.items()})


@runtime_checkable
class RecordsAnswers(Protocol):
    """An operator who is a person (backends `web` and `console`), as against a simulated one, who acts in
    the simulated world and is simply replayed. What the person answered in a step is persisted with the
    step's rows, so a resumed run asks nobody twice: a step replayed on a fresh simulated world takes its
    answers from the record (`replay`), and a step skipped on resume (a real cell) hands over what its
    answers established, such as how the cameras are mounted (`recall`)."""

    def answers(self) -> list[dict]:
        """What was answered since the step began (cell.begin_step), JSON-able, in order."""

    def replay(self, answers: list[dict] | None) -> None:
        """Answer the step's requests from these, in order, asking nobody; None: ask as usual again."""

    def recall(self, answers: list[dict]) -> None:
        """Take in what the steps done before the resume established (they are not executed again): their
        answers, in plan order."""


@dataclass
class Progress:
    done: int
    total: int
    cell_time_s: float
    row: dict | None
    frames: tuple = ()  # the frames the step captured (the daemon shows the latest of each camera)
    step: int | None = None  # the plan's index of the step just done
    rows: tuple = ()  # every row it gave (in samples.csv already)


class ReplayMismatch(RunFolderError):
    """Replaying a simulated run's persisted steps did not reproduce them: the world cannot be restored."""


# columns that carry measurements (the rest are time stamps and bookkeeping)
_NOT_MEASURED = {"cell_time_s", "step_rows", "image", "operator"}
OPERATOR_COLUMN = "operator"  # a person's answers of the step (RecordsAnswers), JSON, on the step's first row


def collect(routine, params: Params, cell: Cell, folder: RunFolder, *, seed: int | None,
            resume: bool = False, save_images: bool = False, control: JobControl | None = None,
            on_progress: Callable[[Progress], None] | None = None, replay_sim: bool = False,
            pipeline: bool = True) -> list[dict]:
    """Execute the plan into `folder` and return every sample (old and new).

    `replay_sim`: when resuming on a simulated cell built afresh (a restarted daemon), first re-execute
    the persisted steps on the world, discarding what they measure, so that the world's state (arm
    position, placed spheres, clock) is the one an uninterrupted run would have; each replayed step
    is checked against its persisted rows. Real cells are never replayed.

    `pipeline` (a `Pipelines` routine): a step's measurement, and the target's refit on it, are processed in a
    worker thread while the arm makes the next step's approach (the steps that `overlap`); then they are joined,
    the step persisted and the target's decision taken, and only then is the next step captured. Its rows are persisted before any pause, abort or fault
    of that approach takes effect. When the joined step meets the target, the next budget step has already been
    approached: it is not captured (a resume replays that approach too). False: each step whole, in turn.
    """
    control = control or JobControl()
    person = cell.operator if isinstance(cell.operator, RecordsAnswers) else None
    plan = routine.plan(params, cell.devices)
    plan_dicts = [s.to_dict() for s in plan]
    inputs = {t: cell.devices.calibrations[t].get("calibration_id") for t in routine.inputs(params, cell.devices)
              if t in cell.devices.calibrations}
    manifest = {"routine": routine.name, "params": params.model_dump(mode="json"), "seed": seed, "inputs": inputs,
                "cell": cell.config.cell.name, "cell_file": cell.cell_text, "plan": plan_dicts,
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if resume:
        old = folder.manifest()
        for key in ("routine", "params", "seed", "inputs", "plan"):
            if old.get(key) != manifest[key]:
                raise RunFolderError(f"cannot resume {folder.path}: its {key} differs from this run's")
    else:
        folder.create(manifest, routine.sample_columns + ("cell_time_s", "step_rows", "image")
                      + ((OPERATOR_COLUMN,) if person is not None else ()))
    columns = tuple(folder.manifest()["columns"])
    if OPERATOR_COLUMN not in columns:
        person = None  # a run folder from before answers were kept, or of another operator: asked as before
    samples = folder.samples()
    done = {int(r["step"]) for r in samples}
    answered = {int(r["step"]): json.loads(r[OPERATOR_COLUMN]) for r in samples if r.get(OPERATOR_COLUMN)}
    elapsed = max((float(r["cell_time_s"]) for r in samples), default=0.0)
    clock = cell.clock
    t0 = clock.now()
    devices = guarded_devices(cell.devices, control)
    split = routine if isinstance(routine, Pipelines) else None
    overlapping = split if pipeline else None
    if replay_sim and samples and cell.sim_world is not None:
        _replay(routine, params, cell, devices, plan, samples, done, person, answered, overlapping)
        elapsed = 0.0  # the world's clock now stands where the uninterrupted run's would
    elif person is not None:
        person.recall([a for step in plan if step.index in done for a in answered.get(step.index, [])])
    if on_progress:
        on_progress(Progress(len(done), len(plan), elapsed, None))
    # a routine with an accuracy target stops its calibration budget once `enough` says so (TargetsAccuracy);
    # judged on the samples of the steps done so far in plan order, persisted or new: a resume decides alike
    targeted = routine if isinstance(routine, TargetsAccuracy) else None
    persisted: dict[int, list[dict]] = {}
    for r in samples:
        persisted.setdefault(int(r["step"]), []).append(r)
    judged: list[dict] = []
    met, total = False, len(plan)
    pending: _Measuring | None = None  # the step captured last, its measurement in the worker thread

    def judging(step: Step) -> bool:
        return targeted is not None and targeted.budget(step) and not met

    def judge(position: int, step: Step, decided: bool | None = None) -> None:
        """`decided`: what `enough` said of the samples so far, asked beside the next approach already."""
        nonlocal met, total
        if judging(step):
            met = bool(targeted.enough(list(judged), params)) if decided is None else decided
            total = len(plan) - _skipped(targeted, plan[position + 1:], done) if met else total

    def measure_and_judge(step: Step, captured, history: list[dict], stamp: dict, before: list[dict] | None):
        """The worker's part of a step: its measurement, and the target's refit on it (`before`: the samples the
        decision adds it to; None: no decision to make)."""
        result = split.measure(step, captured, params, history)
        if before is None:
            return result, None
        return result, bool(targeted.enough(before + [dict(r, step_rows=len(result.rows), **stamp)
                                                      for r in result.rows], params))

    def persist(step: Step, position: int, result: StepResult, stamp: dict, answers: list[dict],
                decided: bool | None = None) -> None:
        # overlays are the routine's figures (model drawn on the image): kept even without save_images
        kept = [f for f in result.frames or () if save_images or f.camera_id.startswith("overlay-")]
        if kept:
            stamp = dict(stamp, image=";".join(folder.save_image(f"step{step.index:05d}_{f.camera_id}.png", f.image)
                                               for f in kept))
        # step_rows lets a reopened folder drop a step that a crash cut part way through writing
        rows = [dict(r, step_rows=len(result.rows), **stamp) for r in result.rows]
        if person is not None and rows and answers:
            rows[0][OPERATOR_COLUMN] = json.dumps(to_jsonable(answers))
        folder.append_many(rows, columns)
        samples.extend(rows)
        judged.extend(rows)
        done.add(step.index)
        judge(position, step, decided)
        row = rows[-1]
        if on_progress:
            on_progress(Progress(len(done), total, row["cell_time_s"], row, tuple(result.frames or ()),
                                 step.index, tuple(rows)))

    def settle() -> None:
        """Join the measurement in flight, if any, and persist it (a failed one raises: nothing is persisted)."""
        nonlocal pending
        if pending is not None:
            measuring, pending = pending, None
            result, decided = measuring.result.result()
            persist(measuring.step, measuring.position, result, measuring.stamp, measuring.answers, decided)

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="cellctl-measure") as worker:
        try:
            for position, step in enumerate(plan):
                if met and targeted.budget(step):
                    continue
                if step.index in done:
                    settle()
                    judged += persisted[step.index]
                    judge(position, step)
                    continue
                if pending is not None and split.overlaps(step):
                    if control.paused:
                        settle()  # the step before is kept before the pause holds the run
                    control.checkpoint()
                    cell.begin_step(step.index)
                    split.approach(step, params, devices, list(samples))  # beside the measurement in flight
                    settle()
                    if met and targeted.budget(step):
                        continue  # approached while the step before met the target: not captured
                    if not control.halted:  # an immediate stop cuts the step instead: its capture is refused
                        control.checkpoint()  # a pause or an abort asked meanwhile holds the arm here, settled
                else:
                    settle()
                    if met and targeted.budget(step):
                        continue
                    control.checkpoint()
                    cell.begin_step(step.index)
                    if split is None:
                        result = routine.execute(step, params, devices, samples)
                        persist(step, position, result, {"cell_time_s": elapsed + clock.now() - t0},
                                person.answers() if person is not None else [])
                        continue
                    split.approach(step, params, devices, list(samples))
                history = list(samples)
                captured = split.capture(step, params, devices, history)
                stamp = {"cell_time_s": elapsed + clock.now() - t0}
                answers = person.answers() if person is not None else []
                if overlapping is None:
                    persist(step, position, split.measure(step, captured, params, history), stamp, answers)
                    continue
                pending = _Measuring(step, position, stamp, answers, worker.submit(
                    measure_and_judge, step, captured, history, stamp, list(judged) if judging(step) else None))
            settle()
        except BaseException:
            settle()  # a pause, an abort or a fault of the next approach: the step measured before is kept
            raise
    return samples


@dataclass
class _Measuring:
    """A step captured, its measurement running in the worker thread (`collect`)."""

    step: Step
    position: int
    stamp: dict
    answers: list
    result: Future  # of (its StepResult, what the target's refit decided or None)


def _skipped(targeted, rest: list[Step], done: set[int]) -> int:
    """How many of the steps after a met target are skipped: its budget's, not done before."""
    return sum(1 for s in rest if targeted.budget(s) and s.index not in done)


def _replay(routine, params: Params, cell: Cell, devices: Devices, plan: list[Step], samples: list[dict],
            done: set[int], person: RecordsAnswers | None = None, answered: dict | None = None,
            overlapping: Pipelines | None = None) -> None:
    """Re-execute the persisted steps in plan order on the simulated world (see `collect`); a person's
    requests take the answers recorded with each step. `overlapping`: the routine, when the run measured beside
    the next approach: a step that met the target is followed by the next budget step's approach, as it was."""
    by_step: dict[int, list[dict]] = {}
    for r in samples:
        by_step.setdefault(int(r["step"]), []).append(r)
    # the target's decisions matter here only for the approaches made beside a measurement
    targeted = routine if overlapping is not None and isinstance(routine, TargetsAccuracy) else None
    history: list[dict] = []
    met = False
    for position, step in enumerate(plan):
        if step.index not in done:
            continue  # a step cut short before: it runs for real after the replay
        cell.begin_step(step.index)
        if person is not None:
            person.replay((answered or {}).get(step.index, []))
        try:
            result = routine.execute(step, params, devices, list(history))
        finally:
            if person is not None:
                person.replay(None)
        kept = by_step[step.index]
        if len(result.rows) != len(kept) or any(not _same(a, b) for a, b in zip(result.rows, kept)):
            raise ReplayMismatch(f"replaying step {step.index} on the simulated world did not reproduce its "
                                 "persisted samples; the run cannot be resumed exactly")
        history += kept
        if targeted is not None and targeted.budget(step) and not met:
            met = bool(targeted.enough(list(history), params))
            after = plan[position + 1] if position + 1 < len(plan) else None
            if met and after is not None and targeted.budget(after) and after.index not in done \
                    and overlapping.overlaps(after):
                cell.begin_step(after.index)  # the approach the run made while this step was measured
                overlapping.approach(after, params, devices, history[:len(history) - len(kept)])


def _same(new: dict, kept: dict) -> bool:
    """Equal as persisted: both through the CSV cell form (exact float repr)."""
    return all(csv_cell(v) == csv_cell(kept.get(k)) for k, v in new.items() if k not in _NOT_MEASURED)
