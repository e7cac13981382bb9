"""What the CLI does in this process, on a cell file or on files: run a routine, fit, map, check, serve."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from calibration.routines import routine_class

from ..calstore import CalibrationStore
from ..config import load_cell_file
from ..daemon.auth import read_token
from ..report import print_summary
from ..runs import SEQUENCES, fit_samples, run_routine, run_sequence
from ..store import write_atomic, write_json
from .args import InputError, parse_params, parse_size, read_csv
from .display import ProgressBar
from .verbs import EXIT_OK

FIT_ALIASES = {"csm": "csm-positioning"}


def run(args) -> int:
    """`cellctl run` without a daemon: the routine (or sequence) runs here, into --out."""
    if not args.config or not args.out:
        raise InputError("run in-process needs --config FILE and --out DIR (or give --url / CELLCTL_URL to "
                         "submit the job to the daemon)")
    config, text = load_cell_file(args.config)
    overrides = parse_params(args.param)
    if args.seed is not None and config.sim is None:
        raise InputError("--seed applies to simulated cells only; this cell file has no 'sim:' section")
    # a cell in a fleet: what this run stores goes to the plant with the daemon's next delivery
    store = CalibrationStore(args.store or config.store_path(), replicate=config.fleet is not None)
    if args.routine in SEQUENCES:
        if overrides:
            raise InputError(f"--param does not apply to {args.routine}; set each routine's parameters in the cell file")
        return run_sequence_here(args, config, text, store)
    with ProgressBar(args.routine, args.quiet) as bar:
        result = run_routine(args.routine, config, text, args.out, seed=args.seed, overrides=overrides,
                             resume=args.resume, save_images=args.save_images, store=store,
                             on_progress=bar.on_progress)
    print_summary(result, Path(args.out))
    if "calibration" in result:
        c = result["calibration"]
        print(f"stored as calibration {c['id']} (version {c['version']} of {c['target']}, active) in {store.path}")
    return EXIT_OK


def run_sequence_here(args, config, text, store) -> int:
    bars: list[ProgressBar] = []

    def on_step(routine):
        bars.append(ProgressBar(routine, args.quiet).__enter__())
        return bars[-1].on_progress

    try:
        done = run_sequence(args.routine, config, text, args.out, seed=args.seed, resume=args.resume, store=store,
                            on_step=on_step, save_images=args.save_images)
    finally:
        for bar in bars:
            bar.__exit__(None, None, None)
    for routine, result in done["results"].items():
        print_summary(result, Path(args.out) / done["summary"]["runs"][routine]["folder"])
    print(f"{args.routine}: {len(done['results'])} routines, cell time {done['summary']['cell_time_s']:.0f} s; "
          f"calibrations stored in {store.path}")
    return EXIT_OK


def fit(args) -> int:
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


def map_pixels(args) -> int:
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


def check(args) -> int:
    config, _ = load_cell_file(args.config)
    devices = ", ".join(f"{name} ({dev.backend})" for _, name, dev in config.devices())
    print(f"{args.config}: valid cell file {config.cell.name!r}: {devices}; areas: {', '.join(config.areas) or 'none'}")
    return EXIT_OK


def serve(args) -> int:
    from ..daemon import serve as serve_daemon

    return serve_daemon(args.config, args.host, args.port, tls=args.tls)


def token(args) -> int:
    """Print the daemon's token (read from the file beside its database; made at the daemon's first start)."""
    if not args.store and not args.config:
        raise InputError("token needs --config FILE (its store holds the token) or --store DIR")
    store = Path(args.store) if args.store else load_cell_file(args.config)[0].store_path()
    try:
        print(read_token(store))
    except (FileNotFoundError, ValueError, PermissionError) as exc:
        raise InputError(str(exc)) from None
    return EXIT_OK

