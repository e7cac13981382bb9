"""The CLI verbs that talk to a running daemon (`cellctl serve`) over HTTP.

The daemon's URL comes from `--url` or `CELLCTL_URL`; the token (for commands)
from `--token`, `CELLCTL_TOKEN`, or the token file beside the database of
`--config`'s cell (`cellctl token` prints it); an operator lock id, if this
client holds the lock, from `CELLCTL_LOCK`. Exit status as for the in-process
CLI: 0 done, 1 the cell failed (job faulted, daemon unreachable), 2 bad input
(the daemon refused the request), 130 interrupted (job paused or aborted).

`add_daemon_commands(subparsers)` registers the verbs on an argparse parser;
`main(argv)` runs them on their own (`python -m cellctl.client ...`).
"""

from __future__ import annotations

import argparse
import getpass
import json
import os
import socket
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx

EXIT_OK, EXIT_FAULT, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
TERMINAL = {"done": EXIT_OK, "faulted": EXIT_FAULT, "aborted": EXIT_INTERRUPTED}


class DaemonError(Exception):
    """The daemon refused a request (4xx) or could not be reached."""

    def __init__(self, message: str, status: int | None = None):
        super().__init__(message)
        self.status = status


class DaemonClient:
    def __init__(self, url: str, token: str | None = None, lock: str | None = None, timeout: float = 15.0):
        self.url = url.rstrip("/")
        headers = {"X-Cellctl-Client": _client_name()}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        if lock:
            headers["X-Cellctl-Lock"] = lock
        self.http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout)

    def close(self) -> None:
        self.http.close()

    def request(self, method: str, path: str, **kwargs) -> httpx.Response:
        try:
            r = self.http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            raise DaemonError(f"cannot reach the daemon at {self.url}: {exc}") from None
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise DaemonError(f"{r.status_code}: {detail}", r.status_code)
        return r

    def get(self, path: str, **params):
        return self.request("GET", path, params=params or None).json()

    def post(self, path: str, body: dict | None = None):
        return self.request("POST", path, json=body).json()

    def events(self, job: int | None = None, since: int | None = None) -> Iterator[tuple[str, dict]]:
        """(kind, data) from the server-sent event stream, as they come."""
        params = {k: v for k, v in (("job", job), ("since", since)) if v is not None}
        try:
            with self.http.stream("GET", "/events", params=params, timeout=httpx.Timeout(15.0, read=60.0)) as stream:
                kind = "message"
                for line in stream.iter_lines():
                    if line.startswith("event: "):
                        kind = line[7:]
                    elif line.startswith("data: "):
                        yield kind, json.loads(line[6:])
        except httpx.HTTPError as exc:
            raise DaemonError(f"the event stream from {self.url} broke: {exc}") from None


def _client_name() -> str:
    try:
        user = getpass.getuser()
    except Exception:  # noqa: BLE001 - no user name: still a client
        user = "user"
    return f"{user}@{socket.gethostname()}"[:64]


# -- arguments ---------------------------------------------------------------------------------


def daemon_url(args) -> str | None:
    """The daemon's URL from --url or CELLCTL_URL (None: no daemon asked for)."""
    return getattr(args, "url", None) or os.environ.get("CELLCTL_URL") or None


def _token(args) -> str | None:
    if getattr(args, "token", None):
        return args.token
    if os.environ.get("CELLCTL_TOKEN"):
        return os.environ["CELLCTL_TOKEN"]
    config = getattr(args, "config", None)
    if config:
        from .config import load_cell_file
        from .daemon.auth import read_token

        try:
            return read_token(load_cell_file(config)[0].store_path())
        except (FileNotFoundError, ValueError, PermissionError):
            return None
    return None


def connect(args) -> DaemonClient:
    url = daemon_url(args)
    if not url:
        raise DaemonError("no daemon: give --url URL or set CELLCTL_URL (e.g. http://127.0.0.1:8470)", 400)
    return DaemonClient(url, _token(args), os.environ.get("CELLCTL_LOCK"))


def _run(fn):
    """Wrap a verb: the client is opened and closed, errors become messages and exit codes."""

    def verb(args) -> int:
        try:
            client = connect(args)
        except DaemonError as exc:
            print(f"cellctl: error: {exc}", file=sys.stderr)
            return EXIT_INPUT
        try:
            return fn(client, args)
        except DaemonError as exc:
            print(f"cellctl: error: {exc}", file=sys.stderr)
            return EXIT_INPUT if exc.status is not None else EXIT_FAULT
        except KeyboardInterrupt:
            print("cellctl: stopped following; the job goes on in the daemon", file=sys.stderr)
            return EXIT_INTERRUPTED
        finally:
            client.close()

    verb.__name__ = fn.__name__
    verb.__doc__ = fn.__doc__
    return verb


