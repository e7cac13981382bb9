"""The hand-eye cell's UR5e through the real UR driver: ur-rtde against the UR protocol simulator on loopback
(config/sim-ur5e-handeye-ur.yaml), which moves the very UR5e the simulated cameras render.

The simulator's controller speaks for a six-axis arm there (drivers/sim/servers/ur/six_axis.py): moveJ goes to the
joints given, moveL to the joints its nominal kinematics find on the arm's branch, actual_q is the arm's encoders and
actual_TCP_pose their nominal forward kinematics. The in-process fake (config/sim-ur5e-handeye.yaml, SimUr5eArm)
computes the same with the same functions (geometry/ur_controller.py), its pose carried as a controller sends it, so
the same seed gives the same samples to the last bit, hence the same X, Y and truth figures. A joint target outside
the limits is refused with the joint named, and nothing moves.

Each test's cell runs its simulator on an address of this module's own (UR ports are fixed); cells that share one
(two runs of the same cell file) take turns.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from drivers.interfaces import DeviceState, JointState, MotionRejected, MotionStopped
from drivers.sim.servers.ur.server import AddressClaim, PortsTaken

from calibration.routines.six_axis.hand_eye import HandEye

from cellctl.config import load_cell_file
from cellctl.core import report
from cellctl.core.cell import Cell
from cellctl.core.runs import run_routine, with_seed
from cellctl.stores.run_folder import RunFolder

from tests.conftest import ROOT

pytestmark = pytest.mark.long  # run first: see conftest.py

pytest.importorskip("rtde_control")

FAKE_CELL = ROOT / "config" / "sim-ur5e-handeye.yaml"
UR_CELL = ROOT / "config" / "sim-ur5e-handeye-ur.yaml"
HOSTS = {"routine": "127.0.0.32", "driver-limits": "127.0.0.33", "controller-limits": "127.0.0.34",
         "turns": "127.0.0.35"}
SEED = 3
POSE = ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")
TRUTH = ("hand_eye_translation_error_mm", "hand_eye_rotation_error_deg", "world_translation_error_mm",
         "world_rotation_error_deg", "touch_mean_mm", "touch_max_mm")


def ur_cell_file(folder, host: str, **arm) -> tuple:
    """(config, text) of sim-ur5e-handeye-ur.yaml with its simulator and arm on `host`, and `arm` options added."""
    path = folder / f"handeye-ur-{host}.yaml"
    path.write_text(yaml.safe_dump({"extends": str(UR_CELL), "arm": {"host": host, **arm},
                                    "sim": {"servers": [{"protocol": "ur", "host": host}]}}))
    return load_cell_file(path)


@pytest.fixture
def no_plots(monkeypatch):
    """The report's plots are no part of what is compared (result.json and samples.csv are)."""
    monkeypatch.setattr(report, "plot_residuals", lambda *args: None)
    monkeypatch.setattr(report, "plot_chart", lambda *args: None)


def test_hand_eye_through_ur_rtde_gives_the_in_process_samples_and_figures(tmp_path, no_plots):
    params = dict(HandEye.small_params)
    config, text = load_cell_file(FAKE_CELL)
    assert config.arm.backend == "sim-ur5e"
    fake = run_routine("hand-eye", config, text, tmp_path / "fake", seed=SEED, overrides=params)

    config, text = ur_cell_file(tmp_path, HOSTS["routine"])
    config = with_seed(config, SEED)
    with Cell(config, text) as cell:  # the run borrows this cell: it is seen to be the real driver on the simulator
        assert type(cell.arm).__name__ == "UrArm" and cell.arm.settings.host == HOSTS["routine"]
        simulator = cell.sim_servers[0]
        real = run_routine("hand-eye", config, text, tmp_path / "ur", seed=SEED, overrides=params, cell=cell)
        assert simulator.process.said("moveJ to") and simulator.process.said("moveL to")  # poses and touches

    # the same samples, every column to the last bit: joints, the flange's pose, corners, the cell time
    fake_rows, real_rows = RunFolder(tmp_path / "fake").samples(), RunFolder(tmp_path / "ur").samples()
    assert len(real_rows) == len(fake_rows) == real["n_samples"] == fake["n_samples"]
    assert any(r["set"] == "touch" and r["status"] == "ok" for r in real_rows)  # moveL went through too
    for a, b in zip(fake_rows, real_rows):
        differ = {k: (a[k], b.get(k)) for k in a if a[k] != b.get(k) and not (a[k] != a[k] and b.get(k) != b.get(k))}
        assert not differ, f"step {a['step']}: the protocol's sample differs from the fake's: {differ}"

    # hence the same X (flange -> camera), Y (base -> board) and truth figures
    for transform in ("hand_eye", "world"):
        for key in POSE:
            assert real["model"][transform][key] == pytest.approx(fake["model"][transform][key], abs=1e-6), \
                (transform, key)
    for key in TRUTH:
        assert real["truth"][key] == pytest.approx(fake["truth"][key], abs=1e-6), key
    assert real["truth"]["hand_eye_translation_error_mm"] < 0.4  # and a good calibration, not two equal bad ones
    assert real["cell_time_s"] == pytest.approx(fake["cell_time_s"], abs=1e-9)


