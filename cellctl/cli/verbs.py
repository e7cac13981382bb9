"""The cell's verbs on the command line: one table, each verb bound to a `CellService`.

A verb runs against the daemon (`RemoteService`) when `--url` or `$CELLCTL_URL` names one;
the verbs that need no running cell (calibrations, their export and activation, locate) also
run in-process on the cell file's calibration store (`LocalService.of_store`, with `--config`).
The token comes from `--token`, `$CELLCTL_TOKEN` or the token file of the store (`--store`,
`$CELLCTL_STORE`, or `--config`'s cell's); an operator lock id, if this client holds the lock, from `$CELLCTL_LOCK`.
"""

from __future__ import annotations

import argparse
import getpass
import json
import os
import socket
import sys
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, get_args

from calibration.routines import routine_names, runnable_names, sequences

from cellctl.cli import manual
from cellctl.cli.args import InputError, parse_params
from cellctl.cli.camera import camera, camera_arguments
from cellctl.cli.display import (
    ProgressBar,
    print_audit,
    print_calibrations,
    print_health,
    print_job,
    print_jobs,
    print_operator,
    print_status,
)
from cellctl.errors import NotFound
from cellctl.service import Caller, CellService
from cellctl.service.interface import ExportFormat

EXIT_OK, EXIT_FAULT, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
TERMINAL = {"done": EXIT_OK, "faulted": EXIT_FAULT, "aborted": EXIT_INTERRUPTED}


@dataclass(frozen=True)
class Verb:
    name: str
    help: str
    run: Callable[[CellService, Caller, argparse.Namespace], int]
    arguments: Callable[[argparse.ArgumentParser], None] = lambda p: None
    local: bool = False  # also works without a daemon, on the cell file's calibration store


# -- binding a verb to a service -------------------------------------------------------------------


def client_name() -> str:
    try:
        user = getpass.getuser()
    except Exception:  # noqa: BLE001 - no user name: still a client
        user = "user"
    return f"{user}@{socket.gethostname()}"[:64]


def daemon_url(args) -> str | None:
    """The daemon's URL from --url or CELLCTL_URL (None: no daemon asked for)."""
    return getattr(args, "url", None) or os.environ.get("CELLCTL_URL") or None


def token(args) -> str | None:
    """The API token: --token, $CELLCTL_TOKEN, else the store's own (None: none readable)."""
    if getattr(args, "token", None):
        return args.token
    if os.environ.get("CELLCTL_TOKEN"):
        return os.environ["CELLCTL_TOKEN"]
    store = store_dir(args)
    if store is not None:
        from cellctl.service.auth import read_token

        try:
            return read_token(store)
        except (FileNotFoundError, ValueError, PermissionError):
            return None
    return None


def store_dir(args) -> Path | None:
    """The cell's store: --store, $CELLCTL_STORE, or the store of --config's cell (None: none named)."""
    if getattr(args, "store", None):
        return Path(args.store)
    if os.environ.get("CELLCTL_STORE"):
        return Path(os.environ["CELLCTL_STORE"])
    if getattr(args, "config", None):
        from cellctl.config import load_cell_file

        return load_cell_file(args.config, routines=False)[0].store_path()  # the store only: routines unchecked
    return None


def ca(args) -> str | None:
    """The certificate to trust for an https:// daemon (its own, pinned): --ca or $CELLCTL_CA."""
    chosen = getattr(args, "ca", None) or os.environ.get("CELLCTL_CA") or None
    if chosen and not Path(chosen).is_file():
        raise InputError(f"--ca / $CELLCTL_CA: {chosen} is not a file; give the daemon's certificate (PEM), e.g. a "
                         "copy of <store>/tls/daemon.crt from the cell PC")
    return chosen


def owner_daemon(args, owned, doing: str) -> tuple[str, str | None, str | None]:
    """(url, token, ca) of the daemon that owns the cell's store (ownership.CellOwned `owned`), said on one line
    with what is `doing` there; `owned` itself, raised, when no daemon serves it."""
    owner = owned.owner
    if owned.store is None or owner is None or not owner.url:
        raise owned
    print(f"cellctl: the cell's store {owned.store} is owned by the daemon at {owner.url} (pid {owner.pid}); {doing}",
          file=sys.stderr, flush=True)
    own_ca = owned.store / "tls" / "daemon.crt"  # the daemon's own certificate (cellctl.startup.tls)
    chosen_ca = ca(args) or (str(own_ca) if owner.url.startswith("https:") and own_ca.is_file() else None)
    return owner.url, getattr(args, "token", None) or _store_token(owned.store) or token(args), chosen_ca


