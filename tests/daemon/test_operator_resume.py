"""A person is never asked twice, and the time they take is cell time.

What a person (the web operator, the terminal's) answered in a step is kept with the step's samples (the
`operator` column of samples.csv); a resumed run takes it from there:
- on a simulated cell, whose world is rebuilt and the persisted steps replayed, each replayed request takes
  its recorded answer and nobody is asked;
- on a real cell, where the persisted steps are skipped, what their answers established (the cameras'
  mounting) is taken back, so a later step does not ask for it again.
The time a request waits for its answer advances the simulated clock, so a report's cell time includes it
(and a replay restores it).

In-process here (the cell and its web operator's desk, answered by a "person" thread; the terminal's operator
with a slow stdin); through the real daemon, paused, restarted and resumed: test_operator_daemon_resume.py.
"""

from __future__ import annotations

import copy
import json
import shutil
import threading
import time
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from drivers.interfaces import DeviceError, Pose
from drivers.operators.web import desk_for
from drivers.sim.base import SimClock

from calibration.routines import routine_class
from calibration.routines.base import Params, Step, StepResult

from cellctl.config import load_cell_file
from cellctl.core.cell import Cell
from cellctl.core.orchestrator import Aborted, JobControl, RecordsAnswers, collect
from cellctl.core.runs import routine_params, with_seed
from cellctl.stores.run_folder import RunFolder

from tests.support.daemon import ROOT
from tests.support.operator import write_vr_cell

SEED = 3
# vr-experiments, small: 0 reference (align by hand), 1 fig7 (clicks), 2 mount top at 28 deg, 3 approach stop 0
# (clicks), 4 approach stop 1, 5 mount top back to nominal, 6 side nominal, 7 top nominal, 8 ellipse (clicks).
# Nobody jogs a simulated arm: the "hand alignment" is where the arm starts, 20 in in front of the receptacle
EXPERIMENTS = {"fig7_runs": 1, "n_runs": 1, "angles_deg": [28.0], "distances_in": [20.0, 2.0], "views": [],
               "standoff_in": 20.0}


class Person(threading.Thread):
    """Answers the desk's requests as a person at the console would: confirms an instruction, clicks the model
    points where the simulated world shows them (on a copy of the world: its noise and clock stay untouched)."""

    def __init__(self, desk, delay_s: float = 0.0):
        super().__init__(daemon=True)
        self.desk, self.delay_s = desk, delay_s
        self.world = None  # the world of the cell being run (set by the test)
        self.asked: list[tuple] = []  # (kind, camera, object, inter_camera_angle_deg) of every request answered
        self.stopping = threading.Event()
        self.errors: list[str] = []

    def run(self) -> None:
        while not self.stopping.is_set():
            req = self.desk.pending()
            if req is None:
                time.sleep(0.005)
                continue
            d = req.details
            self.asked.append((req.kind, d.get("camera"), d.get("object"), d.get("inter_camera_angle_deg")))
            time.sleep(self.delay_s)
            try:
                if req.kind == "click_points":
                    self.desk.answer_clicks(req.id, self.clicks(req), "person@console")
                else:
                    self.desk.confirm(req.id, "person@console")
            except Exception as exc:  # noqa: BLE001 - the job ends saying why, the test fails on it
                self.errors.append(repr(exc))
                self.desk.decline(req.id, "person@console", f"the test's person failed: {exc!r}")

    def clicks(self, req) -> list[tuple[int, float, float]]:
        world = copy.copy(self.world)
        world.rng, world.clock = np.random.default_rng(req.id), SimClock()
        obj = req.details["object"]
        return world.clicks(req.details["camera"], obj, world.model_solids[obj].vertices, req.details["at_least"])

    def kinds_since(self, mark: int) -> list[tuple]:
        return self.asked[mark:]


@pytest.fixture
def person(tmp_path):
    cell_file = write_vr_cell(tmp_path, timeout_s=120)
    config, text = load_cell_file(cell_file)
    desk = desk_for(config.store_path())
    desk.attach(lambda state, summary: None)  # served, as the daemon's API serves it
    p = Person(desk)
    p.start()
    yield p, config, text
    p.stopping.set()
    p.join(5)
    assert p.errors == []


def experiments(config, out: Path, cell: Cell, **kwargs) -> list[dict]:
    """Its samples (collected only: the fit's figures are not what this is about)."""
    routine = routine_class("vr-experiments")()
    return collect(routine, routine_params(routine, config, EXPERIMENTS), cell, RunFolder(out), seed=SEED, **kwargs)


