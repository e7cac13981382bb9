"""One routine run, start to finish: parameters, collection, fit, truth, result files.

The CLI calls this in-process; the daemon will call the same thing on its worker.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

from pydantic import ValidationError

from drivers.lazy import load

from calibration.errors import UnknownName
from calibration.routines import all_routines, routine_class, sequence
from calibration.routines.base import ChoosesArmCalibration, JudgesCalibrations, Previews

from cellctl.config import CellFile
from cellctl.core.calibrated_arm import CalibratedArm
from cellctl.core.cell import Cell
from cellctl.core.orchestrator import JobControl, Progress, collect
from cellctl.core.report import write_result
from cellctl.errors import InvalidRequest
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.run_folder import RunFolder, RunFolderError, write_json


class ParamError(InvalidRequest, ValueError):
    """Routine parameters that the routine does not accept (names each key and what is allowed)."""


def routine_params(routine, cell_config: CellFile | None, overrides: dict[str, Any]):
    """Cell-file defaults for the routine, then those for its area (`routines: {hybrid.area2: {...}}`),
    overridden by the caller's; errors name the key, and the cell-file section a bad value came from."""
    defaults = cell_config.routines if cell_config else {}
    merged = dict(defaults.get(routine.name, {}), **overrides)
    origin = {key: f"routines.{routine.name}" for key in defaults.get(routine.name, {})}
    area = merged.get("area")
    if area is not None and f"{routine.name}.{area}" in defaults:
        merged = {**merged, **defaults[f"{routine.name}.{area}"], **overrides}
        origin.update({key: f"routines.{routine.name}.{area}" for key in defaults[f"{routine.name}.{area}"]})
    for key in overrides:
        origin.pop(key, None)
    try:
        return routine.Params(**merged)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            key = ".".join(str(p) for p in err["loc"]) or "(parameters)"
            msg = "unknown parameter" if err["type"] == "extra_forbidden" else err["msg"]
            source = origin.get(err["loc"][0]) if err["loc"] else None
            came = f", from the cell file's {source}" if source else ""
            problems.append(f"  {key}: {msg} (got {err.get('input')!r}{came})")
        allowed = ", ".join(routine.Params.model_fields)
        raise ParamError(f"bad parameters for {routine.name}:\n" + "\n".join(problems) + f"\nallowed: {allowed}") from None


def with_seed(config: CellFile, seed: int | None) -> CellFile:
    if seed is None or config.sim is None:
        return config
    return config.model_copy(update={"sim": config.sim.model_copy(update={"seed": seed})})


def run_routine(name: str, config: CellFile, cell_text: str, out: str | Path, *, seed: int | None = None,
                overrides: dict[str, Any] | None = None, resume: bool = False, save_images: bool = False,
                control: JobControl | None = None, store: CalibrationStore | None = None,
                on_progress: Callable[[Progress], None] | None = None, cell: Cell | None = None,
                replay_sim: bool | None = None) -> dict:
    """Run, fit and report; with a store, use its active calibrations and keep the new one as active.

    `cell`: an already connected cell to run on (the daemon's), left open; by default a cell is built
    from `config`, connected and closed. `replay_sim`: see `collect`; by default, a resumed run on a cell
    built here replays (its simulated world is fresh), one on a borrowed cell does not.
    """
    routine = routine_class(name)()
    params = routine_params(routine, config, overrides or {})
    config = with_seed(config, seed)
    seed = config.sim.seed if config.sim else None
    folder = RunFolder(out)
    started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    if replay_sim is None:
        replay_sim = resume and cell is None
    with (Cell(config, cell_text) if cell is None else _Borrowed(cell)) as cell:
        if store is not None:
            cell.devices.calibrations = store.active_models()
        arm_model = cell.devices.calibrations.get("arm")
        if arm_model is not None and isinstance(routine, ChoosesArmCalibration) and not routine.through_arm_calibration(
                params):
            arm_model = None  # the arm as its controller moves it, though a calibration is active
        # every move of the run goes through the arm calibration in force (core/calibrated_arm.py)
        cell.devices.arm = CalibratedArm(cell.arm, arm_model) if arm_model else cell.arm
        samples = collect(routine, params, cell, folder, seed=seed, resume=resume, save_images=save_images,
                          control=control, on_progress=on_progress, replay_sim=replay_sim)
        resolutions = {n: tuple(c.resolution) for n, c in cell.cameras.items()}
        if isinstance(routine, JudgesCalibrations):
            used = {t: cell.devices.calibrations[t] for t in routine.inputs(params, cell.devices)
                    if t in cell.devices.calibrations}
            outcome = routine.judge(samples, params, used, resolutions)
        else:
            outcome = routine.fit(samples, params, resolutions)
        result = {
            "routine": name,
            "cell": config.cell.name,
            "params": params.model_dump(mode="json"),
            "seed": seed,
            "simulated": cell.sim_world is not None,
            "started": started,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "cell_time_s": max((float(r["cell_time_s"]) for r in samples), default=0.0),
            "n_samples": len(samples),
            # the arm calibration every move went through (core/calibrated_arm.py), when one was in force
            **({"arm_calibration": arm_model.get("calibration_id")} if arm_model else {}),
            "model": outcome.model,
            "stats": outcome.stats,
            "rejected": outcome.rejected,
            **outcome.summary,
        }
        if cell.sim_world is not None and routine.truth:
            result["truth"] = load(routine.truth)(cell.sim_world, cell.devices, params, samples, outcome)
        target = routine.output(params, cell.devices)
    # a resumed run whose end failed part way (a full disk) finds what it stored already: stored once per run
    if store is not None and target:
        saved = ((store.saved_from(target, folder.path.resolve()) if resume else None)
                 or store.save(target, result, cell_text, run_dir=folder.path.resolve()))
        result["calibration"] = {"target": target, "id": saved.id, "version": saved.version, "active": saved.active}
    if outcome.calibrations:
        result["updated"] = (_store_versions(outcome, result, store, cell_text, folder, resume) if store is not None
                             else {})
    if store is not None and isinstance(routine, JudgesCalibrations):  # a check is kept with what it checked
        result["check_id"] = ((store.check_from(folder.path.resolve()) if resume else None)
                              or store.save_check(result, folder.path.resolve()))
    write_result(folder.path, result, outcome)
    return result