def _store_token(store: Path) -> str | None:
    from cellctl.service.auth import read_token

    try:
        return read_token(store)
    except (FileNotFoundError, ValueError, PermissionError):
        return None


def service_for(verb: Verb, args) -> CellService:
    url = daemon_url(args)
    if url:
        from cellctl.service.remote import RemoteService

        return RemoteService(url, token(args), ca=ca(args))
    if verb.local and getattr(args, "config", None):
        from cellctl.config import load_cell_file
        from cellctl.service.local import LocalService
        from cellctl.stores.calibrations import CalibrationStore

        config, _ = load_cell_file(args.config)
        path = Path(getattr(args, "store", None) or config.store_path())
        store = CalibrationStore(path, replicate=config.fleet is not None)  # an activation reaches the plant too
        return LocalService.of_store(config, store)
    needs = " (or --config FILE to read the cell's store directly)" if verb.local else ""
    raise InputError(f"{verb.name}: no daemon: give --url URL or set CELLCTL_URL (e.g. http://127.0.0.1:8470){needs}")


def _owned_for(verb: Verb, args):
    """The store's ownership while a local verb writes it (beside a daemon the write would go unaudited)."""
    if daemon_url(args) or not (verb.local and getattr(args, "config", None) and _writes(verb, args)):
        return nullcontext()
    from cellctl.startup.ownership import own_store

    action = getattr(args, "action", None)
    cal_id = args.id if action in ("activate", "deactivate") else args.activate
    return own_store(store_dir(args), f"cellctl {verb.name} (local)",
                     verb=f"cellctl calibrations {action or 'activate'} {cal_id}")


def _writes(verb: Verb, args) -> bool:
    """Does this local verb write the store? (The others only read it, beside any owner.)"""
    return verb.name == "calibrations" and (getattr(args, "action", None) in ("activate", "deactivate")
                                            or getattr(args, "activate", None) is not None)


def invoke(verb: Verb, args) -> int:
    with _owned_for(verb, args):
        service = service_for(verb, args)
        try:
            # on the store itself (no daemon), the caller is the store's owner: the audit says so
            credential = "token" if daemon_url(args) else "local"
            caller = Caller(client_name(), os.environ.get("CELLCTL_LOCK"), f"cli {verb.name}", credential)
            return verb.run(service, caller, args)
        finally:
            close = getattr(service, "close", None)
            if close:
                close()


# -- the verbs ---------------------------------------------------------------------------------------


def status(s: CellService, caller: Caller, args) -> int:
    print_status(s.status(), getattr(s, "url", "this PC"))
    return EXIT_OK


def submit(s: CellService, caller: Caller, args) -> int:
    """`cellctl run` through the daemon: queue the job; with --wait, follow it and print its results."""
    job = s.submit(caller, args.routine, parse_params(args.param), args.seed, args.save_images)
    print(f"job {job['id']} queued: {job['routine']} (run folder {job['run_dir']})")
    return follow(s, job["id"], args.quiet) if args.wait else EXIT_OK


def follow(s: CellService, job_id: int, quiet: bool = False) -> int:
    """Follow a job to its end (or a pause) through the event stream; print its results."""
    job = s.job(job_id)
    if job["state"] not in TERMINAL and job["state"] != "paused":
        with ProgressBar(f"job {job_id}", quiet) as bar:
            for kind, data in s.events(job=job_id, since=0):
                if kind == "progress":
                    bar.on_event(data)
                elif kind == "state" and (data["state"] in TERMINAL or data["state"] == "paused"):
                    # the stream replays the job's earlier events too (since=0): a resumed job's old fault or
                    # pause ends nothing, so the job's state now decides
                    if s.job(job_id)["state"] in (*TERMINAL, "paused"):
                        break
    job = s.job(job_id)
    print(f"job {job_id}: {job['state']} ({job['reason']})")
    if job["state"] == "done":
        print_results(s, job)
    elif job["state"] == "faulted":
        print(f"acknowledge it (cellctl ack {job_id}) and resume it (cellctl resume {job_id}) when the cell is safe")
    return TERMINAL.get(job["state"], EXIT_INTERRUPTED)


