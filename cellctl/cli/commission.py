"""`cellctl commission`: the device self-test (the work: cellctl/service/commission.py).

    cellctl commission --config CELL                 every device: link, readings, grip, focus, exposure; the
                                                     arm's 5 mm move and back after a y at the prompt
    cellctl commission --config CELL --device cam2   one device
    cellctl commission --config CELL --move          the motion without asking (--yes too)
    cellctl commission --config CELL --json          the service's answer as JSON

Through the daemon when one is named (--url, $CELLCTL_URL) or owns the cell's store (the motion then needs the
operator lock: cellctl lock acquire, export CELLCTL_LOCK); else in this process, on the cell file's devices, while
this process owns the cell (as `cellctl run` does). Exit status: 0 no problem found, 1 a check found a problem,
2 bad input or refused.
"""

from __future__ import annotations

import argparse
import json
import sys

from cellctl.cli.args import InputError
from cellctl.cli.verbs import EXIT_FAULT, EXIT_OK, Verb, client_name, connection_options, daemon_url, invoke

DESCRIPTION = ("The device self-test. For each device, in order: the link (connect, version, latency); the readings "
               "(pose and joints, vacuum, a frame); the arm's slow 5 mm move and back, only when confirmed (--move, "
               "--yes, or y at the prompt; else skipped), which each camera that sees it measures from its images; a "
               "grip with nothing held; each camera's focus and exposure. Every finding names its fix. Through the "
               "daemon when one is named (--url, $CELLCTL_URL) or owns the cell's store (the move then needs the "
               "operator lock); else in this process on the cell file's devices. Exit status: 0 nothing found, 1 a "
               "check found a problem, 2 bad input or refused.")
MOVE_PROMPT = ("The self-test moves the arm {mm:g} mm and back, slowly ({speed:g} mm/s), from where it stands. "
               "Is the way clear? [y/N] ")


def add_commission_command(sub) -> None:
    p = sub.add_parser("commission", help="the device self-test: each device's link, readings, a confirmed 5 mm "
                                          "move of the arm, a grip with nothing held, each camera's focus and "
                                          "exposure; every finding with its fix (exit 1 when one is found)",
                          description=DESCRIPTION)
    p.add_argument("--device", metavar="NAME", help="only this device (the arm, the gripper or a camera)")
    p.add_argument("--move", action="store_true", help="move the arm 5 mm and back without asking (the operator "
                                                       "confirms the way is clear)")
    p.add_argument("--yes", "-y", action="store_true", help="the same as --move")
    p.add_argument("--json", action="store_true", help="print the service's answer as JSON")
    connection_options(p, local=True)
    p.set_defaults(func=cmd_commission)


def run_commission(s, caller, args) -> int:
    move = confirmed(args)
    if move:  # the move is for the lock's holder: this client's lock, else one taken for the command (as jog does)
        from cellctl.cli.manual import holding_lock

        with holding_lock(s, caller) as with_lock:
            answer = s.commission(with_lock, args.device, move)
    else:
        answer = s.commission(caller, args.device, move)
    if args.json:
        print(json.dumps(answer, indent=2))
    else:
        from cellctl.cli.display import print_checks

        print_checks(answer)
    return EXIT_FAULT if answer["problems"] else EXIT_OK


COMMISSION = Verb("commission", "the device self-test", run_commission)


def moves(args) -> bool:
    """Would the self-test move the arm (every device, the arm, or a camera watching it)? The gripper alone: no."""
    return args.device is None or args.device != "gripper"


def confirmed(args) -> bool:
    """The motion runs only when the operator confirmed it: --move / --yes, or y at the prompt on a terminal.
    Without either the motion check is reported as skipped."""
    if args.move or args.yes:
        return True
    if not moves(args) or not sys.stdin.isatty():
        return False
    from cellctl.service.commission import MOVE_MM, MOVE_SPEED_M_S

    print(MOVE_PROMPT.format(mm=MOVE_MM, speed=MOVE_SPEED_M_S * 1e3), end="", file=sys.stderr, flush=True)
    try:
        answer = sys.stdin.readline().strip().lower()
    except (EOFError, KeyboardInterrupt):
        answer = ""
    return answer in ("y", "yes")


def cmd_commission(args) -> int:
    """Through the daemon when one is named or owns the cell's store; else here, on the cell file's devices."""
    if daemon_url(args):
        return invoke(COMMISSION, args)
    if not args.config:
        raise InputError("commission needs --config FILE (the cell to test in this process), or --url URL / "
                         "$CELLCTL_URL (its daemon)")
    from pathlib import Path

    from cellctl.config import load_cell_file
    from cellctl.startup.ownership import CellOwned, own_cell

    config, text = load_cell_file(args.config)
    store_path = Path(args.store) if args.store else config.store_path()
    try:
        with own_cell(config, store_path, "cellctl commission"):
            return here(args, config, text, store_path)
    except CellOwned as owned:  # nothing was touched: the owner's daemon runs the self-test
        from cellctl.cli.verbs import owner_daemon

        url, token, ca = owner_daemon(args, owned, "running the self-test there")
        return invoke(COMMISSION, argparse.Namespace(**{**vars(args), "url": url, "token": token, "ca": ca}))


def here(args, config, text, store_path) -> int:
    """The self-test in this process, on the cell this process owns: its devices connected one by one (one that
    does not connect is a finding), audited in the store's audit log."""
    from cellctl.core.cell import Cell
    from cellctl.service import Caller
    from cellctl.service.commission import check_device
    from cellctl.service.local import LocalService
    from cellctl.stores.calibrations import CalibrationStore

    store = CalibrationStore(store_path, replicate=config.fleet is not None)
    service = LocalService.of_store(config, store, text)
    caller = Caller(client_name(), None, "cli commission (in-process)", credential="local")
    cell = None
    try:
        cell = Cell(config, text)
        check_device(cell, config, args.device)  # before anything connects or asks: an unknown device is an error
        errors = connect(cell, args.device)
        answer = service.commission_here(caller, cell, args.device, confirmed(args), errors)
    finally:
        if cell is not None:
            cell.close()
        service.close()
    if args.json:
        print(json.dumps(answer, indent=2))
    else:
        from cellctl.cli.display import print_checks

        print_checks(answer)
    return EXIT_FAULT if answer["problems"] else EXIT_OK


def connect(cell, device: str | None) -> dict[str, str]:
    """Connect what the self-test of `device` (None: every device) uses, each on its own: the device, and for the
    arm's move the arm and the cameras that watch it (a gripper alone: itself). A simulated cell's protocol
    simulators start first. Returns why each that did not connect did not (its link check says so)."""
    from drivers.interfaces import DeviceError

    errors: dict[str, str] = {}
    try:
        cell.start_sim_servers()
    except DeviceError as exc:  # its devices then say they cannot connect, each by name
        errors["sim.servers"] = str(exc)
    kinds = {name: kind for kind, name, _ in cell.named_devices()}
    wanted = {device} if device is not None else set(kinds)
    if device is not None and kinds[device] in ("arm", "camera"):
        wanted |= {n for n, k in kinds.items() if k in ("arm", "camera")} if kinds[device] == "arm" else {"arm"}
    for kind, name, dev in cell.named_devices():
        if name not in wanted or kind == "operator":
            continue
        try:
            dev.connect()
        except Exception as exc:  # noqa: BLE001 - any failure is the device's finding
            errors[name] = f"{type(exc).__name__}: {exc}"
    return errors
