"""The IRB 120 cell of seed 002 through the real ABB driver: AbbArm over loopback against the ABB protocol
simulator serving the six-axis world (config/sim-irb120-abb.yaml).

- csm-positioning through AbbArm gives the in-process fake's figures for the same seed;
- the Arm contract and the six-axis conventions of the simulated controller (six joints in degrees, tool0 at
  the IRB 120's flange, tool and work object frames, full orientation), each checked against the fake.

Why the figures are close but not bit-equal: MoveAbsJ carries each joint with 4 decimals of a degree, so the
wire rounds a commanded joint by up to 5e-5 deg (0.9 urad); over the IRB 120's reach (< 0.6 m) that puts the
fixture up to ~0.5 um per joint elsewhere than the fake puts it. The cameras (about 2000 px per m at 1.2 m)
see that as a few thousandths of a pixel, and the estimates, the loops' next joints and the errors move by
about a micrometre. Measured (seed 5, SMALL): marks <= 0.005 px apart, predicted targets <= 0.9 um, loop
joints <= 2e-4 deg, figures <= 1.2 um (the 5-target leave-one-out error is the most sensitive); the planned
poses' reported joints are equal (encoder counts of 1e-4 deg, which the wire carries exactly). So: mm
figures within 3 um (ten times below the loop's 0.03 mm tolerance), px figures within 0.002 px, counts
equal. Poses read over the wire: 1e-4 mm and 1e-6 per quaternion component.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz, tool_down

from drivers.arms.abb import AbbArm
from drivers.interfaces import JointState, MotionRejected, Pose
from drivers.sim.irb120_csm.devices import SimSixAxisArm
from drivers.sim.kinds import build_world
from drivers.sim.servers import abb as abb_sim
from drivers.sim.servers import sim_device

from cellctl.config import CellFileError, load_cell_file, parse_cell_file
from cellctl.core.runs import run_routine
from cellctl.stores.run_folder import read_samples_text

from tests.conftest import ROOT
from tests.support.contract import ArmContract
from tests.support.wait import eventually

FAKE_CELL = ROOT / "config" / "sim-irb120-csm.yaml"
ABB_CELL = ROOT / "config" / "sim-irb120-abb.yaml"
SMALL = {"n_targets": 5, "loops": ["three:w4", "white:w4"], "k_values": [1, 3]}
MM, PX, DEG = 3e-3, 2e-3, 1.5e-4  # see the module docstring


@pytest.fixture(autouse=True)
def _threads_end_with_each_test(no_leftover_threads):
    """Servers, drivers and their logger threads all end with the test."""


# --- the routine, fake against ABB ------------------------------------------------------------------


def _run(cell_file, out):
    config, text = load_cell_file(cell_file)
    return run_routine("csm-positioning", config, text, out, seed=5, overrides=SMALL)


def _stats(result) -> dict[str, float]:
    s, t = result["stats"], result["truth"]
    flat = {f"positioning.{k}": s["positioning"][k] for k in ("mean_mm", "max_mm")}
    flat.update({f"loo_3d.{k}": s["loo_3d"][k] for k in ("mean_mm", "max_mm")})
    flat.update({f"physical.{k}": t["positioning_physical"][k] for k in ("mean_mm", "max_mm")})
    return flat


def test_csm_positioning_through_abb_gives_the_fakes_figures(irb120_abb_cell_file, tmp_path, monkeypatch):
    moves_on_the_wire = []
    real_move_joints = abb_sim.AbbServer._move_joints

    def counted(server, p):
        moves_on_the_wire.append(p)
        return real_move_joints(server, p)

    monkeypatch.setattr(abb_sim.AbbServer, "_move_joints", counted)
    fake = _run(FAKE_CELL, tmp_path / "fake")
    assert moves_on_the_wire == []
    real = _run(irb120_abb_cell_file, tmp_path / "abb")

    assert len(moves_on_the_wire) > 20  # the moves went over the wire as MoveAbsJ
    assert real["n_samples"] == fake["n_samples"]
    assert real["stats"]["iterations"] == fake["stats"]["iterations"]
    assert real["stats"]["positioning"]["n"] == fake["stats"]["positioning"]["n"] == 5
    assert _stats(real) == pytest.approx(_stats(fake), abs=MM)
    for cam, fit in fake["stats"]["camera_fit"].items():
        assert real["stats"]["camera_fit"][cam] == pytest.approx(fit, abs=PX)
    assert real["stats"]["positioning"]["mean_mm"] <= 0.1 and real["truth"]["positioning_physical"]["mean_mm"] <= 0.1

    # sample by sample: the same steps and outcomes; planned poses to one encoder count, the loops' poses
    # (from estimates a micrometre apart) to a few; marks to hundredths of a pixel
    rows = [read_samples_text((tmp_path / tag / "samples.csv").read_text()) for tag in ("fake", "abb")]
    for a, b in zip(*rows, strict=True):
        assert (a["step"], a["status"], a["camera"], a["feature"]) == (b["step"], b["status"], b["camera"], b["feature"])
        if a["status"] == "ok":
            joints = [f"j{i}_deg" for i in range(1, 7)]
            tol = DEG if a["phase"] in ("survey", "approach") else 10 * DEG
            assert [b[j] for j in joints] == pytest.approx([a[j] for j in joints], abs=tol)
            assert (b["u_px"], b["v_px"]) == pytest.approx((a["u_px"], a["v_px"]), abs=0.02)


# --- the six-axis simulated controller -----------------------------------------------------------------


def _cell_options():
    """(the ABB arm's options, the six-axis sim section) of sim-irb120-abb.yaml."""
    config, _ = load_cell_file(ABB_CELL)
    return config.arm.options, config.sim


@pytest.fixture
def six_axis():
    """(server, world) on a fresh IRB 120 world, on free ports."""
    options, sim = _cell_options()
    world = build_world(sim)
    server = abb_sim.start(world, "127.0.0.1", 0, logger_port=0, limits=options["limits"])
    try:
        yield server, world
    finally:
        server.close()


def _abb(server, **changes) -> AbbArm:
    options, _ = _cell_options()
    return AbbArm.create("abb", {**options, "motion_port": server.motion_port, "logger_port": server.logger_port,
                                 **changes})


@pytest.fixture
def arm(six_axis):
    device = _abb(six_axis[0])
    device.connect()
    yield device
    device.close()


def _angle(q1, q2) -> float:
    """Angle (rad) between two orientations given as quaternions w, x, y, z (q and -q are the same)."""
    r1, r2 = (Rotation.from_quat(np.roll(q, -1)) for q in (q1, q2))
    return float((r1.inv() * r2).magnitude())


def _fake(world) -> SimSixAxisArm:
    """The world's in-process fake: what the ABB controller must agree with."""
    return sim_device("arm", world, {"limits": _cell_options()[0]["limits"]})


class TestAbbOnTheSixAxisSimulator(ArmContract):
    reachable = Pose(0.35, 0.0, 0.25, 0.0)  # the fixture frame, tool down

    @pytest.fixture
    def make_device(self, six_axis):
        return lambda: _abb(six_axis[0])


def test_the_server_drives_the_worlds_own_six_axis_arm(six_axis, arm):
    server, world = six_axis
    assert isinstance(server.arm, SimSixAxisArm) and server.arm.world is world
    assert arm.robot_info().robot_type == "IRB 120-3/0.6"


def test_six_joints_in_degrees_and_the_fakes_pose(six_axis, arm):
    _, world = six_axis
    q = np.radians([5.0, 15.0, 5.0, 10.0, 70.0, -20.0])
    arm.move_joints(JointState(tuple(q)))
    assert arm.joints().positions == pytest.approx(tuple(q), abs=math.radians(1e-4))
    assert world.joints == pytest.approx(q, abs=1e-12)  # 4 decimals of a degree carry these exactly
    fake = _fake(world).pose()
    pose = arm.pose()  # the tool of the cell file is the fixture: the fake's frame
    assert pose.xyz == pytest.approx(fake.xyz, abs=1e-7)
    assert _angle(pose.orientation, fake.orientation) < 3e-6  # 6 decimals per component


def test_tool0_is_the_irb120_flange(arm):
    arm.set_tool((0, 0, 0, 1, 0, 0, 0))
    arm.move_joints(JointState((0.0,) * 6))
    pose = arm.pose()  # the IRB 120 at zero joints: tool0 at (374, 0, 630) mm pointing along +x
    assert pose.xyz == pytest.approx((0.374, 0.0, 0.630), abs=1e-7)
    assert pose.orientation == pytest.approx((math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0), abs=1e-6)  # as sent: w >= 0
    arm.set_tool((0, 0, 40, 1, 0, 0, 0))
    assert arm.pose().xyz == pytest.approx((0.414, 0.0, 0.630), abs=1e-7)  # the fixture, 40 mm along tool0's z


def test_full_orientation_and_the_work_object(six_axis, arm):
    _, world = six_axis
    fake = _fake(world)
    tilted = tool_down(math.radians(20)) * Rotation.from_euler("xy", [8, -5], degrees=True)
    target = Pose(0.40, 0.05, 0.22, orientation=quaternion_wxyz(tilted))
    arm.move_linear(target)
    pose = arm.pose()
    # the wire gives the fake's pose; both are the nominal kinematics of joints read to 1e-4 deg (encoder
    # counts), so they meet the target to about a micrometre
    assert pose.xyz == pytest.approx(fake.pose().xyz, abs=1e-7)
    assert _angle(pose.orientation, fake.pose().orientation) < 3e-6
    assert pose.xyz == pytest.approx(target.xyz, abs=2e-6)
    assert _angle(pose.orientation, target.orientation) < 1e-5
    # a work object 100 mm along x, turned 90 deg about z: the same TCP, seen from there
    turn = Rotation.from_euler("z", 90, degrees=True)
    arm.set_workobject((100, 0, 0, *quaternion_wxyz(turn)))
    in_wobj = arm.pose()
    assert in_wobj.xyz == pytest.approx(turn.inv().apply(pose.xyz - [0.1, 0, 0]), abs=1e-7)
    assert _angle(quaternion_wxyz(turn * Rotation.from_quat(np.roll(in_wobj.orientation, -1))), pose.orientation) < 3e-6
    arm.move_linear(Pose(0.05, -0.25, 0.22, orientation=in_wobj.orientation))  # 5 cm back along the base's x
    assert fake.pose().xyz == pytest.approx((0.35, 0.05, 0.22), abs=2e-6)


def test_refusals_leave_the_arm_where_it_was(six_axis):
    server, world = six_axis
    arm = _abb(server, joint_limits=None)  # nothing checked on the PC: the controller refuses
    arm.connect()
    try:
        before = world.joints.copy()
        with pytest.raises(MotionRejected, match="refused"):
            arm.move_joints(JointState(tuple(np.radians([0, 0, 80, 0, 0, 0]))))  # J3 stops at +70 deg
        with pytest.raises(MotionRejected, match="refused"):
            arm.move_linear(Pose(0.68, 0.0, 0.05))  # inside the box, out of the IRB 120's reach
        assert world.joints == pytest.approx(before, abs=0)
    finally:
        arm.close()
    checked = _abb(server)  # the cell file's joint limits: refused before any byte is sent
    checked.connect()
    try:
        with pytest.raises(MotionRejected, match="axis 3 target 80.0000 is outside joint_limits"):
            checked.move_joints(JointState(tuple(np.radians([0, 0, 80, 0, 0, 0]))))
    finally:
        checked.close()


def test_logger_streams_the_six_joints(arm):
    q = (10.0, -5.0, 20.0, 30.0, 60.0, 45.0)
    arm.move_joints(JointState(tuple(np.radians(q))))
    joints = eventually(lambda: (logged := arm.logged()[1]) and logged.values[0] == 10.0 and logged, timeout=3.0,
                        every=0.01, what="the logged joints at the target")
    assert joints.values == pytest.approx(q, abs=1e-4)


def test_the_six_axis_cell_serves_abb_only():
    config, _ = load_cell_file(ABB_CELL)
    assert [s.protocol for s in config.sim.servers] == ["abb"] and config.arm.backend == "abb"
    assert load_cell_file(FAKE_CELL)[0].sim.servers == []
    with pytest.raises(CellFileError, match="'vgc10' has nothing to serve in the IRB 120 cell.*allowed: abb"):
        parse_cell_file(FAKE_CELL.read_text() + "  servers:\n    - {protocol: vgc10, port: 0}\n")