def print_results(s: CellService, job: dict) -> None:
    from cellctl.core.report import print_summary

    folder = Path(job["run_dir"])
    sequence = sequences().get(job["routine"])
    if sequence is None:
        print_summary(s.result(job["id"]), folder)
        return
    summary = s.result(job["id"])  # of a sequence that did not finish: the routines that did
    for item in summary["runs"]:
        print_summary(s.result(job["id"], item), folder / sequence.folder(item))
    if summary.get("complete", True):
        print(f"{job['routine']}: {len(sequence.items)} routines, cell time {summary['cell_time_s']:.0f} s")
    else:
        print(f"{summary['message']}; not finished: {', '.join(summary['not_finished'])}")


def jobs(s: CellService, caller: Caller, args) -> int:
    listed = s.jobs(args.state)
    if args.json:
        print(json.dumps(listed, indent=2))
    else:
        print_jobs(listed)
    return EXIT_OK


def job(s: CellService, caller: Caller, args) -> int:
    print_job(s.job(args.id))
    return EXIT_OK


def job_command(action: str) -> Callable[[CellService, Caller, argparse.Namespace], int]:
    def command(s: CellService, caller: Caller, args) -> int:
        if action == "pause":
            j = s.pause(caller, args.id, args.immediate)
        else:
            j = getattr(s, action)(caller, args.id)
        print(j["message"])  # what the command did: a pause asked of a running job takes effect later
        if action == "resume" and args.wait:
            return follow(s, j["id"], args.quiet)
        return EXIT_OK

    return command


def results(s: CellService, caller: Caller, args) -> int:
    """The result tables of the job's routines that finished: all of them once it is done; of a sequence that did
    not finish, those that did (their results and the calibrations they stored and activated stand), then what
    happened. Exit status: how the job ended, as `run --wait` says it (0 done, 1 faulted, 130 aborted or paused),
    so a script never takes a part for the whole; 2 while it is queued or running."""
    job = s.job(args.id)
    if job["state"] != "done":
        try:
            print_results(s, job)
        except NotFound as exc:  # a single routine that did not finish: no result, and the reason why
            print(f"cellctl: {exc}", file=sys.stderr)
        return {**TERMINAL, "paused": EXIT_INTERRUPTED}.get(job["state"], EXIT_INPUT)
    print_results(s, job)
    url = getattr(s, "url", None)
    if url:
        print(f"report: {url}/jobs/{args.id}/report  plot: {url}/jobs/{args.id}/plot")
    return EXIT_OK


def calibrations(s: CellService, caller: Caller, args) -> int:
    """List; `activate ID` (or --activate ID); `deactivate ID`; `export ID --format opencv|json|urdf [--out FILE]`
    (urdf: an `arm` calibration)."""
    if args.action == "activate" or args.activate is not None:
        cal = s.activate(caller, args.id if args.action == "activate" else args.activate)
        print(f"calibration {cal['id']} (version {cal['version']} of {cal['target']}) is now active")
    elif args.action == "deactivate":
        cal = s.deactivate(caller, args.id)
        print(f"calibration {cal['id']} (version {cal['version']} of {cal['target']}) is out of use: "
              f"{cal['target']} has no active calibration")
    elif args.action == "export":
        doc = s.export(args.id, args.format)
        if args.out:
            from cellctl.stores.run_folder import write_atomic

            write_atomic(Path(args.out), doc.text)
            print(f"wrote calibration {args.id} as {args.format} to {args.out}")
        else:
            sys.stdout.write(doc.text)
    elif args.json:
        print(json.dumps(s.calibrations(), indent=2))
    else:
        print_calibrations(s.calibrations(), getattr(s, "url", None) or str(getattr(s, "store_dir", "")))
    return EXIT_OK


