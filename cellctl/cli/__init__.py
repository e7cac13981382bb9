"""`cellctl`: run routines on a cell, fit recorded samples, map pixels with a calibration.

Exit status: 0 done, 1 the cell failed (device fault, job faulted, daemon unreachable),
2 bad input or refused (cell file, argument, samples file, a request the cell refused, a cell another
process owns, a port in use),
130 interrupted (samples kept; resume with --resume, or the job is paused or aborted).

Modules: `verbs` (the cell's verbs, one table, each bound to the daemon or to the cell file's
store), `local` (what runs in this process: run, fit, map, check, serve, token), `sim`
(`cellctl sim`: protocol simulators), `args` (input checks), `display` (progress, listings).
"""

from __future__ import annotations

import argparse
import sys

from calibration.routines import fit_aliases, routine_names

from cellctl.cli import verbs
from cellctl.cli.commission import add_commission_command
from cellctl.cli.fleet import add_fleet_command
from cellctl.cli.opcua import add_opcua_command
from cellctl.cli.sim import add_sim_command
from cellctl.cli.store import add_store_command
from cellctl.cli.verbs import (
    EXIT_FAULT,
    EXIT_INPUT,
    EXIT_INTERRUPTED,
    VERBS,
    Verb,
    connection_options,
    daemon_url,
    invoke,
)
from cellctl.startup import TLS_HELP

# Imports here stay light (no numerics, no pydantic, no web framework): `cellctl --help` and the daemon's
# verbs start in a fraction of a second. What runs in this process (.local) is imported when it runs.
# httpx loads its own command line (click, rich, pygments: more than half its import time) unless that is
# missing; cellctl never uses it, so it is marked missing before httpx is first imported.
sys.modules.setdefault("httpx._main", None)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        return _interrupted()
    except Exception as exc:  # noqa: BLE001 - mapped to an exit status below, or raised again
        if _raised(exc, "cellctl.errors:Unreachable"):
            print(f"cellctl: error: {exc}", file=sys.stderr)
            return EXIT_FAULT
        if _raised(exc, "cellctl.cli.args:InputError", "cellctl.config:CellFileError",
                   "calibration.errors:CalibrationError", "cellctl.stores.run_folder:RunFolderError",
                   "cellctl.errors:ServiceError"):
            print(f"cellctl: error: {exc}", file=sys.stderr)
            return EXIT_INPUT
        if _raised(exc, "drivers.interfaces:DeviceError"):
            print(f"cellctl: the cell failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            return EXIT_FAULT
        if _raised(exc, "cellctl.core.orchestrator:Aborted"):
            return _interrupted()
        raise


def _raised(exc: Exception, *classes: str) -> bool:
    """Is `exc` one of these "module:Class"es? A class whose module was never imported was not raised, so
    only the loaded modules are looked in (an error does not import the numerics to be classified)."""
    for target in classes:
        module, _, name = target.partition(":")
        if module in sys.modules and isinstance(exc, getattr(sys.modules[module], name)):
            return True
    return False


def _interrupted() -> int:
    print("cellctl: interrupted; the samples so far are kept (resume with --resume; a daemon job goes on)",
          file=sys.stderr)
    return EXIT_INTERRUPTED


def in_process(name: str):
    """The command `name` of .local (run, fit, plan, map, check, serve, token), imported when it runs."""

    def command(args) -> int:
        from cellctl.cli import local

        return getattr(local, name)(args)

    return command


class NamesKept(argparse.HelpFormatter):
    """Help wrapped between words only: a routine's name ("virtual-grid-area2") is never split at its hyphens."""

    def _split_lines(self, text: str, width: int) -> list[str]:
        import textwrap

        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cellctl", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", formatter_class=NamesKept, help="run a calibration routine on the cell (in-process, "
                                                                 "or through the daemon with --url / $CELLCTL_URL)")
    verbs.run_arguments(run)
    connection_options(run, local=True)
    run.set_defaults(func=cmd_run)

    for verb in VERBS:
        p = sub.add_parser(verb.name, help=verb.help)
        verb.arguments(p)
        connection_options(p, verb.local)
        p.set_defaults(func=lambda args, verb=verb: invoke(verb, args))

    fit = sub.add_parser("fit", formatter_class=NamesKept, help="fit a routine's model from a recorded samples CSV")
    fit.add_argument("routine", choices=sorted([*routine_names(), *fit_aliases()]), metavar="ROUTINE",
                     help="one of: " + ", ".join(routine_names()) + "".join(
                         f"; {alias}: {name}" for alias, name in fit_aliases().items()))
    fit.add_argument("--samples", required=True, help="CSV with the columns the routine fits from (its samples.csv "
                                                      "has them; docs/reference/csv-formats.md names each routine's)")
    fit.add_argument("--out", required=True, help="calibration JSON to write")
    fit.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    fit.add_argument("--image-size", metavar="WxH", help="camera resolution (default: from the pixels seen)")
    fit.add_argument("--config", help="cell file whose routine parameters to fit with (as the run did)")
    fit.set_defaults(func=in_process("fit"))

    plan = sub.add_parser("plan", formatter_class=NamesKept, help="show the poses a routine that plans its own motion "
                          "will visit, before anything moves (nothing connects)")
    plan.add_argument("routine", choices=routine_names(), metavar="ROUTINE", help="the routine (hand-eye)")
    plan.add_argument("--config", required=True, help="the cell file (its routine section and cameras)")
    plan.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    plan.set_defaults(func=in_process("plan"))

    mp = sub.add_parser("map", help="map pixels to robot millimetres with a calibration")
    mp.add_argument("calibration", help="cal.json from `cellctl fit`, or a run's result.json")
    mp.add_argument("--pixels", required=True, help="CSV with columns u_px,v_px")
    mp.add_argument("--out", required=True, help="CSV to write with u_px,v_px,x_mm,y_mm")
    mp.set_defaults(func=in_process("map_pixels"))

    check = sub.add_parser("check", help="validate a cell file")
    check.add_argument("--config", required=True)
    check.set_defaults(func=in_process("check"))

    serve = sub.add_parser("serve", help="run the cell daemon (HTTP API on 127.0.0.1)")
    serve.add_argument("--config", required=True, help="cell file (YAML)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8470)
    serve.add_argument("--tls", action="store_true", help=TLS_HELP)
    serve.set_defaults(func=in_process("serve"))

    token = sub.add_parser("token", help="print the daemon's token (local file; needs read access)")
    token.add_argument("--config", help="cell file (its store holds the token)")
    token.add_argument("--store", help="the store folder instead of --config (default: $CELLCTL_STORE)")
    token.set_defaults(func=in_process("token"))

    add_commission_command(sub)
    add_sim_command(sub)
    add_fleet_command(sub)
    add_opcua_command(sub)
    add_store_command(sub)
    return parser


SUBMIT = Verb("run", "submit a routine (or sequence) as a job to the daemon", verbs.submit)


def cmd_run(args) -> int:
    """Through the daemon when one is named, or when one owns the cell's store; else in this process."""
    if daemon_url(args):
        return invoke(SUBMIT, args)
    from cellctl.cli import local
    from cellctl.startup.ownership import CellOwned

    try:
        return local.run(args)
    except CellOwned as owned:  # nothing was touched: the owner's daemon takes the job, or the refusal stands
        return invoke(SUBMIT, local.through_owner(args, owned))


__all__ = ["build_parser", "main"]
