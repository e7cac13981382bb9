"""`cellctl fleet`: the plant database's view of every cell (status, jobs, calibrations, health), the fleet page,
and a replaced cell PC's calibrations restored from it.

The database is named by `--dsn-file F` (a libpq DSN or URI with its password, in an owner-only file), or by
the cell file of `--config` (its `fleet.postgres`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cellctl.cli.args import InputError

# the plant database's client and the stores are imported by the commands that use them: `cellctl --help`
# stays light

QUERIES = {"status": "every cell: state, last seen, live job, active calibrations and their health",
           "jobs": "every cell's jobs, newest first, with their sample counts",
           "calibrations": "every calibration version of every cell",
           "health": "the health of every cell's active calibrations, with the last check of each"}


def add_fleet_command(sub) -> None:
    fleet = sub.add_parser("fleet", help="the plant database: every cell's state, jobs, calibrations and health; "
                                         "the fleet page; restore a replaced cell PC")
    verbs = fleet.add_subparsers(dest="fleet_command", required=True)
    for name, text in QUERIES.items():
        p = verbs.add_parser(name, help=text)
        _database(p)
        p.add_argument("--cell", help="only this cell (its name in the plant)")
        if name == "calibrations":
            p.add_argument("--target", help="only this target (cam1, nozzle, ...)")
        p.add_argument("--json", action="store_true", help="print JSON instead of a table")
        p.set_defaults(func=lambda args, name=name: query(name, args))
    restore = verbs.add_parser("restore", help="put a cell's calibration versions (with their samples, provenance "
                                               "and checks) from the plant database into an empty local store; "
                                               "its new jobs are numbered after the old PC's")
    _database(restore)
    restore.add_argument("--cell", required=True, help="the cell whose calibrations to restore (its plant name)")
    restore.add_argument("--store", help="the store folder to fill (default: the store of --config's cell)")
    restore.set_defaults(func=restore_cell)
    serve = verbs.add_parser("serve", help="serve the fleet page (read-only; loopback by default)")
    _database(serve)
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8480)
    serve.set_defaults(func=serve_page)


def _database(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dsn-file", help="file holding the plant database's DSN (owner-only: chmod 600)")
    p.add_argument("--config", help="a cell file whose fleet.postgres names the database (and, for restore, "
                                    "the store)")


def dsn_of(args) -> str:
    from cellctl.config import load_cell_file
    from cellctl.fleet import secrets

    if args.dsn_file:
        return secrets.from_file(args.dsn_file, "--dsn-file")
    if args.config:
        config, _ = load_cell_file(args.config, routines=False)  # its fleet section only
        pg = config.fleet.postgres if config.fleet is not None else None
        if pg is None:
            raise InputError(f"{args.config} has no fleet.postgres section: give --dsn-file")
        return secrets.read("fleet.postgres", pg.dsn_file, pg.dsn_env, Path(args.config).parent)
    raise InputError("name the plant database: --dsn-file FILE, or --config CELL_FILE with a fleet.postgres section")


def query(name: str, args) -> int:
    import psycopg

    from cellctl.fleet import plant

    with plant.connect(dsn_of(args)) as conn:
        try:
            if name == "calibrations":
                data = plant.calibrations(conn, args.cell, args.target)
            else:
                data = getattr(plant, name)(conn, args.cell)
        except psycopg.errors.UndefinedTable:
            raise InputError("the plant database holds no cellctl tables yet: no cell has connected to it "
                             "(a cell makes them when its fleet.postgres first connects)") from None
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        PRINTERS[name](data)
    return 0


def restore_cell(args) -> int:
    from cellctl.config import load_cell_file
    from cellctl.fleet import plant
    from cellctl.startup.ownership import own_store
    from cellctl.stores.calibrations import CalibrationStore
    from cellctl.stores.jobs import DB_FILE, JobStore

    if args.store:
        store_dir = Path(args.store)
    elif args.config:
        store_dir = load_cell_file(args.config, routines=False)[0].store_path()
    else:
        raise InputError("restore needs --store DIR or --config CELL_FILE (its store)")
    with plant.connect(dsn_of(args)) as conn:
        cals, checks = plant.restore_records(conn, args.cell)
        last = plant.last_ids(conn, args.cell)
    if not cals:
        raise InputError(f"the plant database holds no calibration of cell {args.cell!r}")
    with own_store(store_dir, "cellctl fleet restore", verb=None):  # a store in use is no empty store
        store = CalibrationStore(store_dir)
        jobs = JobStore(store_dir / DB_FILE)
        try:
            if store.list():  # checked before anything is written: a refused restore leaves the store as it was
                raise InputError(f"{store_dir} already holds calibrations: restore into an empty store "
                                 "(a new folder)")
            jobs.continue_after(last)
            n = store.restore(cals, checks)
        finally:
            store.close()
            jobs.close()
    active = sorted(f"{c['target']} v{c['version']}" for c in cals if c["active"])
    print(f"restored {n} calibration versions and {len(checks)} checks of {args.cell} into {store_dir}; "
          f"active: {', '.join(active) or 'none'}")
    return 0


def serve_page(args) -> int:
    from cellctl.fleet.page import serve

    return serve(dsn_of(args), args.host, args.port)


# -- tables --------------------------------------------------------------------------------------


def _table(title: str, columns: list[str], rows: list[list]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    for c in columns:
        table.add_column(c)
    for r in rows:
        table.add_row(*("" if v is None else str(v) for v in r))
    console = Console()
    if not console.is_terminal:  # a pipe or a file: whole lines, not folded at 80 columns
        console = Console(width=200)
    console.print(table)


def _um(value) -> str:
    return f"{value:.2f}" if isinstance(value, (int, float)) else "-"


def _print_status(data: dict) -> None:
    rows = []
    for c in data["cells"]:
        cals = "; ".join(f"{t} v{v['version']} {_um(v['verification_mean_um'])} µm {v['health']}"
                         for t, v in sorted(c["calibrations"].items()))
        rows.append([c["name"], c["state"], c["last_seen"], c["live_job"] or "-", cals or "-"])
    _table("Cells", ["cell", "state", "last seen", "live job", "calibrations (verification mean, health)"], rows)


def _print_jobs(data: dict) -> None:
    _table("Jobs", ["cell", "id", "routine", "state", "samples", "updated"],
           [[j["cell"], j["id"], j["routine"], j["state"], j["samples"], j["updated"]] for j in data["jobs"]])


def _print_calibrations(data: dict) -> None:
    _table("Calibrations", ["cell", "id", "target", "version", "active", "routine", "created", "ver. mean µm"],
           [[c["cell"], c["id"], c["target"], c["version"], "ACTIVE" if c["active"] else "", c["routine"],
             c["created"], _um(c["verification_mean_um"])] for c in data["calibrations"]])


def _print_health(data: dict) -> None:
    rows = []
    for h in data["health"]:
        last = h["last_check"] or {}
        drift = last.get("drift") or {}
        rows.append([h["cell"], h["target"], h["version"], h["verdict"], last.get("created", "-"),
                     f"{last['p_value']:.3g}" if isinstance(last.get("p_value"), float) else "-",
                     f"{_um(drift.get('dx_um'))}, {_um(drift.get('dy_um'))}" if drift else "-", last.get("action", "-")])
    _table("Health", ["cell", "target", "version", "verdict", "last check", "p-value", "drift dx, dy µm", "action"],
           rows)


PRINTERS = {"status": _print_status, "jobs": _print_jobs, "calibrations": _print_calibrations,
            "health": _print_health}
