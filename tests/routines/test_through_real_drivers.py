"""The calibration routines through the real drivers and real sockets.

The cell files sim-microcell-abb.yaml and sim-microcell-ur.yaml replace the in-process fakes of
the arm and the gripper by the ABB socket driver + OnRobot VGC10 (Modbus TCP), and by ur-rtde +
Robotiq EPick (RTU over TCP); their protocol simulators run on loopback on the same simulated
world the cameras render. Same seed, same samples: the figures must be those of the fake cell,
up to the ABB wire's resolution (positions travel with 4 decimals of a mm).
"""

from __future__ import annotations

import socket

import pytest

from drivers.interfaces import DeviceError, DeviceState, JointState, MotionStopped, Pose

from cellctl.config import CellFileError, load_cell_file
from cellctl.core.cell import Cell
from cellctl.core.runs import run_routine

from tests.conftest import ROOT

pytestmark = pytest.mark.long  # run first: see conftest.py

SMALL_VG = {"rows": 4, "cols": 4, "n_verify": 10}
# without camera 1's centring check (it needs a calibrated cam1; it adds only moves and captures here)
SMALL_AREA2 = {"rows": 3, "cols": 3, "n_verify": 3, "centring_area": None}




def _run(cell_file, routine, params, tmp_path, tag):
    config, text = load_cell_file(cell_file)
    return run_routine(routine, config, text, tmp_path / tag, seed=2, overrides=params)


def _figures(result):
    s = result["stats"]
    return [s["calibration"]["mean_um"], s["calibration"]["max_um"], s["verification"]["mean_um"],
            s["verification"]["max_um"], result["truth"]["mapping_mean_um"]]


@pytest.mark.parametrize("routine,params", [("virtual-grid", SMALL_VG), ("virtual-grid-area2", SMALL_AREA2)])
def test_abb_and_vgc10_give_the_fake_cells_figures(abb_cell_file, tmp_path, routine, params):
    fake = _run(ROOT / "config" / "sim-microcell.yaml", routine, params, tmp_path, "fake")
    real = _run(abb_cell_file, routine, params, tmp_path, "abb")
    assert real["n_samples"] == fake["n_samples"]
    # the wire rounds commanded and reported positions to 0.1 µm: each by up to 0.05 µm per axis
    assert _figures(real) == pytest.approx(_figures(fake), abs=0.1)
    assert real["truth"]["mapping_mean_um"] < 5.0


@pytest.mark.parametrize("routine,params", [("virtual-grid", SMALL_VG), ("virtual-grid-area2", SMALL_AREA2)])
def test_ur_and_epick_give_the_fake_cells_figures(tmp_path, routine, params):
    fake = _run(ROOT / "config" / "sim-microcell.yaml", routine, params, tmp_path, "fake")
    real = _run(ROOT / "config" / "sim-microcell-ur.yaml", routine, params, tmp_path, "ur")
    assert real["n_samples"] == fake["n_samples"]
    assert _figures(real) == pytest.approx(_figures(fake), abs=1e-9)  # RTDE carries doubles: nothing is lost


def test_the_cell_stops_its_simulators_when_it_closes(abb_cell_file):
    config, text = load_cell_file(abb_cell_file)
    port = config.arm.options["motion_port"]
    with Cell(config, text) as cell:
        assert len(cell.sim_servers) == 2
        assert cell.arm.pose() is not None
    assert cell.sim_servers == []
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()


def test_a_simulator_that_cannot_start_leaves_nothing_running(abb_cell_file):
    config, text = load_cell_file(abb_cell_file)
    port = config.arm.options["motion_port"]
    with socket.socket() as taken:
        taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        taken.bind(("127.0.0.1", config.gripper.options["port"]))
        taken.listen()
        cell = Cell(config, text)
        with pytest.raises(DeviceError, match=r"sim.servers\[1\]: the vgc10 simulator on 127.0.0.1:\d+ could not start"):
            cell.connect()
    assert cell.sim_servers == []
    with pytest.raises(OSError):  # the ABB simulator started first was closed again
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()


def test_extends_merges_mappings_and_names_what_is_wrong(tmp_path):
    config, text = load_cell_file(ROOT / "config" / "sim-microcell-abb.yaml")
    assert config.arm.backend == "abb" and config.arm.options["limits"]["x_mm"] == [-10, 160]  # kept from the base
    assert "area2" in config.areas_by_name() and "\nextends:" not in text and "sim-microcell-abb" in text
    missing = tmp_path / "missing.yaml"
    missing.write_text("extends: nowhere.yaml\n")
    with pytest.raises(CellFileError, match="nowhere.yaml: cannot read the cell file"):
        load_cell_file(missing)
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.write_text("extends: b.yaml\n")
    b.write_text("extends: a.yaml\n")
    with pytest.raises(CellFileError, match="a cycle"):
        load_cell_file(a)
    bad = tmp_path / "bad.yaml"
    bad.write_text("extends: [1, 2]\n")
    with pytest.raises(CellFileError, match="extends: expected the path of another cell file"):
        load_cell_file(bad)


# -- the hand-eye cell's UR5e through ur-rtde (the same samples as in-process: tests/drivers/test_ur_handeye_loopback.py)
def test_the_ur5e_refuses_a_linear_target_beyond_its_reach_before_it_moves():
    """The arm behind the controller refuses it (beyond its reach): a script error before anything moves, the driver says so, and
    the arm stays where it is, and nothing more moves until connect() uploads the script again (a real UR's
    program stops)."""
    config, text = load_cell_file(ROOT / "config" / "sim-ur5e-handeye-ur.yaml")
    with Cell(config, text) as cell:
        before, moves = cell.arm.joints().positions, len(cell.sim_world.moves)
        # ur_rtde sees the stopped script, or our driver the refusal first (timing): both name the control script
        with pytest.raises(MotionStopped, match=r"refused the move.*nothing moved|stopped its control script"):
            cell.arm.move_linear(Pose(-0.85, 0.0, 0.3, orientation=(0.0, 0.70710678118654757, 0.70710678118654757, 0.0)))
        assert cell.sim_servers[0].process.said("script error: target not reachable")
        assert cell.arm.joints().positions == before and len(cell.sim_world.moves) == moves
        step = JointState((*before[:5], before[5] + 0.1))
        if cell.arm.state is not DeviceState.FAULTED:  # refused once under way: the next move finds the script gone
            with pytest.raises(MotionStopped, match="control script is not running"):
                cell.arm.move_joints(step)
        assert cell.arm.state is DeviceState.FAULTED and len(cell.sim_world.moves) == moves
        cell.arm.connect()
        cell.arm.move_joints(step)
        assert cell.arm.joints().positions[5] == pytest.approx(before[5] + 0.1, abs=1e-5)
