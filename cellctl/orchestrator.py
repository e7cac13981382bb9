"""Runs a routine on a cell: plan -> collect (every sample persisted) -> fit -> verify.

Pause and abort take effect between steps, where the arm is settled. A run
resumes by skipping the steps whose samples are already in its folder; motion
never restarts by itself: resuming is always an explicit call.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

from calibration.routines.base import Params, Step

from .cell import Cell
from .store import RunFolder, RunFolderError


class Aborted(Exception):
    """The operator aborted the run; the samples collected so far are kept."""


class JobControl:
    """Thread-safe pause / resume / abort, honoured at step boundaries."""

    def __init__(self):
        self._running = threading.Event()
        self._running.set()
        self._abort = threading.Event()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

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


@dataclass
class Progress:
    done: int
    total: int
    cell_time_s: float
    row: dict | None
    frames: tuple = ()  # the frames the step captured (the daemon shows the latest of each camera)


class ReplayMismatch(RunFolderError):
    """Replaying a simulated run's persisted steps did not reproduce them: the world cannot be restored."""


# columns that carry measurements (the rest are time stamps and bookkeeping)
_NOT_MEASURED = {"cell_time_s", "step_rows", "image"}


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
        folder.create(manifest, routine.sample_columns + ("cell_time_s", "step_rows", "image"))
    columns = tuple(folder.manifest()["columns"])
    samples = folder.samples()
    done = {int(r["step"]) for r in samples}
    elapsed = max((float(r["cell_time_s"]) for r in samples), default=0.0)
    clock = cell.clock
    t0 = clock.now()
    if replay_sim and samples and cell.sim_world is not None:
        _replay(routine, params, cell, plan, samples, done)
        elapsed = 0.0  # the world's clock now stands where the uninterrupted run's would
    if on_progress:
        on_progress(Progress(len(done), len(plan), elapsed, None))
    for step in plan:
        if step.index in done:
            continue
        control.checkpoint()
        cell.begin_step(step.index)
        result = routine.execute(step, params, cell.devices, samples)
        stamp = {"cell_time_s": elapsed + clock.now() - t0}
        # overlays are the routine's figures (model drawn on the image): kept even without save_images
        kept = [f for f in result.frames or () if save_images or f.camera_id.startswith("overlay-")]
        if kept:
            stamp["image"] = ";".join(folder.save_image(f"step{step.index:05d}_{f.camera_id}.png", f.image)
                                      for f in kept)
        # step_rows lets a reopened folder drop a step that a crash cut part way through writing
        rows = [dict(r, step_rows=len(result.rows), **stamp) for r in result.rows]
        folder.append_many(rows, columns)
        samples += rows
        done.add(step.index)
        row = rows[-1]
        if on_progress:
            on_progress(Progress(len(done), len(plan), row["cell_time_s"], row, tuple(result.frames or ())))
    return samples


def _replay(routine, params: Params, cell: Cell, plan: list[Step], samples: list[dict], done: set[int]) -> None:
    """Re-execute the persisted steps in plan order on the simulated world (see `collect`)."""
    by_step: dict[int, list[dict]] = {}
    for r in samples:
        by_step.setdefault(int(r["step"]), []).append(r)
    history: list[dict] = []
    for step in plan:
        if step.index not in done:
            continue  # a step cut short before: it runs for real after the replay
        cell.begin_step(step.index)
        result = routine.execute(step, params, cell.devices, list(history))
        kept = by_step[step.index]
        if len(result.rows) != len(kept) or any(not _same(a, b) for a, b in zip(result.rows, kept)):
            raise ReplayMismatch(f"replaying step {step.index} on the simulated world did not reproduce its "
                                 "persisted samples; the run cannot be resumed exactly")
        history += kept


def _same(new: dict, kept: dict) -> bool:
    """Equal as persisted: both through the CSV cell form (exact float repr)."""
    from .store import _cell

    return all(_cell(v) == _cell(kept.get(k)) for k, v in new.items() if k not in _NOT_MEASURED)