def locate(s: CellService, caller: Caller, args) -> int:
    where = s.locate(args.camera, *args.pixel, tuple(args.arm_pose) if args.arm_pose else None, args.diameter_px,
                     args.z_mm, tuple(args.flange) if args.flange else None)
    if args.json:
        print(json.dumps(where, indent=2))
        return EXIT_OK
    if "z_mm" in where:  # a hand-eye camera: the base frame
        print(f"x_mm={where['x_mm']:.4f} y_mm={where['y_mm']:.4f} z_mm={where['z_mm']:.4f} "
              f"sigma_um={_sigma(where['sigma_um'])}  (base frame, on the {where['plane']} plane)")
        print(f"calibration {where['calibration_id']} (version {where['version']} of hand-eye:{where['camera']}), "
              f"health: {where['health']}")
        return EXIT_OK
    print(f"x_mm={where['x_mm']:.4f} y_mm={where['y_mm']:.4f} sigma_um={_sigma(where['sigma_um'])}  (commanded "
          "position at alpha_cal that puts the nozzle there; sigma: 1-σ per axis)")
    region = {True: "outside", False: "inside", None: "unknown (an older calibration: it keeps no region)"}
    print(f"calibration {where['calibration_id']} (version {where['version']} of {where['camera']}), "
          f"health: {where['health']}, calibrated region: {region[where['outside_calibrated_region']]}")
    if where["warning"]:
        print(f"cellctl: warning: {where['warning']}", file=sys.stderr)
    return EXIT_OK


def _sigma(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def features(s: CellService, caller: Caller, args) -> int:
    seen = s.features(args.camera)
    if args.json:
        print(json.dumps(seen, indent=2))
        return EXIT_OK
    print(f"{seen['camera']}: frame {seen['frame_id']}, {len(seen['features'])} features")
    print(f"{'kind':<7} {'u_px':>9} {'v_px':>9} {'x_mm':>10} {'y_mm':>10} {'sigma_um':>8} {'diam_px':>8}")
    for f in seen["features"]:
        xy = (f"{f['x_mm']:>10.4f} {f['y_mm']:>10.4f}" if f["x_mm"] is not None else f"{'-':>10} {'-':>10}")
        print(f"{f['kind']:<7} {f['u_px']:>9.2f} {f['v_px']:>9.2f} {xy} {_sigma(f['sigma_um']):>8} "
              f"{f['diameter_px']:>8.1f}" + (" *" if f.get("outside_calibrated_region") else ""))
    if any(f.get("outside_calibrated_region") for f in seen["features"]):
        print("* outside the calibrated region: the map extrapolates there; sigma_um is its grown uncertainty")
    return EXIT_OK


def health(s: CellService, caller: Caller, args) -> int:
    answer = s.health()
    if args.json:
        print(json.dumps(answer, indent=2))
    else:
        print_health(answer["targets"], args.history)
    return EXIT_OK


def logs(s: CellService, caller: Caller, args) -> int:
    entries = s.audit(args.limit)
    if args.json:
        print(json.dumps(entries, indent=2))
    else:
        print_audit(entries)
    return EXIT_OK


def operator(s: CellService, caller: Caller, args) -> int:
    """The pending operator request (`show`, the default), or its answer: `done ID`, `decline ID [--reason]`.
    A click request is shown with where to answer it: clicks are given at the web console, not here."""
    if args.action != "show" and args.id is None:
        raise InputError(f"cellctl operator {args.action}: give the request's id (cellctl operator shows it)")
    state = s.operator_request()
    console = f"{s.url}/console/" if getattr(s, "url", None) else None
    if args.action == "show":
        if args.json:
            print(json.dumps(state, indent=2))
        else:
            print_operator(state, console)
        return EXIT_OK
    req = state.get("request")
    if req is not None and req["id"] == args.id and req["answer_with"] == "clicks":
        raise InputError(f"operator request {args.id} asks for clicks on a camera frame: answer it (or decline it) "
                         f"at the web console{f' ({console})' if console else ''}, where the frame is shown; the "
                         "CLI cannot click (cellctl abort JOB stops the job instead)")
    if args.action == "done":
        got = s.operator_done(caller, args.id)
    else:
        got = s.operator_decline(caller, args.id, args.reason)
    print(f"operator request {got['request']}: {got['outcome']}" + (f" (job {got['job']})" if got.get("job") else ""))
    return EXIT_OK


def lock(s: CellService, caller: Caller, args) -> int:
    if args.action == "acquire":
        got = s.acquire_lock(caller, caller.who, args.ttl)
        print(f"lock held by {got['holder']} for {got['expires_in_s']} s; export CELLCTL_LOCK={got['lock_id']}")
    elif args.action == "release":
        s.release_lock(caller)
        print("lock released")
    elif args.action == "break":
        got = s.break_lock(caller, args.reason)["broken"]
        print(f"lock of {got['holder']} broken ({got['reason']}); its holder is told, the audit keeps it")
    else:
        got = s.lock_status()
        print(f"held by {got['holder']} ({got['expires_in_s']} s left, idle {got['idle_s']:.0f} s)"
              if got.get("held") else "free")
    return EXIT_OK


# -- their arguments --------------------------------------------------------------------------------


def run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("routine", choices=runnable_names(), metavar="ROUTINE",
                   help="a routine (" + ", ".join(routine_names()) + ") or a sequence of them (" +
                        ", ".join(sequences()) + ")")
    p.add_argument("--out", help="run folder (created; with --resume, reopened); required in-process")
    p.add_argument("--seed", type=int,
                   help="the simulation seed (simulated cells only; default: the cell file's sim.seed)")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="routine parameter")
    p.add_argument("--resume", action="store_true", help="in-process: continue a run from its persisted samples")
    p.add_argument("--save-images", action="store_true", help="keep every camera frame as PNG in the run folder")
    p.add_argument("--wait", action="store_true", help="daemon: follow the job, then print the result table")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def json_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print the service's answer as JSON")


