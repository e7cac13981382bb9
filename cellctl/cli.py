"""`cellctl`: run routines on a cell, fit recorded samples, map pixels with a calibration.

Exit status: 0 done, 1 the cell failed (device fault), 2 bad input (cell file,
argument, samples file), 130 interrupted (samples kept; resume with --resume).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from pathlib import Path

import numpy as np
import yaml

from calibration.errors import CalibrationError
from calibration.routines import ROUTINES, routine_class
from drivers.interfaces import DeviceError

from . import client, report
from .calstore import CalibrationStore, CalibrationStoreError
from .config import CellFileError, load_cell_file
from .orchestrator import Aborted
from .runs import SEQUENCES, ParamError, fit_samples, run_routine, run_sequence
from .simserve import SimServeError, add_sim_command
from .store import RunFolderError, read_samples_text, write_atomic, write_json

EXIT_OK, EXIT_FAULT, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


class InputError(Exception):
    """Bad input from the command line or a file: exit status 2."""


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (InputError, CellFileError, ParamError, CalibrationError, RunFolderError, CalibrationStoreError,
            SimServeError) as exc:
        print(f"cellctl: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except DeviceError as exc:
        print(f"cellctl: the cell failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_FAULT
    except (KeyboardInterrupt, Aborted):
        print("cellctl: interrupted; the samples so far are kept (resume with --resume)", file=sys.stderr)
        return EXIT_INTERRUPTED


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cellctl", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a calibration routine on the cell (in-process, or through the daemon "
                                      "with --url / $CELLCTL_URL)")
    run.add_argument("routine", choices=sorted(ROUTINES) + sorted(SEQUENCES))
    run.add_argument("--config", help="cell file (YAML); required in-process")
    run.add_argument("--out", help="run folder (created; with --resume, reopened); required in-process")
    run.add_argument("--url", help="the daemon to submit the job to (default: $CELLCTL_URL; none: run in-process)")
    run.add_argument("--token", help="the daemon's token (default: $CELLCTL_TOKEN, or read via --config)")
    run.add_argument("--wait", action="store_true", help="daemon: follow the job, then print the result table")
    run.add_argument("--seed", type=int, help="simulation seed (simulated cells only)")
    run.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="routine parameter")
    run.add_argument("--resume", action="store_true", help="continue a run from its persisted samples")
    run.add_argument("--save-images", action="store_true", help="keep every frame as PNG in the run folder")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--store", help="calibration store folder (default: $CELLCTL_STORE, the cell file's "
                                     "store_dir, or ~/.local/share/cellctl/CELL)")
    run.set_defaults(func=cmd_run)

    cals = sub.add_parser("calibrations", help="list the stored calibrations, or make one active")
    cals.add_argument("--config", help="cell file (names the store); required without a daemon")
    cals.add_argument("--url", help="the daemon (default: $CELLCTL_URL; none: read the store directly)")
    cals.add_argument("--token", help="the daemon's token (default: $CELLCTL_TOKEN, or read via --config)")
    client.add_calibrations_actions(cals)
    cals.add_argument("--store", help="calibration store folder (overrides the cell file)")
    cals.add_argument("--activate", type=int, metavar="ID", help="make calibration ID the active one of its target")
    cals.set_defaults(func=cmd_calibrations)

    fit = sub.add_parser("fit", help="fit a routine's model from a recorded samples CSV")
    fit.add_argument("routine", choices=sorted([*ROUTINES, "csm"]), help="csm: csm-positioning's view parameters")
    fit.add_argument("--samples", required=True, help="CSV; virtual-grid: x_mm,y_mm,u_px,v_px,set (set: cal or ver); "
                                                      "rotation-sweep: pos_id,alpha_deg,x_mm,y_mm; "
                                                      "csm: camera,u_px,v_px,j1_deg..j6_deg (README: CSV formats)")
    fit.add_argument("--out", required=True, help="calibration JSON to write")
    fit.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    fit.add_argument("--image-size", metavar="WxH", help="camera resolution (default: from the pixels seen)")
    fit.add_argument("--config", help="cell file whose routine parameters to fit with (as the run did)")
    fit.set_defaults(func=cmd_fit)

    mp = sub.add_parser("map", help="map pixels to robot millimetres with a calibration")
    mp.add_argument("calibration", help="cal.json from `cellctl fit`, or a run's result.json")
    mp.add_argument("--pixels", required=True, help="CSV with columns u_px,v_px")
    mp.add_argument("--out", required=True, help="CSV to write with u_px,v_px,x_mm,y_mm")
    mp.set_defaults(func=cmd_map)

    loc = sub.add_parser("locate", help="where in robot coordinates is what a camera sees at a pixel")
    loc.add_argument("--config", required=True, help="cell file (names the store)")
    loc.add_argument("--store", help="calibration store folder (overrides the cell file)")
    loc.add_argument("--camera", required=True)
    loc.add_argument("--pixel", required=True, nargs=2, type=float, metavar=("U", "V"))
    loc.add_argument("--arm-pose", nargs=3, type=float, metavar=("X_MM", "Y_MM", "ALPHA_DEG"),
                     help="the arm's reported pose, for a camera that rides on it")
    loc.set_defaults(func=cmd_locate)

    check = sub.add_parser("check", help="validate a cell file")
    check.add_argument("--config", required=True)
    check.set_defaults(func=cmd_check)

    serve = sub.add_parser("serve", help="run the cell daemon (HTTP API on 127.0.0.1)")
    serve.add_argument("--config", required=True, help="cell file (YAML)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8470)
    serve.set_defaults(func=cmd_serve)
    client.add_daemon_commands(sub, include_run=False)
    add_sim_command(sub)
    return parser


# -- run ----------------------------------------------------------------------


def cmd_run(args) -> int:
    if client.daemon_url(args):
        return client.cmd_run(args)
    if not args.config or not args.out:
        raise InputError("run in-process needs --config FILE and --out DIR (or give --url / CELLCTL_URL to "
                         "submit the job to the daemon)")
    config, text = load_cell_file(args.config)
    overrides = parse_params(args.param)
    if args.seed is not None and config.sim is None:
        raise InputError("--seed applies to simulated cells only; this cell file has no 'sim:' section")
    store = CalibrationStore(args.store or config.store_path())
    if args.routine in SEQUENCES:
        if overrides:
            raise InputError(f"--param does not apply to {args.routine}; set each routine's parameters in the cell file")
        return run_sequence_cli(args, config, text, store)
    with progress_display(args.routine, args.quiet) as on_progress:
        result = run_routine(args.routine, config, text, args.out, seed=args.seed, overrides=overrides,
                             resume=args.resume, save_images=args.save_images, store=store,
                             on_progress=on_progress)
    report.print_summary(result, Path(args.out))
    if "calibration" in result:
        c = result["calibration"]
        print(f"stored as calibration {c['id']} (version {c['version']} of {c['target']}, active) in {store.path}")
    return EXIT_OK


def run_sequence_cli(args, config, text, store) -> int:
    bars = []

    def on_step(routine):
        bar = progress_display(routine, args.quiet)
        bars.append(bar)
        return bar.__enter__()

    try:
        done = run_sequence(args.routine, config, text, args.out, seed=args.seed, resume=args.resume, store=store,
                            on_step=on_step, save_images=args.save_images)
    finally:
        for bar in bars:
            bar.__exit__(None, None, None)
    for routine, result in done["results"].items():
        report.print_summary(result, Path(args.out) / done["summary"]["runs"][routine]["folder"])
    print(f"{args.routine}: {len(done['results'])} routines, cell time {done['summary']['cell_time_s']:.0f} s; "
          f"calibrations stored in {store.path}")
    return EXIT_OK


def cmd_calibrations(args) -> int:
    if client.daemon_url(args):
        return client.cmd_calibrations(args)
    if not args.config:
        raise InputError("calibrations without a daemon needs --config FILE (or give --url / CELLCTL_URL)")
    if args.action is not None:
        raise InputError(f"calibrations {args.action} goes through the daemon: give --url or set CELLCTL_URL")
    config, _ = load_cell_file(args.config)
    store = CalibrationStore(args.store or config.store_path())
    if args.activate is not None:
        cal = store.activate(args.activate)
        print(f"calibration {cal.id} (version {cal.version} of {cal.target}) is now active")
        return EXIT_OK
    cals = store.list()
    if not cals:
        print(f"no calibrations in {store.path}")
    for c in cals:
        ver = c.result.get("stats", {}).get("verification", {})
        figure = f"ver mean {ver['mean_um']:.2f} µm" if ver.get("mean_um") is not None else ""
        print(f"{c.id:4d}  {c.target:8s} v{c.version:<3d} {'ACTIVE' if c.active else '      '} {c.routine:16s} "
              f"{c.created}  {figure}")
    return EXIT_OK


def parse_params(pairs: list[str]) -> dict:
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise InputError(f"--param {pair!r}: expected KEY=VALUE, e.g. --param rows=8")
        out[key.strip()] = yaml.safe_load(value) if value.strip() else ""
    return out


class progress_display:
    """A rich progress bar (step i / N, simulated cell time) on stderr."""

    def __init__(self, routine: str, quiet: bool):
        self.routine, self.quiet = routine, quiet

    def __enter__(self):
        if self.quiet:
            return None
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("steps  cell time {task.fields[cell]:>7.1f} s"), TimeElapsedColumn(),
                            console=Console(stderr=True), transient=False)
        self.bar.__enter__()
        self.task = self.bar.add_task(self.routine, total=None, cell=0.0)
        return self.update

    def update(self, p) -> None:
        self.bar.update(self.task, completed=p.done, total=p.total, cell=p.cell_time_s)

    def __exit__(self, *exc):
        if not self.quiet:
            self.bar.__exit__(*exc)
        return False


def cmd_serve(args) -> int:
    from .daemon import serve

    return serve(args.config, args.host, args.port)


# -- fit ------------------------------------------------------------------------


FIT_ALIASES = {"csm": "csm-positioning"}


def cmd_fit(args) -> int:
    routine = FIT_ALIASES.get(args.routine, args.routine)
    columns = routine_class(routine).fit_columns
    numeric = tuple(c for c in columns if c.endswith(("_mm", "_px", "_deg")))
    samples = read_csv(args.samples, columns, numeric=numeric)
    for row in samples:  # no step column: each routine knows how its rows group (csm: by joints)
        row.setdefault("status", "ok")
    resolutions = {"*": parse_size(args.image_size)} if args.image_size else None
    cell = load_cell_file(args.config)[0] if args.config else None
    result, _ = fit_samples(routine, samples, parse_params(args.param), resolutions, cell)
    write_json(Path(args.out), result)
    s = result["stats"]
    cal, ver = s.get("calibration", {}), s.get("verification", {})
    print((f"fitted {cal['n']} samples: residual mean {cal['mean_um']:.2f} µm; " if cal.get("n") else "")
          + (f"verification on {ver['n']}: mean {ver['mean_um']:.2f} µm, max {ver['max_um']:.2f} µm"
             if ver.get("n") else "no verification rows")
          + f"; rejected {len(result['rejected'])}; wrote {args.out}")
    return EXIT_OK


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--image-size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 2448x2050") from None
    if w <= 0 or h <= 0:
        raise InputError(f"--image-size {text!r}: width and height must be positive")
    return w, h


def read_csv(path: str, required: tuple[str, ...], numeric: tuple[str, ...]) -> list[dict]:
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    header = next(csv.reader(io.StringIO(text)), None)
    if not header:
        raise InputError(f"{path}: empty file; expected a header with columns {', '.join(required)}")
    missing = [c for c in required if c not in [h.strip() for h in header]]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}; required: {', '.join(required)}"
                         f" (found: {', '.join(header)})")
    rows = read_samples_text(text)
    if not rows:
        raise InputError(f"{path}: no data rows")
    for i, row in enumerate(rows):
        measured = row.get("status") in (None, "ok")  # rows marked unmeasured may carry nan
        for col in numeric:
            value = row.get(col)
            if value is None and "set" in row:  # not every set fills every column (e.g. grid dots have no x_mm)
                continue
            if not isinstance(value, (int, float)) or (measured and not math.isfinite(value)):
                raise InputError(f"{path}: row {i + 2}, column {col}: {value!r} is not a finite number")
            row[col] = float(value)
    return rows


# -- map --------------------------------------------------------------------------


def cmd_map(args) -> int:
    from calibration.models.planar import PlanarMap

    try:
        doc = json.loads(Path(args.calibration).read_text())
    except OSError as exc:
        raise InputError(f"{args.calibration}: cannot read: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{args.calibration}: not JSON: {exc}") from None
    model = doc.get("model") if isinstance(doc, dict) else None
    if not isinstance(model, dict) or "map" not in model:
        raise InputError(f"{args.calibration}: no planar calibration (expected a 'model' with a 'map'); "
                         "use the cal.json of `cellctl fit` or a run's result.json")
    planar = PlanarMap.from_dict(model["map"])
    scale = {"m": 1e3, "mm": 1.0}.get(model.get("plane_unit", "m"))
    if scale is None:
        raise InputError(f"{args.calibration}: plane_unit {model.get('plane_unit')!r}; allowed: m, mm")
    rows = read_csv(args.pixels, ("u_px", "v_px"), numeric=("u_px", "v_px"))
    uv = np.array([[r["u_px"], r["v_px"]] for r in rows])
    xy = planar.pixel_to_plane(uv) * scale
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["u_px", "v_px", "x_mm", "y_mm"])
    for (u, v), (x, y) in zip(uv, xy):
        w.writerow([repr(float(u)), repr(float(v)), f"{x:.6f}", f"{y:.6f}"])
    write_atomic(Path(args.out), buf.getvalue())
    print(f"mapped {len(rows)} pixels; wrote {args.out}")
    return EXIT_OK


def cmd_locate(args) -> int:
    from calibration.usage import CellCalibration
    from drivers.interfaces import Pose

    config, _ = load_cell_file(args.config)
    store = CalibrationStore(args.store or config.store_path())
    pose = None
    if args.arm_pose:
        x, y, alpha = args.arm_pose
        pose = Pose(x * 1e-3, y * 1e-3, 0.0, math.radians(alpha))
    x, y = CellCalibration(store.active_models()).locate(args.camera, [args.pixel], pose)[0] * 1e3
    print(f"x_mm={x:.4f} y_mm={y:.4f}  (commanded position at alpha_cal that puts the nozzle there)")
    return EXIT_OK


def cmd_check(args) -> int:
    config, _ = load_cell_file(args.config)
    devices = ", ".join(f"{name} ({dev.backend})" for _, name, dev in config.devices())
    print(f"{args.config}: valid cell file {config.cell.name!r}: {devices}; areas: {', '.join(config.areas) or 'none'}")
    return EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

