"""What the CLI does in this process, on a cell file or on files: run a routine, fit, map, check, serve."""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path

import numpy as np

from calibration.routines import fit_aliases, is_sequence, routine_class

from cellctl.cli.args import InputError, parse_params, parse_size, read_csv, read_text
from cellctl.cli.display import ProgressBar, fill, label
from cellctl.cli.verbs import EXIT_OK, client_name, owner_daemon, store_dir
from cellctl.config import load_cell_file
from cellctl.core.report import print_summary, print_tables
from cellctl.core.runs import fit_samples, preview_routine
from cellctl.service import Caller
from cellctl.service.auth import read_token
from cellctl.startup.ownership import CellOwned, own_cell
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.run_folder import write_atomic, write_json


def run(args) -> int:
    """`cellctl run` without a daemon: the routine (or sequence) runs here, into --out, while this process owns
    the cell (CellOwned when another process does: cmd_run then goes through its daemon, see through_owner)."""
    if not args.config:
        raise _needs("--config FILE")
    config, text = load_cell_file(args.config)
    store_path = Path(args.store) if args.store else config.store_path()
    with own_cell(config, store_path, f"cellctl run {args.routine}"):
        if store_path.exists():  # as the daemon at its start: never run on a store that fails its check
            from cellctl.stores.backup import check_store

            backups = config.store.backup
            hint = f" --store {store_path}" if args.store else f" --config {args.config}"
            check_store(store_path, backups.folder(store_path) if backups else None, hint)
        return run_owned(args, config, text, store_path)


def _needs(option: str) -> InputError:
    return InputError(f"run in-process needs {option} (or give --url URL / $CELLCTL_URL to submit the job to the "
                      "daemon)")


def run_owned(args, config, text, store_path: Path) -> int:
    """The run through the service on the store this process owns: checked as a daemon's job is, and audited."""
    if not args.out:  # asked only now: when a daemon owns the cell, it takes the job and picks the folder
        raise _needs("--out DIR")
    overrides = parse_params(args.param)
    # a cell in a fleet: what this run stores goes to the plant with the daemon's next delivery
    from cellctl.service.local import LocalService  # the service's heavy half, for the run only (not fit, check)

    store = CalibrationStore(store_path, replicate=config.fleet is not None)
    service = LocalService.of_store(config, store, text)
    caller = Caller(client_name(), None, "cli run (in-process)", credential="local")
    try:
        if is_sequence(args.routine):
            return run_sequence_here(args, service, caller, overrides)
        with ProgressBar(args.routine, args.quiet) as bar:
            result = service.run_here(caller, args.routine, overrides, args.seed, Path(args.out), resume=args.resume,
                                      save_images=args.save_images, on_progress=bar.on_progress)
    finally:
        service.close()
    print_summary(result, Path(args.out))
    if "calibration" in result:
        c = result["calibration"]
        print(f"stored as calibration {c['id']} (version {c['version']} of {c['target']}, active) in {store.path}")
    return EXIT_OK


def through_owner(args, owned: CellOwned) -> argparse.Namespace:
    """The arguments of `cellctl run --url --wait` to the daemon that owns the cell's store (said on one line),
    or `owned` itself, raised, when no daemon can take the job: another owner, --resume (its job is the
    daemon's to resume)."""
    owner = owned.owner
    if args.resume and owned.store is not None and owner is not None and owner.url:
        raise InputError(f"--resume continues an in-process run, but the cell's store {owned.store} is owned by "
                         f"{owner.describe()}: resume its job there (cellctl jobs --url {owner.url} lists them; "
                         f"cellctl resume JOB --url {owner.url})")
    ignored = "; --out is ignored: the daemon picks the run folder (named below)" if args.out else ""
    url, token, ca = owner_daemon(args, owned, f"submitting the job there and following it{ignored}")
    return argparse.Namespace(**{**vars(args), "url": url, "wait": True, "token": token, "ca": ca})


def run_sequence_here(args, service, caller: Caller, overrides: dict) -> int:
    bars: list[ProgressBar] = []

    def on_step(routine):
        bars.append(ProgressBar(label(args.routine, routine), args.quiet).__enter__())
        return bars[-1].on_progress

    try:
        done = service.run_here(caller, args.routine, overrides, args.seed, Path(args.out), resume=args.resume,
                                save_images=args.save_images, on_step=on_step)
    finally:
        for bar in bars:
            bar.__exit__(None, None, None)
    for routine, result in done["results"].items():
        print_summary(result, Path(args.out) / done["summary"]["runs"][routine]["folder"])
    print(f"{args.routine}: {len(done['results'])} routines, cell time {done['summary']['cell_time_s']:.0f} s; "
          f"calibrations stored in {service.calstore.path}")
    return EXIT_OK


