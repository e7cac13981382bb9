"""A step's measurement overlaps the next step's move (issue 31): `collect` processes step k's capture in a worker
thread while the arm approaches step k+1, then persists k and only then captures k+1.

The samples are those of a run without the overlap; what is measured is persisted whatever stops the next
approach; a target met while the next budget step was approached skips that step's capture, and a run cut
anywhere and resumed on a fresh simulated world replays that approach too."""

from __future__ import annotations

import functools
import shutil
import threading

import pytest

from drivers.interfaces import MotionStopped, Pose

from calibration.routines.base import Pipelines, Step, StepResult, execute_split
from calibration.routines.micro.virtual_grid import CAL

from cellctl.core import orchestrator, runs
from cellctl.core.orchestrator import Aborted, JobControl, collect
from cellctl.core.runs import run_routine
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.run_folder import RunFolder

from tests.daemon.test_stop import FakeCell, NoParams

GRID = {"rows": 5, "cols": 5, "n_verify": 8}  # a budget of 2 x 25 grid samples (test_targeted.py's SMALL)
SWEEP = {"rows": 1, "cols": 3, "step_deg": 60.0, "n_verify": 4}  # a budget of 3 x 6 turns
OUT_OF_REACH = 0.5  # µm: the whole budget is spent, no step is approached and not captured
WAIT_S = 10.0  # a bound on waiting for an event that must come (a failure, not a pace)


def samples_csv(folder) -> str:
    return (folder / "samples.csv").read_text()


def without_overlap(monkeypatch):
    """run_routine's runs from here on measure each step before the next move (collect(pipeline=False))."""
    monkeypatch.setattr(runs, "collect", functools.partial(orchestrator.collect, pipeline=False))


# -- the same samples with and without the overlap -----------------------------------------------------------------

@pytest.fixture(scope="module")
def calibrated_store(microcell, tmp_path_factory):
    """Camera 1 calibrated (the rotation sweep measures with it)."""
    folder = tmp_path_factory.mktemp("store")
    config, text = microcell
    store = CalibrationStore(folder / "store")
    run_routine("virtual-grid", config, text, folder / "vg", seed=0, store=store,
                overrides={"rows": 5, "cols": 5, "passes": 1, "n_verify": 2, "target_um": 0.001})
    store.close()
    return folder / "store"


def run_with_store(microcell, store_dir, out, routine, overrides, **kwargs):
    shutil.copytree(store_dir, out.parent / f"{out.name}-store")
    store = CalibrationStore(out.parent / f"{out.name}-store")
    try:
        return run_routine(routine, *microcell, out, seed=3, store=store, overrides=overrides, **kwargs)
    finally:
        store.close()


@pytest.mark.parametrize("routine, overrides", [("virtual-grid", GRID), ("rotation-sweep", SWEEP)])
def test_the_whole_budget_gives_the_same_samples_csv_with_and_without_the_overlap(
        microcell, calibrated_store, tmp_path, monkeypatch, routine, overrides):
    overrides = dict(overrides, target_um=OUT_OF_REACH)
    overlapped = run_with_store(microcell, calibrated_store, tmp_path / "overlapped", routine, overrides)
    without_overlap(monkeypatch)
    plain = run_with_store(microcell, calibrated_store, tmp_path / "plain", routine, overrides)
    assert samples_csv(tmp_path / "overlapped") == samples_csv(tmp_path / "plain")
    assert overlapped["cell_time_s"] == plain["cell_time_s"]
    assert overlapped["model"] == plain["model"]


