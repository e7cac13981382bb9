"""`cellctl jog`, `cellctl move-to`, `cellctl grip`, `cellctl release`: the arm and the vacuum by hand, through the
daemon's manual-motion verbs (cellctl/service/manual.py), with the same checks as the console's jog panel.

Manual motion is for the holder of the operator lock: with $CELLCTL_LOCK set, this client's lock is used; without
it, the lock is taken for the one command (if nobody holds it) and given back after. While the arm moves this
command sends the dead-man heartbeat; Ctrl-C stops the arm, and so does this command dying (no more heartbeats).
"""

from __future__ import annotations

import argparse
import time
from contextlib import contextmanager
from dataclasses import replace

from cellctl.service import Caller, CellService

HEARTBEAT_S = 0.05  # well inside the daemon's heartbeat time-out (manual.heartbeat_timeout_s, 0.15 s by default)
EXIT_OK, EXIT_STOPPED, EXIT_INTERRUPTED = 0, 1, 130


@contextmanager
def holding_lock(s: CellService, caller: Caller):
    """The caller with a lock: its own ($CELLCTL_LOCK), else one taken now and released after."""
    if caller.lock is not None:
        yield caller
        return
    got = s.acquire_lock(caller, caller.who, 60.0)
    with_lock = replace(caller, lock=got["lock_id"])
    try:
        yield with_lock
    finally:
        s.release_lock(with_lock)


def follow(s: CellService, caller: Caller, motion: dict) -> int:
    """Heartbeat the move to its end; Ctrl-C stops it. Prints where the arm stands."""
    try:
        while motion["state"] == "moving":
            time.sleep(HEARTBEAT_S)
            motion = s.manual_alive(caller, motion["motion"])
    except KeyboardInterrupt:
        motion = s.manual_stop(caller, motion["motion"])
        print(f"stopped (Ctrl-C): {motion['what']}, moved {motion['moved_mm']:.3f} mm")
        return EXIT_INTERRUPTED
    p = motion["pose"]
    print(f"{motion['what']}: {motion['state']} ({motion['reason']}); moved {motion['moved_mm']:.3f} mm, now "
          f"x={p['x_mm']:.3f} y={p['y_mm']:.3f} z={p['z_mm']:.3f} mm alpha={p['alpha_deg']:.3f} deg")
    return EXIT_OK if motion["state"] == "done" else EXIT_STOPPED


def jog(s: CellService, caller: Caller, args) -> int:
    with holding_lock(s, caller) as c:
        return follow(s, c, s.jog(c, args.axis, args.distance, frame=args.frame, speed_pct=args.speed))


def move_to(s: CellService, caller: Caller, args) -> int:
    if args.position is not None and args.xyz:
        raise SystemExit("cellctl move-to: give X Y Z or --position NAME, not both")
    pose = None
    if args.position is None:
        if len(args.xyz or ()) != 3:
            raise SystemExit("cellctl move-to: give X Y Z (mm) or --position NAME")
        pose = {"x_mm": args.xyz[0], "y_mm": args.xyz[1], "z_mm": args.xyz[2], "alpha_deg": args.alpha}
        if args.quaternion is not None:
            pose["quaternion_wxyz"] = args.quaternion
    with holding_lock(s, caller) as c:
        return follow(s, c, s.move_to(c, pose, args.position, args.speed))


def vacuum(on: bool):
    def command(s: CellService, caller: Caller, args) -> int:
        with holding_lock(s, caller) as c:
            got = s.vacuum(c, on)
        print(f"vacuum {got['vacuum']}: {got['vacuum_kpa']:.1f} kPa, object "
              f"{'detected' if got['object_detected'] else 'not detected'}")
        return EXIT_OK
    return command


def speed_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--speed", type=float, metavar="PCT", help="%% of the arm's speed (default and most: the cell "
                                                              "file's manual.speed_pct, 10 %% unless set)")


def jog_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("axis", choices=["x", "y", "z", "rx", "ry", "rz"], help="x, y, z (mm) or rx, ry, rz (deg)")
    p.add_argument("distance", type=float, help="the step, signed (mm or deg; at most manual.max_step_mm / _deg)")
    p.add_argument("--frame", choices=["cell", "tool"], default="cell", help="the axis of the cell (default) or "
                                                                             "of the tool")
    speed_option(p)


def move_to_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("xyz", nargs="*", type=float, metavar="X Y Z", help="the target in mm, in the cell frame")
    p.add_argument("--alpha", type=float, default=0.0, help="the tool's turn about the vertical, deg")
    p.add_argument("--quaternion", type=float, nargs=4, metavar=("W", "X", "Y", "Z"),
                   help="six-axis arms: the tool's orientation instead of --alpha")
    p.add_argument("--position", help="a named position of the cell file (manual.positions)")
    speed_option(p)