def test_a_joint_target_outside_the_limits_is_refused_with_the_joint_named_and_nothing_moves(tmp_path):
    """The driver knows the UR5e's limits (joint_limits_rad, +-360 deg as the simulated UR5e's): the target is
    refused before anything is sent; the arm stays READY and moves on the next good target."""
    config, text = ur_cell_file(tmp_path, HOSTS["driver-limits"])
    with Cell(config, text) as cell:
        arm, world = cell.arm, cell.sim_world
        before, pose, moves = arm.joints().positions, arm.pose(), len(world.moves)
        with pytest.raises(MotionRejected, match=r"joint wrist3=7\.0000 is outside its limits \[-6\.28\d*, "
                                                 r"6\.28\d*\] rad; nothing moved"):
            arm.move_joints(JointState((*before[:5], 7.0)))
        assert arm.joints().positions == before and arm.pose() == pose and len(world.moves) == moves
        assert arm.state is DeviceState.READY
        good = (*before[:5], before[5] + 0.1)
        arm.move_joints(JointState(good))
        assert arm.joints().positions == pytest.approx(good, abs=1e-5) and len(world.moves) == moves + 1


def test_the_simulated_controller_refuses_a_joint_target_outside_its_limits_and_nothing_moves(tmp_path):
    """A driver set up with wider limits than the robot's (a wrong cell file) sends the target: the controller
    stops its control script with a script error naming the joint, before the arm moves; the driver says the move
    was refused and nothing moved, and connect() brings the arm back."""
    config, text = ur_cell_file(tmp_path, HOSTS["controller-limits"], joint_limits_rad=[[-10.0, 10.0]] * 6)
    with Cell(config, text) as cell:
        arm, world, simulator = cell.arm, cell.sim_world, cell.sim_servers[0]
        before, moves = arm.joints().positions, len(world.moves)
        # ur_rtde sees the stopped script, or our driver the refusal first (timing): both name the control script
        with pytest.raises(MotionStopped, match=r"refused the move.*control script.*nothing moved"):
            arm.move_joints(JointState((*before[:5], 7.0)))
        assert simulator.process.said("script error: moveJ: joint wrist3=7.0000 rad is outside its limits")
        assert arm.state is DeviceState.FAULTED
        arm.connect()  # uploads the control script again
        assert arm.joints().positions == before and len(world.moves) == moves
        good = (*before[:5], before[5] - 0.1)
        arm.move_joints(JointState(good))
        assert arm.joints().positions == pytest.approx(good, abs=1e-5) and len(world.moves) == moves + 1


def test_two_cells_on_one_simulated_address_take_turns():
    """UR ports are fixed: a second cell's simulator on an address another cell's holds waits for it (up to its
    wait), then says who holds it; within one process a second claim fails at once."""
    host = HOSTS["turns"]
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys; from drivers.sim.servers.ur.server import AddressClaim\n"
        f"claim = AddressClaim({host!r}, 5.0).acquire(); print('held', flush=True); sys.stdin.read(); claim.release()")],
        cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(PortsTaken, match=rf"another cell has run a UR simulator on {host} .*another loopback"):
            AddressClaim(host, 0.2).acquire()
        holder.stdin.close()  # the other cell closes
        assert holder.wait(30) == 0
        claim = AddressClaim(host, 30.0).acquire()
        try:
            with pytest.raises(PortsTaken, match=f"this process already runs a UR simulator on {host}"):
                AddressClaim(host, 30.0).acquire()
        finally:
            claim.release()
        AddressClaim(host, 0.0).acquire().release()  # free again
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
        holder.stdout.close()
        if not holder.stdin.closed:
            holder.stdin.close()
