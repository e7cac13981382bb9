"""The contract every registered routine keeps (`Routine` in calibration/routines/base.py), on its simulated cell.

Parametrized over `calibration.routines.all_routines()`: a routine added later is checked with no edit here.
For each routine:
1. its plan is deterministic (two freshly built cells of the same seed plan the same steps) and non-empty;
2. every row `execute` returns stays within `sample_columns`, holds plain CSV values and names its step;
3. aborting at a step drawn from a generator seeded by the routine's name, then resuming, gives the same
   samples (every column) and the same result (stats, model, cell time) as an uninterrupted run;
4. its report.md leads with its result table and embeds only files that exist in the run folder, and the
   terminal summary shows its tables within 100 columns.

A routine runs on the cell file whose `routines:` section configures it (the micro cell by default), with small
parameters (SMALL below, else the routine's `small_params`, else its cell file's defaults), and with a copy of a
store holding the calibrations routines take as inputs, filled once for the module. The report's plots are not drawn.
"""

from __future__ import annotations

import functools
import io
import json
import math
import random
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from calibration.routines import all_routines, routine_class
from calibration.routines.base import Pipelines

from cellctl.config import load_cell_file
from cellctl.core import report
from cellctl.core.cell import Cell
from cellctl.core.orchestrator import Aborted, JobControl
from cellctl.core.runs import routine_params, run_routine, run_sequence, with_seed
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.run_folder import RunFolder, to_jsonable

from tests.conftest import MICROCELL, ROOT

SEED = 3
# the hand-eye cell's routines run here through ur-rtde against the UR simulator on loopback (sim-ur5e-handeye-ur,
# first of the two that configure them): a run resumed through the real driver must equal an uninterrupted one.
# In-process they are tested in tests/routines/test_hand_eye.py and test_table_pick.py, and
# tests/drivers/test_ur_handeye_loopback.py holds the two paths to the same samples and figures.
# arm-kinematics runs here on the UR5e (its wrist-board observation, the images); the IRB 120's fixed-cameras one is
# tested in tests/routines/test_arm_kinematics_irb120.py
CELL_FILES = (MICROCELL, ROOT / "config" / "sim-ur5e-handeye-ur.yaml", ROOT / "config" / "sim-ur5e-uncalibrated.yaml",
              ROOT / "config" / "sim-irb120-csm.yaml", ROOT / "config" / "sim-vr.yaml",
              ROOT / "config" / "sim-ur5e-handeye.yaml")
BOOKKEEPING = ("cell_time_s", "step_rows", "image")  # the columns the orchestrator adds to every row

# small runs keep the module quick (the store's calibrate-cell runs at these sizes too); a routine missing here
# runs with its own small_params, else with its cell file's defaults
SMALL = {
    "virtual-grid": {"rows": 3, "cols": 3, "passes": 1, "n_verify": 2},
    "virtual-grid-area2": {"rows": 2, "cols": 4, "n_verify": 2},
    "hybrid": {"n_register": 2, "n_verify": 4},
    "rotation-sweep": {"rows": 1, "cols": 2, "step_deg": 90, "n_verify": 2},
    "onboard-camera": {"rows": 3, "cols": 3, "alphas_deg": [0, 20]},
    "place-test": {"n": 3},
    "csm-positioning": {"n_targets": 4, "loops": ["white:w4"], "primary": "white:w4", "k_values": [3],
                        "approach_mm": [[-80, 60, 100]], "max_iterations": 2},
    "vr-approach": {"via_in": [2.0]},
    "vr-experiments": {"fig7_runs": 1, "n_runs": 1, "angles_deg": [28.0], "distances_in": [20.0, 2.0], "views": []},
    # the contract asks for every kind of step, a fit and a report, not for accuracy: 10 calibration poses (the
    # plan still identifies the same 18 deviations; the fit needs 8) and one held out, instead of small_params' 24 + 3
    # (the accuracy is tests/routines/test_arm_kinematics.py's); each pose is a frame and the fit's time grows with them
    "arm-kinematics": {"poses": 10, "verify_poses": 1, "candidates": 40},
    # two cycles, the fewest with a repeatability (small_params: 3); its figures are tests/routines/test_iso9283.py's
    "iso9283": {"cycles": 2},
}
ROUTINES = all_routines()
SMALL.update({n: cls.small_params for n, cls in ROUTINES.items()  # else the routine's own (Routine.small_params)
              if n not in SMALL and getattr(cls, "small_params", None)})