def fit(args) -> int:
    routine = fit_aliases().get(args.routine, args.routine)
    columns = routine_class(routine).fit_columns
    numeric = tuple(c for c in columns if c.endswith(("_mm", "_px", "_deg")))
    samples = read_csv(args.samples, columns, numeric=numeric)
    for row in samples:  # no step column: each routine knows how its rows group (by joints, by position)
        row.setdefault("status", "ok")
    resolutions = {"*": parse_size(args.image_size)} if args.image_size else None
    cell = load_cell_file(args.config)[0] if args.config else None
    result, _ = fit_samples(routine, samples, parse_params(args.param), resolutions, cell)
    write_json(Path(args.out), result)
    s = result["stats"]
    cal, ver = s.get("calibration", {}), s.get("verification", {})
    if "mean_um" not in cal and result.get("summary"):  # a routine whose figures are not a plane's residuals
        said = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in result["summary"].items())
        print(f"fitted {result['n_samples']} rows: {said}; rejected {len(result['rejected'])}; wrote {args.out}")
        return EXIT_OK
    print((f"fitted {cal['n']} samples: residual mean {cal['mean_um']:.2f} µm; " if cal.get("n") else "")
          + (f"verification on {ver['n']}: mean {ver['mean_um']:.2f} µm, max {ver['max_um']:.2f} µm"
             if ver.get("n") else "no verification rows")
          + f"; rejected {len(result['rejected'])}; wrote {args.out}")
    return EXIT_OK


def plan(args) -> int:
    config = load_cell_file(args.config)[0]
    print_tables(args.routine, preview_routine(args.routine, config, parse_params(args.param)))
    return EXIT_OK


def map_pixels(args) -> int:
    """Each pixel's plane position, its 1-σ (from the calibration's covariance, if it keeps one) and whether it lies
    outside the calibrated region (empty: the calibration keeps no region); a pixel off the image is refused."""
    from calibration.models.planar import PlanarMap
    from calibration.usage import OUTSIDE_REGION, map_sigma

    try:
        doc = json.loads(read_text(args.calibration, "calibration"))
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
    off = np.nonzero(~planar.on_image(uv))[0]
    if off.size:  # the map would answer there too, with a number that means nothing
        i = int(off[0])
        said = planar.off_image(*uv[i], "the calibration's")
        raise InputError(f"{args.pixels}: row {i + 2}: {said}"
                         " (the size it was fitted with: `cellctl fit --image-size WxH` sets it)")
    xy = planar.pixel_to_plane(uv) * scale
    sigma_um = map_sigma(model, uv) * scale * 1e3
    inside = planar.in_region(uv)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["u_px", "v_px", "x_mm", "y_mm", "sigma_um", "outside_calibrated_region"])
    for i, ((u, v), (x, y), sigma) in enumerate(zip(uv, xy, sigma_um)):
        w.writerow([repr(float(u)), repr(float(v)), f"{x:.6f}", f"{y:.6f}",
                    f"{sigma:.3f}" if np.isfinite(sigma) else "", "" if inside is None else int(not inside[i])])
    write_atomic(Path(args.out), buf.getvalue())
    print(f"mapped {len(rows)} pixels; wrote {args.out}")
    if inside is not None and not inside.all():
        outside = [str(i + 2) for i in np.nonzero(~inside)[0]]
        print(f"cellctl: warning: {len(outside)} of {len(rows)} pixels (rows {', '.join(outside[:10])}"
              f"{', ...' if len(outside) > 10 else ''}) are {OUTSIDE_REGION}", file=sys.stderr)
    return EXIT_OK


def check(args) -> int:
    config, _ = load_cell_file(args.config)
    print(f"{args.config}: valid cell file {config.cell.name!r}")
    for what, names in (("devices", [f"{name} ({dev.backend})" for _, name, dev in config.devices()]),
                        ("areas", list(config.areas)), ("routines", list(config.routines))):
        print(fill(f"{what}: {', '.join(names) or 'none'}", indent=4, first=2))
    return EXIT_OK


def serve(args) -> int:
    from cellctl.startup import serve as serve_daemon

    return serve_daemon(args.config, args.host, args.port, tls=args.tls)


def token(args) -> int:
    """Print the daemon's token (read from the file beside its database; made at the daemon's first start)."""
    store = store_dir(args)
    if store is None:
        raise InputError("token needs --config FILE (its store holds the token), --store DIR or $CELLCTL_STORE")
    try:
        print(read_token(store))
    except (FileNotFoundError, ValueError, PermissionError) as exc:
        raise InputError(str(exc)) from None
    return EXIT_OK

