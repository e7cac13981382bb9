"""The public open_abb Python client, unmodified, under Python 2.7, against `cellctl sim abb`.

`abb.py` (github.com/robotics/open_abb, abb_node/packages/abb_communications/abb.py) is not part of
this project and is not copied into it: the test runs it where it lies. It needs

- a Python 2.7 interpreter: `CELLCTL_PYTHON2`, else `python2.7` / `python2` on the PATH, else pyenv's;
- the client: `CELLCTL_OPEN_ABB_CLIENT`, the path of its abb.py, else a clone in
  ~/.cache/cellctl/open_abb (`git clone --depth 1 https://github.com/robotics/open_abb ~/.cache/cellctl/open_abb`).

and is skipped, saying which is missing, without them. It drives the simulator as the public client
does (one send, an 80 ms sleep, one recv per request) through the codes of the public SERVER.mod:
connect (tool, work object, speed, zone), ping, a linear move, the pose, the joints, the external axes
(5), a circular move (35 + 36, and one whose circle point is refused: `move_circular` returns False),
the external axis move (34: its `set_external_axis` cannot send it, so through its `send`), the buffer,
robot info, close.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.support.abb import sim_abb_by_hand


def _python2() -> str | None:
    candidates = [os.environ.get("CELLCTL_PYTHON2"), shutil.which("python2.7"), shutil.which("python2"),
                  *sorted(glob.glob(os.path.expanduser("~/.pyenv/versions/2.7*/bin/python2.7")))]
    for candidate in filter(None, candidates):
        try:
            done = subprocess.run([candidate, "-c", "import sys; print(sys.version_info[0])"], capture_output=True,
                                  text=True, timeout=20)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if done.returncode == 0 and done.stdout.strip() == "2":
            return candidate
    return None


CLONE = Path.home() / ".cache" / "cellctl" / "open_abb"
CLIENT_IN_REPO = Path("abb_node") / "packages" / "abb_communications" / "abb.py"


def _public_client() -> Path | None:
    path = os.environ.get("CELLCTL_OPEN_ABB_CLIENT")
    for candidate in (Path(path) if path else None, CLONE / CLIENT_IN_REPO):
        if candidate is not None and candidate.is_file():
            return candidate
    return None


SCRIPT = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
import abb

robot = abb.Robot(ip="127.0.0.1", port_motion=int(sys.argv[2]))  # tool, work object, speed, zone
out = {}
out["ping"] = robot.send("00 #")
robot.set_cartesian([[50, 30, 10], [0, 1, 0, 0]])
out["pose"] = robot.get_cartesian()
out["joints"] = robot.get_joints()
out["external"] = robot.get_external_axis()
out["circular"] = robot.move_circular([[60, 40, 10], [0, 1, 0, 0]], [[50, 50, 10], [0, 1, 0, 0]])
out["after_circular"] = robot.get_cartesian()
out["tilted_circle_point"] = robot.move_circular([[60, 40, 10], [-0.04362, 0.99905, 0, 0]], [[50, 30, 10], [0, 1, 0, 0]])
out["external_move"] = robot.send("34 9E9 9E9 9E9 9E9 9E9 9E9 #")
out["external_move_refused"] = robot.send("34 +0100.00 9E9 9E9 9E9 9E9 9E9 #")
out["buffer_set"] = robot.buffer_set([[[55, 35, 10], [0, 1, 0, 0]], [[45, 35, 10], [0, 1, 0, 0]]])
out["buffer_execute"] = robot.buffer_execute()
out["after_buffer"] = robot.get_cartesian()
out["info"] = robot.get_robotinfo()
robot.close()
print(json.dumps(out))
"""


def test_the_public_open_abb_client_under_python_2_7_drives_cellctl_sim_abb(tmp_path):
    python2 = _python2()
    if python2 is None:
        pytest.skip("no Python 2.7 interpreter (set CELLCTL_PYTHON2, or install one: pyenv install 2.7.18)")
    client = _public_client()
    if client is None:
        pytest.skip(f"the public open_abb client is not here: set CELLCTL_OPEN_ABB_CLIENT to the path of its abb.py, "
                    f"or clone github.com/robotics/open_abb into {CLONE}")
    script = tmp_path / "drive.py"
    script.write_text(SCRIPT)
    with sim_abb_by_hand() as port:
        done = subprocess.run([python2, str(script), str(client.parent), str(port)], capture_output=True, text=True,
                              timeout=60)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["ping"] == "0 1 "
    assert out["pose"][0] == pytest.approx([50, 30, 10], abs=0.051)
    assert out["joints"] == pytest.approx([50, 30, 10, 0, 0, 0], abs=0.051)  # x, y, z (mm), alpha (deg), 0, 0
    assert out["external"] == [9e9] * 6  # the micro cell has no external axes
    assert out["circular"] == "36 1 "
    assert out["after_circular"][0] == pytest.approx([50, 50, 10], abs=0.051)
    assert out["tilted_circle_point"] is False  # 35 refused (a 4-axis arm cannot tilt): the client sends no 36
    assert out["external_move"] == "34 1 " and out["external_move_refused"] == "34 0 "
    assert out["buffer_set"] is True and out["buffer_execute"] == "33 1 "
    assert out["after_buffer"][0] == pytest.approx([45, 35, 10], abs=0.051)
    assert out["info"] == ["SIM-0001", "6.99.0 cellctl-sim", "cellctl 4-axis micro cell"]
