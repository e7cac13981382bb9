"""An immediate pause, an abort or a shutdown stops the arm inside a step, not at the next step boundary.

The latch is at the orchestrator level (every device command of a routine passes `JobControl.command`), so it
holds whatever the driver's own `stop()` does when nothing is moving: tested on a driver-like fake whose stop,
like a real controller's, only acts on a motion under way, and on the daemon (in-process, the simulated micro
cell) with the pause or the shutdown arriving between the move and the capture of a step.
"""

from __future__ import annotations

import threading
import time

import pytest

from drivers.interfaces import MotionStopped, Pose
from drivers.sim.devices import SimArm, SimCamera

from calibration.routines.base import Devices, Step, StepResult

from cellctl.core.orchestrator import Halted, JobControl, collect
from cellctl.stores.run_folder import RunFolder

from tests.support.daemon import SEED, SMALL, write_cell_file
from tests.support.wait import eventually

# -- the mechanism, on driver-like fakes (no simulated world) ----------------------------------------------


class LikeARealArm:
    """stop() acts only on the motion under way (as on a controller); a move clears it as it starts."""

    name = "arm"

    def __init__(self, move_s: float = 0.0):
        self.moves: list[Pose] = []
        self.stops = 0
        self.move_s = move_s
        self._stop = threading.Event()
        self.entered = threading.Event()  # the command reached the driver
        self.go = threading.Event()
        self.go.set()

    def move_linear(self, target, speed=None):
        self.entered.set()
        self.go.wait(5)
        self._stop.clear()  # a stop sent before the motion started is lost, like on a controller
        self.moves.append(target)
        if self._stop.wait(self.move_s):
            raise MotionStopped("arm: stopped part way")

    def pose(self):
        return self.moves[-1] if self.moves else Pose(0, 0, 0, 0)

    def stop(self):
        self.stops += 1
        self._stop.set()


class FakeCamera:
    name = "cam"
    resolution = (10, 10)

    def __init__(self, on_capture=None):
        self.captures = 0
        self.on_capture = on_capture

    def capture(self, timeout_s: float = 2.0):
        self.captures += 1
        if self.on_capture:
            self.on_capture()
        return None


class TwoMovesPerStep:
    """A routine whose steps move, capture, move again (like a pick: above, down, grip, up)."""

    name = "two-moves"
    sample_columns = ("step", "n")

    def plan(self, params, devices):
        return [Step(i, "visit", {}) for i in range(3)]

    def inputs(self, params, devices):
        return ()

    def execute(self, step, params, devices, history=()):
        devices.arm.move_linear(Pose(step.index, 0, 0, 0))
        devices.camera("cam").capture()
        devices.arm.move_linear(Pose(step.index, 1, 0, 0))
        return StepResult({"step": step.index, "n": len(history)}, [])


class FakeCell:
    def __init__(self, arm, cam):
        self.devices = Devices(arm, {"cam": cam})
        self.config = type("C", (), {"cell": type("N", (), {"name": "fake"})()})()
        self.cell_text = ""
        self.sim_world = None
        self.operator = None  # a cell whose routines ask nobody
        self.clock = type("Clock", (), {"now": staticmethod(time.monotonic)})()

    def begin_step(self, key):
        pass


class NoParams:
    def model_dump(self, mode="json"):
        return {}


def test_a_halt_during_a_capture_stops_the_second_move_of_the_step(tmp_path):
    arm = LikeARealArm()
    control = JobControl()
    cam = FakeCamera()
    cam.on_capture = lambda: cam.captures == 2 and control.halt(arm.stop)  # in step 1, between its two moves
    folder = RunFolder(tmp_path / "run")
    with pytest.raises(Halted, match="arm: move_linear not started"):
        collect(TwoMovesPerStep(), NoParams(), FakeCell(arm, cam), folder, seed=None, control=control)
    # step 0 whole, step 1's first move only: nothing moved after the halt although the arm's stop was a no-op
    assert arm.moves == [Pose(0, 0, 0, 0), Pose(0, 1, 0, 0), Pose(1, 0, 0, 0)]
    assert [r["step"] for r in folder.samples()] == [0]  # the cut step is not kept: it is redone on resume
    # nothing starts until an explicit resume lifts the halt
    with pytest.raises(Halted):
        control.command("arm", "move_linear", arm.move_linear, Pose(9, 9, 0, 0))
    control.resume()
    control.command("arm", "move_linear", arm.move_linear, Pose(9, 9, 0, 0))
    assert arm.moves[-1] == Pose(9, 9, 0, 0)


def test_a_stop_lost_by_the_driver_is_sent_again_while_the_command_is_in_flight():
    """The halt lands after the latch let a move through but before the motion started (its stop is lost)."""
    arm = LikeARealArm(move_s=5.0)
    arm.go.clear()
    control = JobControl()
    outcome: list = []

    def run():
        try:
            control.command("arm", "move_linear", arm.move_linear, Pose(1, 0, 0, 0))
            outcome.append("completed")
        except MotionStopped as exc:
            outcome.append(exc)

    t = threading.Thread(target=run)
    t.start()
    assert arm.entered.wait(5)
    control.halt(arm.stop)  # arrives before the move clears its stop flag: the driver drops it
    t0 = time.monotonic()
    arm.go.set()
    t.join(3)
    assert not t.is_alive() and isinstance(outcome[0], MotionStopped)
    assert time.monotonic() - t0 < 1.0  # stopped by the re-sent stop, not after the 5 s move
    assert arm.stops >= 2