@pytest.mark.parametrize("routine, overrides", [("virtual-grid", GRID), ("rotation-sweep", SWEEP)])
def test_a_met_target_costs_one_approach_and_changes_no_measurement(microcell, calibrated_store, tmp_path,
                                                                     monkeypatch, routine, overrides):
    overlapped = run_with_store(microcell, calibrated_store, tmp_path / "overlapped", routine, overrides)
    without_overlap(monkeypatch)
    plain = run_with_store(microcell, calibrated_store, tmp_path / "plain", routine, overrides)
    assert overlapped["stats"]["target"]["met"] and plain["stats"]["target"]["met"]
    a, b = RunFolder(tmp_path / "overlapped").samples(), RunFolder(tmp_path / "plain").samples()
    assert [r["step"] for r in a] == [r["step"] for r in b]
    met_at = max(int(r["step"]) for r in a if r["set"] == CAL)
    # the same rows, time stamps included, up to the step that met the target
    assert [r for r in a if int(r["step"]) <= met_at] == [r for r in b if int(r["step"]) <= met_at]
    # after it, the same measurements (the world's noise is keyed by step); only the cell time has the approach
    # made while that step was measured
    measured = [k for k in a[0] if k not in ("cell_time_s", "image", "step_rows")]
    assert [[r[k] for k in measured] for r in a] == [[r[k] for k in measured] for r in b]
    assert overlapped["cell_time_s"] > plain["cell_time_s"]
    print(f"\n{routine}: {overlapped['cell_time_s'] - plain['cell_time_s']:.2f} s of cell time for the approach "
          "made while the target was met")


# -- the cut and resumed run -----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def whole(microcell, tmp_path_factory):
    folder = tmp_path_factory.mktemp("whole")
    result = run_routine("virtual-grid", *microcell, folder / "run", seed=5, overrides=GRID)
    assert result["stats"]["target"]["met"]
    return folder / "run", result


@pytest.mark.parametrize("cut", ["inside", "before-met", "at-met", "after-met"])
def test_a_run_cut_anywhere_and_resumed_on_a_fresh_world_equals_the_uninterrupted_one(microcell, tmp_path, whole,
                                                                                      cut):
    whole_folder, whole_result = whole
    met_at = whole_result["stats"]["target"]["samples"] - 1  # the budget step that met the target
    # progress.done counts steps persisted: at == met_at + 1 is the met step's own progress (the approach of the
    # next budget step already made), at == met_at the step before it (the met step then captured, then the abort)
    at = {"inside": 5, "before-met": met_at, "at-met": met_at + 1, "after-met": met_at + 3}[cut]
    control = JobControl()

    def abort_at(progress):
        if progress.done == at:
            control.abort()

    with pytest.raises(Aborted):
        run_routine("virtual-grid", *microcell, tmp_path / "cut", seed=5, overrides=GRID, control=control,
                    on_progress=abort_at)
    assert len({r["step"] for r in RunFolder(tmp_path / "cut").samples()}) >= at  # what was measured is kept
    resumed = run_routine("virtual-grid", *microcell, tmp_path / "cut", seed=5, overrides=GRID, resume=True)
    assert samples_csv(tmp_path / "cut") == samples_csv(whole_folder)  # time stamps and all
    for key in ("stats", "model", "cell_time_s"):
        assert resumed[key] == whole_result[key]


# -- the mechanism, on a fake cell -----------------------------------------------------------------------------------

class Arm:
    name = "arm"

    def __init__(self, log, fail_at=None):
        self.log, self.fail_at = log, fail_at
        self.at = Pose(0, 0, 0, 0)

    def move_linear(self, target, speed=None):
        if target.x == self.fail_at:
            raise MotionStopped("arm: protective stop (fake)")
        self.at = target

    def pose(self):
        return self.at


class Camera:
    name = "cam"
    resolution = (10, 10)

    def capture(self, timeout_s: float = 2.0):
        return None