def test_a_resumed_vr_run_asks_the_web_operator_nothing_answered_before(person, tmp_path):
    p, config, text = person
    config = with_seed(config, SEED)
    out = tmp_path / "run"
    control = JobControl()

    def cut_after_the_mount(progress):
        if progress.done == 3:
            control.abort()

    with Cell(config, text) as cell:
        p.world = cell.sim_world
        with pytest.raises(Aborted):
            experiments(config, out, cell, control=control, on_progress=cut_after_the_mount)
    assert [k[0] for k in p.asked] == ["align_by_hand"] + ["click_points"] * 4 + ["mount_camera"]
    assert p.asked[-1][1:] == ("top", None, 28.0)
    first = RunFolder(out).samples()
    assert sorted({r["step"] for r in first}) == [0, 1, 2]
    # each step's answers are kept with its rows: who answered what, and how long it waited
    recorded = {r["step"]: json.loads(r["operator"]) for r in first if r.get("operator")}
    assert [a["verb"] for a in recorded[0]] == ["align_by_hand"]
    assert [(a["verb"], a["camera"], a["object"]) for a in recorded[1]] == [
        ("click_points", cam, obj) for cam in ("side", "top") for obj in ("oru", "receptacle")]
    assert all(a["outcome"] == "answered" and a["by"] == "person@console" and a["waited_s"] >= 0
               and len(a["clicks"]) >= 5 for a in recorded[1])
    assert recorded[2][0]["verb"] == "mount_camera" and recorded[2][0]["inter_camera_angle_deg"] == 28.0
    shutil.copytree(out, tmp_path / "sim-run")

    # a real cell (or a daemon restarted on one): the persisted steps are skipped, not replayed; the camera the
    # operator re-mounted in step 2 is known to be mounted so, and the approach (step 3) does not ask for it
    mark = len(p.asked)
    with Cell(config, text) as cell:
        p.world = cell.sim_world
        real = experiments(config, out, cell, resume=True, replay_sim=False)
    still_to_answer = [("click_points", cam, obj, None) for cam in ("side", "top") for obj in ("oru", "receptacle")]
    assert p.kinds_since(mark) == still_to_answer + [("mount_camera", "top", None, None)] + still_to_answer
    assert len(real) > len(first) and {r["step"] for r in real} == set(range(9))

    # a simulated cell: a fresh world, the persisted steps replayed on it; their requests take the recorded
    # answers (the replay reproduces every persisted row exactly, else it stops with ReplayMismatch)
    mark = len(p.asked)
    with Cell(config, text) as cell:
        p.world = cell.sim_world
        replayed = experiments(config, tmp_path / "sim-run", cell, resume=True, replay_sim=True)
    assert p.kinds_since(mark) == still_to_answer + [("mount_camera", "top", None, None)] + still_to_answer
    assert len(replayed) == len(real) and replayed[:len(first)] == first


def test_a_replayed_step_that_asks_otherwise_than_recorded_stops_clearly(person, tmp_path):
    p, config, text = person
    with Cell(with_seed(config, SEED), text) as cell:
        op = cell.operator
        assert isinstance(op, RecordsAnswers)
        cell.begin_step(0)
        op.replay([{"verb": "mount_camera", "camera": "top", "inter_camera_angle_deg": 28.0, "view_width_in": None,
                    "look_at_in": None, "outcome": "answered", "waited_s": 2.5}])
        before = cell.clock.now()
        op.mount_camera("top", 28.0)  # as recorded: taken, nobody asked, its wait counted again
        assert cell.clock.now() == pytest.approx(before + 2.5)
        with pytest.raises(DeviceError, match="no answer was recorded"):
            op.align_by_hand(cell.arm, 0.0254)
        op.replay([{"verb": "mount_camera", "camera": "side", "inter_camera_angle_deg": None, "view_width_in": 20.0,
                    "look_at_in": None, "outcome": "answered", "waited_s": 1.0}])
        with pytest.raises(DeviceError, match="cannot be resumed exactly"):
            op.mount_camera("side", None, 36.0)
    assert p.asked == []