# -- the daemon, in-process, on the simulated micro cell ------------------------------------------------


@pytest.fixture
def daemon(tmp_path):
    from cellctl.startup.daemon import Daemon

    d = Daemon(write_cell_file(tmp_path, realtime_factor=0.0))
    d.start()
    yield d
    d.stop("test over")


class Recorder:
    """Counts the sim arm's moves and the cameras' captures; runs `hook` right after move number `at` returns."""

    def __init__(self, monkeypatch, at: int, hook):
        self.moves = self.captures = 0
        self.at, self.hook = at, hook
        self.moves_at_hook = self.captures_at_hook = None
        move, capture = SimArm.move_linear, SimCamera.capture

        def move_linear(arm, target, speed=None):
            self.moves += 1
            move(arm, target, speed)
            if self.moves == self.at:
                self.hook()
                self.moves_at_hook, self.captures_at_hook = self.moves, self.captures

        def counted_capture(cam, timeout_s=2.0):
            self.captures += 1
            return capture(cam, timeout_s)

        monkeypatch.setattr(SimArm, "move_linear", move_linear)
        monkeypatch.setattr(SimCamera, "capture", counted_capture)


def wait_state(daemon, job_id: int, states: set[str], timeout: float = 60.0):
    return eventually(lambda: (job := daemon.jobs.get(job_id)).state in states and job, timeout=timeout,
                      what=lambda: f"job {job_id} in {sorted(states)} (it is {daemon.jobs.get(job_id).state})")


def test_an_immediate_pause_stops_the_arm_inside_the_step_and_resumes_exactly(daemon, monkeypatch, reference):
    job = daemon.jobs.submit("virtual-grid", SMALL, SEED, "tester@test")
    # step 6 = move 7: the pause lands after its move, before its capture (each step: move, pose, capture)
    rec = Recorder(monkeypatch, 7, lambda: daemon.worker.pause(job.id, True, "tester@test"))
    daemon.worker.wake()
    paused = wait_state(daemon, job.id, {"paused", "done", "faulted"})
    assert paused.state == "paused" and "immediate" in paused.reason and "redone on resume" in paused.reason
    assert (rec.moves_at_hook, rec.captures_at_hook) == (7, 6)
    time.sleep(0.3)
    assert (rec.moves, rec.captures) == (7, 6)  # no capture, no move after the pause: the step was cut
    assert [r["step"] for r in RunFolder(paused.run_dir).samples()] == list(range(6))
    # the resumed job replays its 6 steps on a fresh world, redoes step 6, ends as if never paused
    daemon.worker.resume(job.id, "tester@test")
    done = wait_state(daemon, job.id, {"done", "faulted", "paused"})
    assert done.state == "done", done.reason
    ref_result, ref_samples = reference
    rows = RunFolder(done.run_dir).samples()
    assert [r["step"] for r in rows] == list(range(24))
    assert [{k: v for k, v in r.items() if k != "image"} for r in rows] == \
        [{k: v for k, v in r.items() if k != "image"} for r in ref_samples]
    assert done.result["stats"] == ref_result["stats"] and done.result["cell_time_s"] == ref_result["cell_time_s"]


def test_an_abort_stops_the_arm_inside_the_step(daemon, monkeypatch):
    job = daemon.jobs.submit("virtual-grid", SMALL, SEED, "tester@test")
    rec = Recorder(monkeypatch, 4, lambda: daemon.worker.abort(job.id, "tester@test"))
    daemon.worker.wake()
    aborted = wait_state(daemon, job.id, {"aborted", "done", "faulted", "paused"})
    assert aborted.state == "aborted" and "samples kept" in aborted.reason
    assert (rec.moves, rec.captures) == (4, 3)
    assert [r["step"] for r in RunFolder(aborted.run_dir).samples()] == [0, 1, 2]


def test_shutdown_stops_the_arm_inside_the_step_and_leaves_the_job_paused(daemon, monkeypatch):
    """What SIGTERM does (service.Server.handle_exit -> Worker.shutdown), arriving between a move and a capture."""
    job = daemon.jobs.submit("virtual-grid", SMALL, SEED, "tester@test")
    arrived = threading.Event()

    def hold_until_shutdown():  # in the worker thread: wait for the shutdown to have latched the job's control
        arrived.set()
        eventually(lambda: getattr(daemon.worker.current[1].request, "kind", None) == "shutdown", timeout=10,
                   every=0.01, what="the shutdown latched in the job's control")

    rec = Recorder(monkeypatch, 5, hold_until_shutdown)
    daemon.worker.wake()
    assert arrived.wait(30)
    stop_calls = []
    real_stop = SimArm.stop
    monkeypatch.setattr(SimArm, "stop", lambda arm: (stop_calls.append(1), real_stop(arm)))
    daemon.worker.shutdown("daemon stopped by signal 15")
    assert not daemon.worker.alive
    job = daemon.jobs.get(job.id)
    assert job.state == "paused" and "signal 15" in job.reason
    assert stop_calls  # the arm was told to stop
    assert (rec.moves, rec.captures) == (5, 4)  # and nothing was commanded after the shutdown began
    assert [r["step"] for r in RunFolder(job.run_dir).samples()] == [0, 1, 2, 3]
