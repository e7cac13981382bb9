"""The ABB driver's tests share: the micro cell's limits, an AbbArm on a simulator, the scripted controller of
the pinned exchanges (a WirePeer), and `cellctl sim abb` started as by hand."""

from __future__ import annotations

import re
import select
import subprocess
import sys
from contextlib import contextmanager

from drivers.arms.abb import AbbArm
from drivers.registry import DriverContext, backend_class
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.servers.abb import AbbServer

from tests.conftest import MICROCELL, ROOT, microcell_data
from tests.support.wire import WirePeer

DATA = microcell_data()
LIMITS = DATA["arm"]["limits"]


def sim_arm(config: SimWorldConfig):
    return backend_class("arm", "sim").create("arm", {"limits": LIMITS}, DriverContext(sim_config=config))


def abb_on(server: AbbServer, **options) -> AbbArm:
    settings = {"host": "127.0.0.1", "motion_port": server.motion_port, "logger_port": server.logger_port,
                "limits": LIMITS, "linear_axes": [1, 2, 3], "reply_timeout_s": 2.0, "move_timeout_s": 10.0}
    return AbbArm.create("abb", {**settings, **options}, None)



# --- pinned exchanges with a scripted controller -------------------------------------------

CONNECT_SCRIPT = [
    (b"00 #", b"0 1 #"),
    (b"06 +0.0000 +0.0000 +0.0000 +1.000000 +0.000000 +0.000000 +0.000000 #", b"6 1 #"),
    (b"07 +0.0000 +0.0000 +0.0000 +1.000000 +0.000000 +0.000000 +0.000000 #", b"7 1 #"),
    (b"08 +100.0000 +50.0000 +50.0000 +50.0000 #", b"8 1 #"),
    (b"09 1 +0.0000 +0.0000 +0.0000 #", b"9 1 #"),
]


class ScriptedController(WirePeer):
    """An ABB controller played from a script: "#"-ended requests, each answered with its scripted reply (chunks
    allowed); a request that differs from the script is recorded and left unanswered."""

    def __init__(self, script):
        super().__init__(script, terminator=b"#", chunk_gap_s=0.005)

    def arm(self, **options) -> AbbArm:
        settings = {"host": "127.0.0.1", "motion_port": self.port, "logger_port": None, "limits": LIMITS,
                    "reply_timeout_s": 1.0, "move_timeout_s": 1.0, **options}
        return AbbArm.create("abb", settings)

@contextmanager
def irb120_on_abb():
    """The IRB 120 cell's six-axis world behind the ABB simulator, an AbbArm connected to it: (world, arm)."""
    from drivers.sim.kinds import build_world
    from drivers.sim.servers.abb import start

    from cellctl.config import load_cell_file

    world = build_world(load_cell_file(ROOT / "config" / "sim-irb120-csm.yaml")[0].sim)
    box = {"x_mm": (-1000, 1000), "y_mm": (-1000, 1000), "z_mm": (-1000, 1000), "alpha_deg": (-360, 360)}
    server = start(world, port=0, logger_port=0)
    try:
        arm = AbbArm.create("abb", {"host": "127.0.0.1", "motion_port": server.motion_port, "logger_port": None,
                                    "limits": box, "move_timeout_s": 30.0})
        arm.connect()
        try:
            yield world, arm
        finally:
            arm.close()
    finally:
        server.close()


def readline_within(stream, timeout_s: float) -> str:
    """One line of a child's output, or '' after `timeout_s` (never blocks the test for good)."""
    ready, _, _ = select.select([stream], [], [], timeout_s)
    return stream.readline() if ready else ""



def same_rotation(q, expected, tol: float) -> bool:
    return max(abs(a - b) for a, b in zip(q, expected)) < tol or max(abs(a + b) for a, b in zip(q, expected)) < tol



@contextmanager
def sim_abb_by_hand():
    """`cellctl sim abb` started as by hand, on a free port: yields that port; it must stop cleanly after."""
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "sim", "abb", "--config", str(MICROCELL),
                             "--port", "0"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        banner = readline_within(proc.stdout, 30.0)
        found = re.search(r"serving on 127\.0\.0\.1:(\d+) \(logger \d+\), open_abb replies", banner)
        assert found, f"no banner from cellctl sim abb: {banner!r}"
        yield int(found[1])
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0


def server_reply(server: AbbServer, fields: str) -> bytes:
    """What `server` sends for a reply of these fields, in its dialect."""
    return (fields + (" #" if server.reply_dialect == "cellctl" else " ")).encode()