# -- verbs ------------------------------------------------------------------------------------


@_run
def cmd_status(c: DaemonClient, args) -> int:
    """The cell, its devices, the arm's pose, the live job, the lock."""
    s = c.get("/cell")
    print(f"cell {s['cell']} ({'simulated' if s['simulated'] else 'real'}) at {c.url}")
    for d in s["devices"]:
        print(f"  {d['kind']:8s} {d['name']:10s} {d['backend']:10s} {d['state']}"
              + (f"  ({d['error']})" if d.get("error") else ""))
    p = s.get("arm_pose")
    if p:
        print(f"  arm pose: x {p['x_mm']:.3f} y {p['y_mm']:.3f} z {p['z_mm']:.3f} mm, alpha {p['alpha_deg']:.3f} deg")
    print(f"  live job: {s['job'] if s['job'] is not None else 'none'}")
    lock = s["lock"]
    print(f"  lock: held by {lock['holder']} ({lock['expires_in_s']} s left)" if lock.get("held") else "  lock: free")
    return EXIT_OK


@_run
def cmd_run(c: DaemonClient, args) -> int:
    """Submit a job; with --wait, follow it with a progress bar and print the result table."""
    from .cli import InputError, parse_params

    try:
        params = parse_params(args.param)
    except InputError as exc:
        raise DaemonError(str(exc), 400) from None
    body = {"routine": args.routine, "params": params}
    if args.seed is not None:
        body["seed"] = args.seed
    if getattr(args, "save_images", False):  # only when asked: a daemon from before it refuses the field
        body["save_images"] = True
    job = c.post("/jobs", body)
    print(f"job {job['id']} queued: {job['routine']} (run folder {job['run_dir']})")
    if not args.wait:
        return EXIT_OK
    return follow(c, job["id"], quiet=args.quiet)


def follow(c: DaemonClient, job_id: int, quiet: bool = False) -> int:
    """Follow a job to its end (or a pause) through the event stream; print its results."""
    bar = None if quiet else _Bar(job_id)
    try:
        job = c.get(f"/jobs/{job_id}")
        state = job["state"]
        if state not in TERMINAL and state != "paused":
            for kind, data in c.events(job=job_id, since=0):
                if kind == "progress" and bar:
                    bar.update(data)
                elif kind == "state":
                    state = data["state"]
                    if state in TERMINAL or state == "paused":
                        break
    finally:
        if bar:
            bar.close()
    job = c.get(f"/jobs/{job_id}")
    print(f"job {job_id}: {job['state']} ({job['reason']})")
    if job["state"] == "done":
        _print_results(c, job)
    elif job["state"] == "faulted":
        print(f"acknowledge it (cellctl ack {job_id}) and resume it (cellctl resume {job_id}) when the cell is safe")
    return TERMINAL.get(job["state"], EXIT_INTERRUPTED)


class _Bar:
    """step i / N, ETA in cell time, the current residual (rich, on stderr)."""

    def __init__(self, job_id: int):
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        self.progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("steps  cell {task.fields[cell]}  ETA {task.fields[eta]}  "
                                            "residual {task.fields[residual]}"), TimeElapsedColumn(),
                                 console=Console(stderr=True), transient=False)
        self.progress.__enter__()
        self.task = self.progress.add_task(f"job {job_id}", total=None, cell="-", eta="-", residual="-")

    def update(self, p: dict) -> None:
        eta = p.get("eta_cell_s")
        res = p.get("residual_um")
        name = p["item"] or p["routine"]
        self.progress.update(self.task, description=name, completed=p["step"], total=p["total"],
                             cell=f"{p['cell_time_s']:.1f} s", eta=f"{eta:.0f} s" if eta is not None else "-",
                             residual=f"{res:.2f} µm" if res is not None else "-")

    def close(self) -> None:
        self.progress.__exit__(None, None, None)


def _print_results(c: DaemonClient, job: dict) -> None:
    from .report import print_summary
    from .runs import SEQUENCES

    folder = Path(job["run_dir"])
    items = SEQUENCES.get(job["routine"])
    if items is None:
        print_summary(c.get(f"/jobs/{job['id']}/result"), folder)
        return
    for k, item in enumerate(items, start=1):
        print_summary(c.get(f"/jobs/{job['id']}/result", item=item), folder / f"{k:02d}-{item.replace('.', '-')}")
    summary = c.get(f"/jobs/{job['id']}/result")
    print(f"{job['routine']}: {len(items)} routines, cell time {summary['cell_time_s']:.0f} s")