class Overlapping:
    """Three visits; measure(k) waits until approach(k+1) has begun (only a measurement beside it can return)."""

    name = "overlapping"
    sample_columns = ("step", "history")

    def __init__(self, log, fail_measure_at=None, pause=None):
        self.log, self.fail_measure_at, self.pause = log, fail_measure_at, pause
        self.beside = pause is None  # paused before the next approach: the measurement must return alone
        self.approached = {k: threading.Event() for k in range(4)}

    def plan(self, params, devices):
        return [Step(i, "visit", {}) for i in range(3)]

    def inputs(self, params, devices):
        return ()

    def execute(self, step, params, devices, history=()):
        return execute_split(self, step, params, devices, history)

    def approach(self, step, params, devices, history):
        self.log.append(("approach", step.index))
        self.approached[step.index].set()
        devices.arm.move_linear(Pose(step.index, 0, 0, 0))

    def capture(self, step, params, devices, history):
        self.log.append(("capture", step.index))
        if self.pause is not None and step.index == 1:
            self.pause()
        devices.camera("cam").capture()
        return step.index

    def measure(self, step, captured, params, history):
        if step.index == self.fail_measure_at:
            raise ValueError("no feature (fake)")
        if self.beside and step.index < 2 and not self.approached[step.index + 1].wait(WAIT_S):
            raise AssertionError(f"measure({step.index}) ran alone: approach({step.index + 1}) never began beside it")
        self.log.append(("measured", step.index))
        return StepResult({"step": step.index, "history": len(history)})

    def overlaps(self, step):
        return True


def run_fake(tmp_path, routine, arm, log, control=None):
    def persisted(progress):
        if progress.step is not None:
            log.append(("persisted", progress.step))

    folder = RunFolder(tmp_path / "run")
    collect(routine, NoParams(), FakeCell(arm, Camera()), folder, seed=None, control=control,
            on_progress=persisted)
    return folder


def test_the_measurement_runs_beside_the_next_approach_and_the_next_capture_waits_for_it(tmp_path):
    log: list = []
    routine = Overlapping(log)
    assert isinstance(routine, Pipelines)
    folder = run_fake(tmp_path, routine, Arm(log), log)
    assert log == [("approach", 0), ("capture", 0), ("approach", 1), ("measured", 0), ("persisted", 0),
                   ("capture", 1), ("approach", 2), ("measured", 1), ("persisted", 1),
                   ("capture", 2), ("measured", 2), ("persisted", 2)]
    # each measurement saw every step before it: the one before was persisted before this one was captured
    assert [(r["step"], r["history"]) for r in folder.samples()] == [(0, 0), (1, 1), (2, 2)]


def test_a_fault_in_the_next_approach_keeps_the_step_measured_beside_it(tmp_path):
    log: list = []
    with pytest.raises(MotionStopped, match="protective stop"):
        run_fake(tmp_path, Overlapping(log), Arm(log, fail_at=2), log)
    assert [r["step"] for r in RunFolder(tmp_path / "run").samples()] == [0, 1]
    assert ("persisted", 1) in log and ("capture", 2) not in log


def test_a_failed_measurement_is_raised_and_not_persisted(tmp_path):
    log: list = []
    with pytest.raises(ValueError, match="no feature"):
        run_fake(tmp_path, Overlapping(log, fail_measure_at=1), Arm(log), log)
    assert [r["step"] for r in RunFolder(tmp_path / "run").samples()] == [0]  # resume re-runs step 1


def test_a_pause_at_the_checkpoint_first_persists_the_step_measured(tmp_path):
    log: list = []
    control = JobControl()
    routine = Overlapping(log, pause=control.pause)  # paused while step 1 is captured
    paused_with_step_1 = threading.Event()
    outcome: list = []

    def persisted(progress):
        if progress.step is not None:
            log.append(("persisted", progress.step))
            if progress.step == 1 and control.paused:
                paused_with_step_1.set()

    def run():
        try:
            collect(routine, NoParams(), FakeCell(Arm(log), Camera()), RunFolder(tmp_path / "run"), seed=None,
                    control=control, on_progress=persisted)
        except Aborted as exc:
            outcome.append(exc)

    worker = threading.Thread(target=run)
    worker.start()
    assert paused_with_step_1.wait(WAIT_S)  # step 1 kept while the run is held, before step 2 moved
    assert [r["step"] for r in RunFolder(tmp_path / "run").samples()] == [0, 1]
    control.abort()
    worker.join(WAIT_S)
    assert not worker.is_alive() and outcome
    assert ("approach", 2) not in log