def jobs_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--state", help="only jobs in this state")
    json_option(p)


def health_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--history", action="store_true", help="every check, not only the last")
    json_option(p)


def logs_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--limit", type=int, default=100)
    json_option(p)


def job_id_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("id", type=int)


def pause_arguments(p: argparse.ArgumentParser) -> None:
    job_id_argument(p)
    p.add_argument("--immediate", action="store_true", help="stop the arm now; the cut step is redone")


def resume_arguments(p: argparse.ArgumentParser) -> None:
    job_id_argument(p)
    p.add_argument("--wait", action="store_true", help="follow the job to its end")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def calibrations_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--activate", type=int, metavar="ID", help="make calibration ID the active one of its target")
    json_option(p)
    actions = p.add_subparsers(dest="action")
    a = actions.add_parser("activate", help="make calibration ID the active one of its target")
    a.add_argument("id", type=int)
    d = actions.add_parser("deactivate", help="take calibration ID out of use (its target then has none)")
    d.add_argument("id", type=int)
    e = actions.add_parser("export", help="export a calibration")
    e.add_argument("id", type=int)
    e.add_argument("--format", choices=get_args(ExportFormat), default="json",
                   help="json, opencv (OpenCV FileStorage YAML), or urdf (an arm calibration: the calibrated arm)")
    e.add_argument("--out", help="file to write (default: standard output)")
    for action in (a, d, e):  # `calibrations activate 1 --config F`: the options work after the action too
        connection_options(action, local=True, below=True)


def locate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--camera", required=True)
    p.add_argument("--pixel", required=True, nargs=2, type=float, metavar=("U", "V"))
    p.add_argument("--arm-pose", nargs=3, type=float, metavar=("X_MM", "Y_MM", "ALPHA_DEG"),
                   help="the arm's reported pose, for a camera that rides on it")
    p.add_argument("--diameter-px", type=float, help="a sphere's apparent diameter (a calibration that corrects "
                                                     "sphere heights uses it)")
    p.add_argument("--z-mm", type=float, help="a hand-eye camera: the height of the plane to locate on (base "
                                              "frame; default: the board's plane)")
    p.add_argument("--flange", nargs=7, type=float, metavar=("X_MM", "Y_MM", "Z_MM", "QW", "QX", "QY", "QZ"),
                   help="a wrist camera (hand-eye): the flange pose the frame was taken at (default: the arm's "
                        "pose now, from the daemon)")
    p.add_argument("--json", action="store_true", help="print the service's answer as JSON")


def features_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("camera")
    p.add_argument("--json", action="store_true", help="print the service's answer as JSON")