NAMES = sorted(ROUTINES)


@functools.cache
def cell_file_of(name: str) -> Path:
    """The cell file that configures the routine (its `routines:` section), else the micro cell."""
    for path in CELL_FILES:
        config, _ = load_cell_file(path)
        if name in config.routines:
            return path
    return MICROCELL


@functools.cache
def setup(name: str):
    """(config with SEED, text, params) of the routine's run."""
    config, text = load_cell_file(cell_file_of(name))
    params = routine_params(routine_class(name)(), config, SMALL.get(name, {}))
    return with_seed(config, SEED), text, params


@pytest.fixture(scope="module", autouse=True)
def no_plots():
    """The report's plots are not part of the contract (result.json is), and drawing them is most of a small run."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(report, "plot_residuals", lambda *args: None)
        mp.setattr(report, "plot_chart", lambda *args: None)
        yield


@pytest.fixture(scope="module")
def calibrated_store(tmp_path_factory) -> Path:
    """A store (closed) with the calibrations routines take as inputs: cam1, nozzle, cam2 and cam3 from calibrate-cell
    on the micro cell at the small sizes (they still calibrate well enough to place spheres), vr from vr-coarse,
    hand-eye:wrist from hand-eye on the UR5e cell."""
    config, text = load_cell_file(MICROCELL)
    small = {name: dict(config.routines.get(name, {}), **SMALL.get(name, {})) for name in config.routines}
    config = config.model_copy(update={"routines": small})
    folder = tmp_path_factory.mktemp("contract-store")
    store = CalibrationStore(folder / "store")
    run_sequence("calibrate-cell", config, text, folder / "cc", seed=SEED, store=store)
    vr_config, vr_text, _ = setup("vr-coarse")
    run_routine("vr-coarse", vr_config, vr_text, folder / "vr-coarse", store=store)
    he_config, he_text, _ = setup("hand-eye")
    run_routine("hand-eye", he_config, he_text, folder / "hand-eye", store=store, overrides=SMALL["hand-eye"])
    store.close()
    return folder / "store"


def store_copy(calibrated_store: Path, where: Path) -> CalibrationStore:
    """A run's own copy of the calibrated store: what the run saves stays out of the other runs' inputs."""
    shutil.copytree(calibrated_store, where)
    return CalibrationStore(where)


def active_models(calibrated_store: Path) -> dict:
    store = CalibrationStore(calibrated_store)
    try:
        return store.active_models()
    finally:
        store.close()


def plan_on_a_fresh_cell(name: str, calibrations: dict) -> list[dict]:
    config, text, params = setup(name)
    with Cell(config, text) as cell:
        cell.devices.calibrations = dict(calibrations)
        return [s.to_dict() for s in routine_class(name)().plan(params, cell.devices)]


@pytest.mark.parametrize("name", NAMES)
def test_plan_is_deterministic_and_not_empty(name, calibrated_store):
    calibrations = active_models(calibrated_store)
    first = plan_on_a_fresh_cell(name, calibrations)
    second = plan_on_a_fresh_cell(name, calibrations)
    assert first, f"{name}: empty plan"
    assert first == second, f"{name}: two cells of seed {SEED} planned different steps"
    assert [s["index"] for s in first] == list(range(len(first))), f"{name}: step indices are not 0..n-1"
    # the manifest keeps the plan as JSON and a resume compares it: it must come back equal
    assert json.loads(json.dumps(to_jsonable(first))) == first, f"{name}: the plan does not survive JSON"


@pytest.fixture(scope="module", params=NAMES)
def whole_run(request, calibrated_store, tmp_path_factory):
    """One uninterrupted run of the routine into FOLDER/whole, with every row its `execute` returned:
    (name, folder, [(step index, rows)])."""
    name = request.param
    config, text, _ = setup(name)
    folder = tmp_path_factory.mktemp(f"contract-{name}")
    cls = routine_class(name)
    executed: list[tuple[int, list[dict]]] = []
    method = "measure" if issubclass(cls, Pipelines) else "execute"  # where a step's rows come from
    original = getattr(cls, method)

    def recording(self, step, *args, **kwargs):
        result = original(self, step, *args, **kwargs)
        executed.append((step.index, [dict(r) for r in result.rows]))
        return result

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cls, method, recording)
        run_routine(name, config, text, folder / "whole", overrides=SMALL.get(name, {}),
                    store=store_copy(calibrated_store, folder / "store"))
    return name, folder, executed


def test_rows_stay_within_sample_columns(whole_run):
    name, folder, executed = whole_run
    columns = ROUTINES[name].sample_columns
    assert "step" in columns, f"{name}: no step column (a resume finds the steps done by it)"
    assert executed, f"{name}: no step executed"
    for index, rows in executed:
        assert rows, f"{name}: step {index} returned no row"
        for row in rows:
            outside = sorted(set(row) - set(columns))
            assert not outside, f"{name}: step {index} returned columns outside sample_columns: {outside}"
            assert row.get("step") == index, f"{name}: a row of step {index} says step={row.get('step')!r}"
            for key, value in row.items():
                assert value is None or isinstance(value, (str, int, float, np.generic)), \
                    f"{name}: step {index}, {key} is a {type(value).__name__} (a CSV cell holds one value)"
                assert not (isinstance(value, str) and value.startswith(("[", "{")) and is_json(value)), \
                    f"{name}: step {index}, {key} holds JSON inside a CSV cell: {value[:60]!r}"
    header = (folder / "whole" / "samples.csv").read_text().splitlines()[0].split(",")
    assert header == [*columns, *BOOKKEEPING], f"{name}: samples.csv's columns are not sample_columns + bookkeeping"
    assert len(RunFolder(folder / "whole").samples()) == sum(len(rows) for _, rows in executed)


def is_json(text: str) -> bool:
    try:
        json.loads(text)
    except ValueError:
        return False
    return True


def test_abort_at_a_random_step_then_resume_equals_the_uninterrupted_run(whole_run, calibrated_store):
    name, folder, _ = whole_run
    config, text, _ = setup(name)
    n_steps = len(json.loads((folder / "whole" / "run.json").read_text())["plan"])
    at = random.Random(name).randrange(1, n_steps) if n_steps > 1 else 0  # reproducible, differs by routine
    store = store_copy(calibrated_store, folder / "cut-store")
    control = JobControl()

    def abort_at_step(progress):
        if progress.done == at:
            control.abort()

    cut = folder / "cut"
    with pytest.raises(Aborted):
        run_routine(name, config, text, cut, overrides=SMALL.get(name, {}), store=store, control=control,
                    on_progress=abort_at_step)
    assert len({r["step"] for r in RunFolder(cut).samples()}) == at
    run_routine(name, config, text, cut, overrides=SMALL.get(name, {}), store=store, resume=True)

    whole_rows, cut_rows = RunFolder(folder / "whole").samples(), RunFolder(cut).samples()
    assert len(cut_rows) == len(whole_rows), f"{name} aborted at step {at}: row count differs"
    for a, b in zip(whole_rows, cut_rows):
        differ = {k: (a[k], b.get(k)) for k in a if not same_value(a[k], b.get(k))}
        assert not differ, f"{name} aborted at step {at}: step {a['step']} differs after resume: {differ}"
    whole = json.loads((folder / "whole" / "result.json").read_text())
    resumed = json.loads((cut / "result.json").read_text())
    for key in ("stats", "model", "cell_time_s"):
        assert resumed[key] == whole[key], f"{name} aborted at step {at}: result {key} differs after resume"


def same_value(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def test_report_leads_with_its_result_table_and_embeds_only_files_it_wrote(whole_run):
    """The plots are not drawn here (no_plots): a report that embeds a figure anyway embeds a missing file."""
    name, folder, _ = whole_run
    run = folder / "whole"
    text = (run / "report.md").read_text()
    for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
        assert (run / target).is_file(), f"{name}: report.md embeds {target}, which the run did not write"
    first = text.split("\n## ", 1)[1]  # the first section after the title and the run's line
    body = [line for line in first.splitlines()[1:] if line.strip()]
    assert body and body[0].startswith("| "), f"{name}: report.md's first section is not a table: {first[:200]!r}"
    result = json.loads((run / "result.json").read_text())
    assert result["tables"] and first.startswith(result["tables"][0]["title"])

    console = Console(width=100, record=True, file=io.StringIO())
    report.print_summary(result, run, console=console)
    shown = console.export_text()
    too_wide = [line for line in shown.splitlines() if len(line) > 100]
    assert not too_wide, f"{name}: the terminal summary is wider than 100 columns: {too_wide[:2]}"
    assert "…" not in shown, f"{name}: the terminal summary cut a cell"
    title = " ".join(result["tables"][0]["title"].split())  # a long title wraps between words
    assert title in " ".join(shown.split()) and "─" * 20 in shown, f"{name}: no result table on the terminal"