def _store_versions(outcome, result: dict, store: CalibrationStore, cell_text: str, folder: RunFolder,
                    resume: bool = False) -> dict:
    """The versions a routine proposes besides its output (a check's touch-ups), each active, with its provenance:
    the version it corrects and the run that made it (whose samples are kept with it)."""
    updated = {}
    for target, version in outcome.calibrations.items():
        entry = {key: result[key] for key in ("routine", "cell", "params", "seed", "simulated", "started", "finished",
                                               "cell_time_s", "n_samples") if key in result}
        entry.update(model=version.model, stats=version.stats,
                     provenance={"parent": version.parent, "run": str(folder.path.resolve()), "made_by": result["routine"]})
        saved = ((store.saved_from(target, folder.path.resolve()) if resume else None)
                 or store.save(target, entry, cell_text, run_dir=folder.path.resolve()))
        updated[target] = saved.id
    return updated


class _Borrowed:
    """A cell someone else connected and will close."""

    def __init__(self, cell: Cell):
        self.cell = cell

    def __enter__(self) -> Cell:
        return self.cell

    def __exit__(self, *exc) -> None:
        pass


def fit_samples(name: str, samples: list[dict], overrides: dict[str, Any] | None = None,
                resolutions: dict | None = None, cell_config: CellFile | None = None) -> tuple[dict, Any]:
    """`cellctl fit`: the routine's own fit on recorded samples, no cell needed (`cell_config`: take the
    routine's parameters from a cell file, as its run did)."""
    routine = routine_class(name)()
    params = routine_params(routine, cell_config, overrides or {})
    outcome = routine.fit(samples, params, resolutions)
    result = {"routine": name, "params": params.model_dump(mode="json"), "n_samples": len(samples),
              "model": outcome.model, "stats": outcome.stats, "rejected": outcome.rejected}
    if outcome.summary:
        result["summary"] = outcome.summary
    return result, outcome


def preview_routine(name: str, config: CellFile | None, overrides: dict[str, Any] | None = None) -> list[dict]:
    """`cellctl plan`: what a routine that plans its own motion will do, as tables, before anything moves (nothing
    connects: the image size comes from the cell file's simulated camera when it has one)."""
    routine = routine_class(name)()
    if not isinstance(routine, Previews):
        raise UnknownName(f"{name} plans no motion of its own to preview; routines that do: "
                          f"{', '.join(n for n, c in all_routines().items() if issubclass(c, Previews))}")
    params = routine_params(routine, config, overrides or {})
    camera = getattr(params, "camera", None)
    sim = getattr(config, "sim", None) if config else None
    size = None
    if sim is not None and camera in getattr(sim, "cameras", {}):
        size = tuple(sim.cameras[camera].resolution_px)
    return routine.preview(params, size)


def sequence_summary(name: str, cell: str, seed: int | None, results: dict[str, dict]) -> dict:
    """A sequence's result.json: per routine that ran to its end (`results`, by item), its folder, statistics,
    scalar model values, truth figures and the calibration it stored."""
    return {"routine": name, "cell": cell, "seed": seed, "cell_time_s": sum(r["cell_time_s"] for r in results.values()),
            "runs": {r: {"folder": sequence(name).folder(r), "stats": res["stats"], "model": {
                key: v for key, v in res["model"].items() if not isinstance(v, dict)},
                "truth": {key: v for key, v in (res.get("truth") or {}).items() if isinstance(v, float)},
                "calibration": res.get("calibration")}
                for r, res in results.items()}}


def run_sequence(name: str, config: CellFile, cell_text: str, out: str | Path, *, seed: int | None = None,
                 resume: bool = False, store: CalibrationStore | None = None,
                 on_step: Callable[[str], Callable[[Progress], None] | None] | None = None,
                 on_item_done: Callable[[str, dict], None] | None = None, **routine_options) -> dict:
    """Each routine in its own run folder under `out`; with resume, finished ones are kept as they are.

    `on_item_done(item, result)`: after each routine this call ran to its end. `routine_options` go to every
    `run_routine` (control, replay_sim, cell_factory: a callable giving the cell for each routine)."""
    cell_factory = routine_options.pop("cell_factory", None)
    out = Path(out)
    if out.exists() and not resume and any(out.glob("[0-9][0-9]-*")):
        raise RunFolderError(f"{out} already holds runs; resume them (--resume) or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for item in sequence(name).items:
        folder = out / sequence(name).folder(item.name)
        if (folder / "result.json").exists():
            results[item.name] = json.loads((folder / "result.json").read_text())
            continue
        results[item.name] = run_routine(item.routine, config, cell_text, folder, seed=seed, store=store,
                                         overrides=dict(item.params) or None,
                                         resume=resume and (folder / "run.json").exists(),
                                         on_progress=on_step(item.name) if on_step else None,
                                         cell=cell_factory() if cell_factory else None, **routine_options)
        if on_item_done is not None:
            on_item_done(item.name, results[item.name])
    summary = sequence_summary(name, config.cell.name, seed, results)
    write_json(out / "result.json", summary)
    return {"summary": summary, "results": results}