def operator_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", nargs="?", choices=["show", "done", "decline"], default="show",
                   help="show the pending request (default); done ID: its instruction is done; decline ID: it cannot "
                        "be done (the job faults; acknowledge and resume to be asked again)")
    p.add_argument("id", nargs="?", type=int, help="the request's id (done, decline)")
    p.add_argument("--reason", default="", help="decline: why (shown in the job's reason)")
    p.add_argument("--json", action="store_true", help="show: print the service's answer as JSON")


def lock_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", nargs="?", choices=["acquire", "release", "status", "break"], default="status",
                   help="break: free a stale lock whoever holds it (needs --reason; audited, the holder is told)")
    p.add_argument("--ttl", type=float, default=600.0, help="seconds the lock lasts unless renewed")
    p.add_argument("--reason", default="", help="break: why (required; shown to the holder, kept in the audit)")


VERBS = (
    Verb("status", "the daemon's cell: devices, arm pose, live job, lock", status),
    Verb("jobs", "list the jobs", jobs, jobs_arguments),
    Verb("job", "one job with its history", job, job_id_argument),
    Verb("pause", "pause a job (at the next step boundary; --immediate: now)", job_command("pause"),
         pause_arguments),
    Verb("resume", "resume a paused (acknowledged) job", job_command("resume"), resume_arguments),
    Verb("ack", "acknowledge a faulted job (nothing moves; then resume)", job_command("acknowledge"),
         job_id_argument),
    Verb("abort", "abort a job (arm stopped, samples kept)", job_command("abort"), job_id_argument),
    Verb("results", "the result tables of a job's finished routines (exit status: how the job ended)", results,
         job_id_argument),
    Verb("calibrations", "list the stored calibrations, make one active, or export one", calibrations,
         calibrations_arguments, local=True),
    Verb("locate", "where in robot coordinates is what a camera sees at a pixel", locate, locate_arguments,
         local=True),
    Verb("features", "what a camera sees now: nozzle and spheres with pixel, robot position, sigma", features,
         features_arguments),
    Verb("camera", "a camera live: its exposure and gain (--set), a drawn frame (--snapshot PNG), the settings "
         "written back to the cell file (--save, --yes)", camera, camera_arguments),
    Verb("jog", "jog the arm one step along or about an axis (the lock holder; checked, audited)", manual.jog,
         manual.jog_arguments),
    Verb("move-to", "move the arm in a straight line to X Y Z or a named position (the lock holder)",
         manual.move_to, manual.move_to_arguments),
    Verb("grip", "switch the vacuum on by hand (the lock holder)", manual.vacuum(True)),
    Verb("release", "switch the vacuum off by hand (the lock holder)", manual.vacuum(False)),
    Verb("health", "do the calibrations still hold: per target its last check, verdict and drift", health,
         health_arguments, local=True),
    Verb("logs", "the audit log", logs, logs_arguments),
    Verb("lock", "the operator lock: acquire, release, status, break --reason TEXT", lock, lock_arguments),
    Verb("operator", "what a routine waits for a person to do: show it, answer done or decline (clicks: at the "
         "web console)", operator, operator_arguments),
)


def connection_options(p: argparse.ArgumentParser, local: bool, below: bool = False) -> None:
    """--url, --token, --ca, --config, --store. `below`: on an action's parser (`calibrations activate`), where
    an option not given must leave the verb's value alone (argparse copies a sub-parser's defaults over it)."""
    default = argparse.SUPPRESS if below else None
    p.add_argument("--url", default=default, help="the daemon (default: $CELLCTL_URL)" + (
        "; none: read the store directly" if local else ""))
    p.add_argument("--token", default=default, help="the daemon's token (default: $CELLCTL_TOKEN, or the token "
                                                    "file of the store: --store, $CELLCTL_STORE or --config's)")
    p.add_argument("--ca", metavar="FILE", default=default, help="an https:// daemon's certificate to trust "
                   "(pinned; default: $CELLCTL_CA; the daemon's is <store>/tls/daemon.crt)")
    p.add_argument("--config", default=default, help="cell file: names the store (and the token file beside it)")
    p.add_argument("--store", default=default, help="calibration store folder (default: $CELLCTL_STORE, the cell "
                                                    "file's store_dir, or ~/.local/share/cellctl/CELL)")
