"""How long the hand-eye fit takes at 15, 50 and 200 poses, beside OpenCV's chain on the same corners.

    .venv/bin/python tools/bench_hand_eye.py [--poses 15 50 200] [--seed 1] [--repeat 3]

The corners come from the simulated UR5e cell (config/sim-ur5e-handeye.yaml) at planned eye-in-hand poses, where
they truly project plus 0.05 px of noise (no rendering: this times the fit, not the simulator). Columns: the
simultaneous adjustment (models.hand_eye.fit_views, intrinsics, board scale and a flange correction per pose), the
first intrinsics it starts from (cv2.calibrateCamera), and OpenCV's chain after them (solvePnP per pose, then
calibrateHandEye PARK); each the best of --repeat, in seconds, and X's error against the truth.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from geometry import ur

from drivers.sim.kinds import build_world

from calibration.models import hand_eye as he
from calibration.routines.six_axis.hand_eye import HandEye, chain_pairs, first_intrinsics

from cellctl.config import load_cell_file
from cellctl.core.runs import routine_params

ROOT = Path(__file__).resolve().parents[1]


def views_at(world, plan, rng) -> list[he.View]:
    views = []
    for p in plan.poses:
        world.move_joints(p.joints)
        ids, uv = world.corner_pixels("wrist", "table", world.camera_pose("wrist"))
        views.append(he.View(p.name, ur.forward(world.reported_joints()), ids, uv + rng.normal(0, 0.05, uv.shape)))
    return views


def best_of(repeat: int, work):
    times, out = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        out = work()
        times.append(time.perf_counter() - start)
    return min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, nargs="+", default=[15, 50, 200])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    config, _ = load_cell_file(ROOT / "config" / "sim-ur5e-handeye.yaml")
    world = build_world(config.sim.model_copy(update={"seed": args.seed}))
    routine = HandEye()
    params = routine_params(routine, config, {})
    board = he.Board(params.drawing().corners())
    X_true = world.cameras["wrist"].mount
    print(f"{'poses':>5} {'corners':>8} {'fit s':>7} {'first K s':>9} {'OpenCV s':>8} {'fit X mm':>9} "
          f"{'OpenCV X mm':>11}")
    for n in args.poses:
        plan = routine.pose_plan(routine_params(routine, config, {"poses": n, "verify_poses": 0}), (2448, 2048))
        views = views_at(world, plan, np.random.default_rng(args.seed))
        t_first, lens0 = best_of(args.repeat, lambda views=views: first_intrinsics(views, board, (2448, 2048)))
        t_fit, result = best_of(args.repeat, lambda views=views, lens0=lens0: he.fit_views(views, board,
                                                                                            "eye-in-hand", lens0))

        def chain(views=views, lens0=lens0):
            pairs = chain_pairs(views, board, lens0)
            return he.opencv_baselines([v.T_base_flange for v in views], pairs, "eye-in-hand")["PARK"]

        t_cv, park = best_of(args.repeat, chain)
        print(f"{n:5d} {sum(len(v.ids) for v in views):8d} {t_fit:7.2f} {t_first:9.2f} {t_cv:8.3f} "
              f"{he.transform_error(result.X, X_true)[0] * 1e3:9.3f} "
              f"{he.transform_error(park['X'], X_true)[0] * 1e3:11.3f}", flush=True)


if __name__ == "__main__":
    main()
