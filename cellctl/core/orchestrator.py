"""Runs a routine on a cell: plan -> collect (every sample persisted) -> fit -> verify.

Pause and abort take effect between steps, where the arm is settled. An
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

An operator who is a person (the web console's, a terminal's: `RecordsAnswers`) is
never asked twice: what they answered in a step is persisted with the step's rows (the
column `operator`, JSON, on its first row), and a resumed run takes it from there.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from dataclasses import dataclass
from typing import Callable, Protocol, runtime_checkable

from drivers.interfaces import MotionStopped

from calibration.routines.base import Devices, Params, Step, TargetsAccuracy

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
            on_progress: Callable[[Progress], None] | None = None, replay_sim: bool = False) -> list[dict]:
    """Execute the plan into `folder` and return every sample (old and new).

    `replay_sim`: when resuming on a simulated cell built afresh (a restarted daemon), first re-execute
    the persisted steps on the world, discarding what they measure, so that the world's state (arm
    position, placed spheres, clock) is the one an uninterrupted run would have; each replayed step
    is checked against its persisted rows. Real cells are never replayed.
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
    if replay_sim and samples and cell.sim_world is not None:
        _replay(routine, params, cell, devices, plan, samples, done, person, answered)
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
    for position, step in enumerate(plan):
        if met and targeted.budget(step):
            continue
        if step.index in done:
            judged += persisted[step.index]
            if targeted is not None and targeted.budget(step) and not met:
                met = bool(targeted.enough(list(judged), params))
                total = len(plan) - _skipped(targeted, plan[position + 1:], done) if met else total
            continue
        control.checkpoint()
        cell.begin_step(step.index)
        result = routine.execute(step, params, devices, samples)
        stamp = {"cell_time_s": elapsed + clock.now() - t0}
        # overlays are the routine's figures (model drawn on the image): kept even without save_images
        kept = [f for f in result.frames or () if save_images or f.camera_id.startswith("overlay-")]
        if kept:
            stamp["image"] = ";".join(folder.save_image(f"step{step.index:05d}_{f.camera_id}.png", f.image)
                                      for f in kept)
        # step_rows lets a reopened folder drop a step that a crash cut part way through writing
        rows = [dict(r, step_rows=len(result.rows), **stamp) for r in result.rows]
        if person is not None and rows and person.answers():
            rows[0][OPERATOR_COLUMN] = json.dumps(to_jsonable(person.answers()))
        folder.append_many(rows, columns)
        samples += rows
        judged += rows
        done.add(step.index)
        if targeted is not None and targeted.budget(step) and not met:
            met = bool(targeted.enough(list(judged), params))
            total = len(plan) - _skipped(targeted, plan[position + 1:], done) if met else total
        row = rows[-1]
        if on_progress:
            on_progress(Progress(len(done), total, row["cell_time_s"], row, tuple(result.frames or ()),
                                 step.index, tuple(rows)))
    return samples


def _skipped(targeted, rest: list[Step], done: set[int]) -> int:
    """How many of the steps after a met target are skipped: its budget's, not done before."""
    return sum(1 for s in rest if targeted.budget(s) and s.index not in done)


def _replay(routine, params: Params, cell: Cell, devices: Devices, plan: list[Step], samples: list[dict],
            done: set[int], person: RecordsAnswers | None = None, answered: dict | None = None) -> None:
    """Re-execute the persisted steps in plan order on the simulated world (see `collect`); a person's
    requests take the answers recorded with each step."""
    by_step: dict[int, list[dict]] = {}
    for r in samples:
        by_step.setdefault(int(r["step"]), []).append(r)
    history: list[dict] = []
    for step in plan:
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


def _same(new: dict, kept: dict) -> bool:
    """Equal as persisted: both through the CSV cell form (exact float repr)."""
    return all(csv_cell(v) == csv_cell(kept.get(k)) for k, v in new.items() if k not in _NOT_MEASURED)