def test_the_web_operator_s_wait_is_simulated_cell_time(person, tmp_path):
    p, config, text = person
    p.delay_s = 0.3
    with Cell(with_seed(config, SEED), text) as cell:
        p.world = cell.sim_world
        cell.begin_step(0)
        before = cell.clock.now()
        t = time.monotonic()
        cell.operator.align_by_hand(cell.arm, 0.0254)
        wall = time.monotonic() - t
        waited = cell.clock.now() - before
        assert 0.3 <= waited <= wall
        assert cell.operator.answers()[0]["waited_s"] == pytest.approx(waited)


# -- the operator at a terminal ----------------------------------------------------------------------------


class SlowEnter:
    """A terminal where the operator presses Enter `delay_s` after each prompt, `n` times; then nobody."""

    def __init__(self, n: int, delay_s: float):
        self.n, self.delay_s, self.read = n, delay_s, 0

    def readline(self) -> str:
        if self.read >= self.n:
            return ""
        self.read += 1
        time.sleep(self.delay_s)
        return "\n"


class AskThenMove:
    """A small routine: the operator is asked (steps 0 and 2), the arm moves (steps 1 and 3)."""

    name: ClassVar[str] = "ask-then-move"
    Params: ClassVar[type[Params]] = Params
    sample_columns: ClassVar[tuple[str, ...]] = ("step", "x_mm")

    def inputs(self, params, devices) -> list[str]:
        return []

    def plan(self, params, devices) -> list[Step]:
        return [Step(i, "ask" if i % 2 == 0 else "move", {}) for i in range(4)]

    def execute(self, step: Step, params, devices, history=()) -> StepResult:
        if step.action == "ask":
            devices.operator.request(f"Confirm step {step.index}")
        else:
            p = devices.arm.pose()
            devices.arm.move_linear(Pose(p.x + 0.002, p.y, p.z, p.alpha))
        return StepResult({"step": step.index, "x_mm": devices.arm.pose().x * 1e3})


def console_cell(tmp_path: Path):
    text = (ROOT / "config" / "sim-microcell.yaml").read_text()
    text = text.replace("operator:\n  backend: sim ", "operator:\n  backend: console ")
    assert "backend: console" in text
    text += f"\nstore_dir: {tmp_path / 'store'}\n"
    (tmp_path / "cell.yaml").write_text(text)
    config, text = load_cell_file(tmp_path / "cell.yaml")
    return with_seed(config, SEED), text


def run_console(config, text, out: Path, stdin, **kwargs) -> list[dict]:
    with Cell(config, text) as cell:
        cell.operator._in = stdin
        return collect(AskThenMove(), Params(), cell, RunFolder(out), seed=SEED, **kwargs)


def test_the_terminal_operator_s_wait_is_cell_time_and_a_replay_does_not_ask_again(tmp_path, capsys):
    config, text = console_cell(tmp_path)
    control = JobControl()

    def cut(progress):
        if progress.done == 3:
            control.abort()

    with pytest.raises(Aborted):
        run_console(config, text, tmp_path / "run", SlowEnter(2, 0.25), control=control, on_progress=cut)
    first = RunFolder(tmp_path / "run").samples()
    waits = {r["step"]: json.loads(r["operator"])[0]["waited_s"] for r in first if r.get("operator")}
    assert sorted(waits) == [0, 2] and min(waits.values()) >= 0.25
    assert first[0]["cell_time_s"] == pytest.approx(waits[0])  # nothing else happened in step 0
    # resumed on a fresh world: steps 0-2 replayed, step 0 and 2's confirmations taken from the samples (a
    # terminal with nobody at it would end the run if anything were asked), the clock restored with them
    rows = run_console(config, text, tmp_path / "run", SlowEnter(0, 0.0), resume=True, replay_sim=True)
    assert rows[:3] == first and [r["step"] for r in rows] == [0, 1, 2, 3]
    # the same run uninterrupted, answered at once: the same moves, its cell time without the waits
    at_once = run_console(config, text, tmp_path / "at-once", SlowEnter(2, 0.0))
    assert [r["x_mm"] for r in at_once] == [r["x_mm"] for r in rows]
    total = sum(waits.values())
    at_once_waits = sum(json.loads(r["operator"])[0]["waited_s"] for r in at_once if r.get("operator"))
    assert rows[-1]["cell_time_s"] - total == pytest.approx(at_once[-1]["cell_time_s"] - at_once_waits, abs=1e-9)
    assert rows[-1]["cell_time_s"] >= total + 0.5 > at_once[-1]["cell_time_s"]
    assert capsys.readouterr().err.count("OPERATOR: Confirm step") == 4  # 2 before the cut, 2 uninterrupted
