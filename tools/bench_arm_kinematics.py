"""How long the arm's kinematic fit takes at 30, 100 and 300 poses (issue 28), on corners of the simulated
uncalibrated UR5e cell projected through its true cameras (no rendering: this times the fit alone).

    .venv/bin/python tools/bench_arm_kinematics.py [--poses 30 100 300] [--seed 0]

Prints, per size: the hand-eye start (nominal arm), the arm's adjustment (observability, fit, covariance), and the
usual chain's arm fit, in wall-clock seconds on this machine, with the resulting position error over the working
volume (truth) as a sanity check. Speed is measured here, never asserted in tests.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from geometry.charuco import BoardDrawing
from geometry.kinematic_table import nominal_table
from geometry.transforms import inverse

from drivers.sim.kinds import build_world

from calibration.models import arm_kinematics as ak
from calibration.models import hand_eye as he
from calibration.routines.six_axis import _arm_poses as poses_
from calibration.routines.six_axis.arm_kinematics import ArmKinematics
from calibration.routines.six_axis.hand_eye import first_intrinsics

from cellctl.config import load_cell_file
from cellctl.truth.arm import working_volume

ROOT = Path(__file__).resolve().parents[1]
CELL = ROOT / "config" / "sim-ur5e-uncalibrated.yaml"


def synthetic_views(world, cands, corners, rng) -> list[ak.ArmView]:
    """The corners each pose's true camera sees (0.05 px noise), the arm within its repeatability, joints as the
    encoder reports them."""
    camera = world.cameras["wrist"]
    board = next(b for b in world.boards.values() if b.config.mount == "table")
    points = (corners * board.scale) @ board.pose[:3, :3].T + board.pose[:3, 3]
    resolution = math.radians(world.config.robot.encoder_resolution_deg)
    views = []
    for k, c in enumerate(cands):
        F = world.true_arm.flange(c.joints)
        F[:3, 3] += rng.normal(0.0, world.config.robot.repeatability_mm * 1e-3, 3)
        uv = camera.posed(F @ camera.mount).project(points) + rng.normal(0.0, 0.05, (len(points), 2))
        w, h = camera.config.resolution_px
        seen = (uv[:, 0] > 0) & (uv[:, 0] < w - 1) & (uv[:, 1] > 0) & (uv[:, 1] < h - 1)
        views.append(ak.ArmView(f"p{k}", np.round(c.joints / resolution) * resolution, np.flatnonzero(seen), uv[seen]))
    return views


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", type=int, nargs="+", default=[30, 100, 300])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    config, _ = load_cell_file(CELL)
    world = build_world(config.sim.model_copy(update={"seed": args.seed}))
    params = config.routines["arm-kinematics"]  # the cell file's section: the region the routine plans in
    drawing = BoardDrawing((12, 9), 0.02, 0.015, "DICT_5X5_250", 0)
    corners = drawing.corners()
    table = nominal_table("ur5e")
    routine = ArmKinematics()
    p = routine.Params(**params)
    region = routine._region(p, (2448, 2048))
    cands = poses_.candidates(region, table, 2 * max(args.poses), args.seed)
    rng = np.random.default_rng(args.seed)
    camera, board = world.cameras["wrist"], next(b for b in world.boards.values() if b.config.mount == "table")
    Q = working_volume(table)
    truth = [inverse(board.pose) @ world.true_arm.flange(q) @ camera.mount for q in Q]
    print(f"{'poses':>5} {'corners':>7} {'hand-eye s':>10} {'arm fit s':>9} {'chain s':>7} {'after mm':>8}")
    for n in args.poses:
        views = synthetic_views(world, cands[:n], corners, rng)
        b = he.Board(corners * board.scale)  # the print as measured exactly: the fit's own error only
        t0 = time.perf_counter()
        hv = ak.views_of(views, table)
        before = he.fit_views(hv, b, "eye-in-hand", first_intrinsics(hv, b, (2448, 2048)))
        t1 = time.perf_counter()
        result = ak.fit(views, b, before.intrinsics, table, before.X, before.Y)
        t2 = time.perf_counter()
        ak.sequential(views, b, before.intrinsics, table, before.X, before.Y, result.observability["free_mask"])
        t3 = time.perf_counter()
        err = np.mean([he.transform_error(inverse(result.Y) @ result.table.forward(q) @ result.X, t)[0]
                       for q, t in zip(Q, truth)]) * 1e3
        print(f"{n:>5} {sum(len(v.ids) for v in views):>7} {t1 - t0:>10.1f} {t2 - t1:>9.1f} {t3 - t2:>7.1f} "
              f"{err:>8.3f}", flush=True)


if __name__ == "__main__":
    main()