@_run
def cmd_jobs(c: DaemonClient, args) -> int:
    """The jobs, newest first."""
    jobs = c.get("/jobs", **({"state": args.state} if args.state else {}))["jobs"]
    if not jobs:
        print("no jobs")
    for j in jobs:
        p = j.get("progress") or {}
        steps = f"{p.get('step', 0)}/{p.get('total', '?')}" if p else "-"
        print(f"{j['id']:5d}  {j['state']:8s} {j['routine']:20s} {steps:>9s}  seed {j['seed']}  {j['updated']}  "
              f"{j['reason']}")
    return EXIT_OK


@_run
def cmd_job(c: DaemonClient, args) -> int:
    """One job: parameters, progress, state history."""
    j = c.get(f"/jobs/{args.id}")
    print(f"job {j['id']}: {j['routine']} {json.dumps(j['params'])} seed {j['seed']}")
    print(f"  state {j['state']}: {j['reason']}" + ("" if j["acknowledged"] else "  (needs acknowledgement)"))
    if j.get("progress"):
        p = j["progress"]
        print(f"  progress: step {p['step']}/{p['total']}, cell time {p['cell_time_s']:.1f} s")
    print(f"  run folder: {j['run_dir']}")
    for h in j["history"]:
        print(f"  {h['at']}  {h['from'] or '-':8s} -> {h['to']:8s} {h['who']}: {h['reason']}")
    return EXIT_OK


def _job_action(action: str):
    @_run
    def verb(c: DaemonClient, args) -> int:
        body = {"mode": "immediate" if getattr(args, "immediate", False) else "deferred"} if action == "pause" else None
        j = c.post(f"/jobs/{args.id}/{action}", body)
        print(f"job {j['id']}: {j['state']}" + (f" ({j['reason']})" if j["reason"] else ""))
        if action == "resume" and getattr(args, "wait", False):
            return follow(c, j["id"], quiet=args.quiet)
        return EXIT_OK

    verb.__name__ = f"cmd_{action}"
    return verb


cmd_pause, cmd_resume, cmd_ack, cmd_abort = (_job_action(a) for a in ("pause", "resume", "ack", "abort"))


@_run
def cmd_results(c: DaemonClient, args) -> int:
    """The result tables of a finished job, and where its report and plot are."""
    job = c.get(f"/jobs/{args.id}")
    if job["state"] != "done":
        print(f"job {args.id} is {job['state']}; it has no result yet", file=sys.stderr)
        return EXIT_INPUT
    _print_results(c, job)
    print(f"report: {c.url}/jobs/{args.id}/report  plot: {c.url}/jobs/{args.id}/plot")
    return EXIT_OK


@_run
def cmd_calibrations(c: DaemonClient, args) -> int:
    """List calibrations; `activate ID`; `export ID --format opencv|json [--out FILE]`."""
    action = getattr(args, "action", None)
    if action == "activate":
        cal = c.post(f"/calibrations/{args.id}/activate")
        print(f"calibration {cal['id']} (version {cal['version']} of {cal['target']}) is now active")
        return EXIT_OK
    if action == "export":
        text = c.request("GET", f"/calibrations/{args.id}/export", params={"format": args.format}).text
        if args.out:
            from .store import write_atomic

            write_atomic(Path(args.out), text)
            print(f"wrote calibration {args.id} as {args.format} to {args.out}")
        else:
            sys.stdout.write(text)
        return EXIT_OK
    cals = c.get("/calibrations")["calibrations"]
    if not cals:
        print("no calibrations")
    for cal in cals:
        ver = (cal.get("stats") or {}).get("verification") or {}
        figure = f"ver mean {ver['mean_um']:.2f} µm" if ver.get("mean_um") is not None else ""
        print(f"{cal['id']:4d}  {cal['target']:8s} v{cal['version']:<3d} {'ACTIVE' if cal['active'] else '      '} "
              f"{cal['routine']:16s} {cal['created']}  {figure}")
    return EXIT_OK


@_run
def cmd_logs(c: DaemonClient, args) -> int:
    """The audit log: who did what, when, and whether it was allowed."""
    for a in c.get("/audit", limit=args.limit)["audit"]:
        print(f"{a['at']}  {a['client']:28s} {a['action']:32s} {a['target']:16s} {a['outcome']}"
              + (f"  {a['detail']}" if a["detail"] else ""))
    return EXIT_OK


@_run
def cmd_lock(c: DaemonClient, args) -> int:
    """Take, renew or release the operator lock (export CELLCTL_LOCK=<id> to command with it)."""
    if args.action == "acquire":
        got = c.post("/lock", {"holder": _client_name(), "ttl_s": args.ttl})
        print(f"lock held by {got['holder']} for {got['expires_in_s']} s; export CELLCTL_LOCK={got['lock_id']}")
    elif args.action == "release":
        c.request("DELETE", "/lock")
        print("lock released")
    else:
        s = c.get("/lock")
        print(f"held by {s['holder']} ({s['expires_in_s']} s left)" if s.get("held") else "free")
    return EXIT_OK


