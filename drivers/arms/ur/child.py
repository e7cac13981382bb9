"""The child process that holds the ur_rtde objects of one UrArm connection.

Why: ur_rtde 1.6.5 can take its process down — a malformed RTDE frame makes its receive
thread throw an uncaught std::length_error (SIGABRT), and destroying its interfaces while
it reconnects in the background segfaults. So `UrArm` (drivers/arms/ur/arm.py) starts this
module as `python -m drivers.arms.ur.child` for every connect() and talks to the
in-process driver `UrRtdeArm` here through drivers/rpc.py; a crash here is the parent's
ConnectionLost, never its death.

Protocol:
- the parent passes the authkey (hex) in $CELLCTL_UR_AUTHKEY and the arm's name and
  settings (JSON) as one line on stdin;
- the child serves `UrRtdeArm`'s calls on 127.0.0.1 (one thread per connection: the
  parent's stop() has its own connection, so it is served while a move runs), prints
  `ready HOST PORT` on stdout, then points its stdout at stderr (ur_rtde prints there);
- the child ends when stdin reaches EOF (the parent closed it, or died) or on SIGTERM.
  It ends with os._exit: ur_rtde's destructors never run (they can segfault).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading

from drivers.arms.ur.rtde_driver import UrArmSettings, UrRtdeArm
from drivers.rpc import ObjectHost

AUTHKEY_ENV = "CELLCTL_UR_AUTHKEY"
CALLS = {"connect", "close", "stop", "speed_stop", "move_linear", "move_joints", "pose", "joints", "set_tcp",
         "robot_mode", "safety_mode", "trigger_protective_stop", "unlock_protective_stop", "state"}


class UrHost(ObjectHost):
    """Every reply carries the driver's state after the call (the parent mirrors it)."""

    def call(self, request):
        return (*super().call(request), self.target.state.value)

    def dispatch(self, name: str, args: tuple):
        if name == "state":
            return None
        return getattr(self.target, name)(*args)


def main() -> None:
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="ur_process %(levelname)s %(message)s")
    setup = json.loads(sys.stdin.buffer.readline())
    arm = UrRtdeArm(setup["name"], UrArmSettings(**setup["settings"]))
    host = UrHost(arm, CALLS, authkey=bytes.fromhex(os.environ.pop(AUTHKEY_ENV)), name=f"{setup['name']}-ur")
    sys.stdout.write(f"ready {host.address[0]} {host.address[1]}\n")
    sys.stdout.flush()
    os.dup2(2, 1)  # nobody reads our stdout any more: a full pipe would block ur_rtde's prints
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.buffer.read(), done.set()), daemon=True).start()
    try:
        done.wait()
    except KeyboardInterrupt:
        pass
    sys.stderr.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