def cmd_token(args) -> int:
    """Print the daemon's token (read from the file beside its database; made at the daemon's first start)."""
    from .config import CellFileError, load_cell_file
    from .daemon.auth import read_token

    try:
        store = Path(args.store) if getattr(args, "store", None) else load_cell_file(args.config)[0].store_path()
        print(read_token(store))
    except (CellFileError, FileNotFoundError, ValueError, PermissionError) as exc:
        print(f"cellctl: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    return EXIT_OK


# -- registration -------------------------------------------------------------------------------


def _connection_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--url", help="the daemon (default: $CELLCTL_URL)")
    p.add_argument("--token", help="bearer token (default: $CELLCTL_TOKEN, or read via --config)")
    p.add_argument("--config", help="cell file, to read the token from beside the daemon's database")


def add_daemon_commands(sub, include_run: bool = True) -> None:
    """Register the daemon verbs on `sub` (argparse subparsers). `include_run=False` leaves out `run` and
    `calibrations` for a parser that already has in-process ones (then dispatch with `daemon_url(args)`)."""

    def verb(name, func, help_text):
        p = sub.add_parser(name, help=help_text)
        _connection_options(p)
        p.set_defaults(func=func)
        return p

    verb("status", cmd_status, "the daemon's cell: devices, arm pose, live job, lock")
    if include_run:
        p = verb("run", cmd_run, "submit a routine (or sequence) as a job to the daemon")
        add_run_options(p)
    verb("jobs", cmd_jobs, "list the jobs").add_argument("--state", help="only jobs in this state")
    verb("job", cmd_job, "one job with its history").add_argument("id", type=int)
    for name, func, text in (("pause", cmd_pause, "pause a job (at the next step boundary; --immediate: now)"),
                             ("resume", cmd_resume, "resume a paused (acknowledged) job"),
                             ("ack", cmd_ack, "acknowledge a faulted job (nothing moves; then resume)"),
                             ("abort", cmd_abort, "abort a job (arm stopped, samples kept)")):
        p = verb(name, func, text)
        p.add_argument("id", type=int)
        if name == "pause":
            p.add_argument("--immediate", action="store_true", help="stop the arm now; the cut step is redone")
        if name == "resume":
            p.add_argument("--wait", action="store_true", help="follow the job to its end")
            p.add_argument("--quiet", action="store_true", help="no progress bar")
    verb("results", cmd_results, "the result tables of a finished job").add_argument("id", type=int)
    if include_run:
        p = verb("calibrations", cmd_calibrations, "list, activate or export calibrations")
        add_calibrations_actions(p)
    verb("logs", cmd_logs, "the audit log").add_argument("--limit", type=int, default=100)
    p = verb("lock", cmd_lock, "the operator lock: acquire, release, status")
    p.add_argument("action", nargs="?", choices=["acquire", "release", "status"], default="status")
    p.add_argument("--ttl", type=float, default=600.0, help="seconds the lock lasts unless renewed")
    p = sub.add_parser("token", help="print the daemon's token (local file; needs read access)")
    p.add_argument("--config", help="cell file (its store holds the token)")
    p.add_argument("--store", help="the store folder instead of --config")
    p.set_defaults(func=cmd_token)


def add_run_options(p: argparse.ArgumentParser) -> None:
    from calibration.routines import ROUTINES

    from .runs import SEQUENCES

    p.add_argument("routine", choices=sorted(ROUTINES) + sorted(SEQUENCES))
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="routine parameter")
    p.add_argument("--seed", type=int, help="simulation seed (simulated cells only)")
    p.add_argument("--save-images", action="store_true",
                   help="keep every camera frame of the job as PNG under its run folder's images/")
    p.add_argument("--wait", action="store_true", help="follow the job: progress bar, then the result table")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_calibrations_actions(p: argparse.ArgumentParser) -> None:
    actions = p.add_subparsers(dest="action")
    a = actions.add_parser("activate", help="make calibration ID the active one of its target")
    a.add_argument("id", type=int)
    e = actions.add_parser("export", help="export a calibration")
    e.add_argument("id", type=int)
    e.add_argument("--format", choices=["opencv", "json"], default="json")
    e.add_argument("--out", help="file to write (default: standard output)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cellctl", description="talk to the cell daemon")
    add_daemon_commands(parser.add_subparsers(dest="command", required=True))
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
