"""Benchmark of the simulated cameras: time per frame of each camera of each simulated cell kind, in the
scenes the routines image (the micro cell's nozzle, a laid dot grid, a placed sphere, the on-board camera;
the six-axis cell's fixture; the VR cell's two views).

    .venv/bin/python tools/bench_sim.py [--repeat N]

Timings are printed, never asserted; tests/drivers/test_sim_render.py asserts what the frames hold.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench_timing import best_of  # tools/bench_timing.py

from drivers.interfaces import Pose
from drivers.sim.kinds import build_world

from cellctl.config import load_cell_file

ROOT = Path(__file__).resolve().parents[1]
TARGET_MS = {"cam1 (2448 x 2050), the nozzle over it": 10.0}


def micro_cell(repeat: int) -> None:
    config, _ = load_cell_file(ROOT / "config" / "sim-microcell.yaml")
    world = build_world(config.sim)
    world.begin_step(0)
    scenes = [  # each set up on the one before
        ("cam1 (2448 x 2050), the nozzle over it", "cam1", lambda: world.move_arm(Pose(0.0405, 0.0302, 0.0))),
        ("cam1, the dot grid laid, the nozzle far out of focus", "cam1",
         lambda: (world.set_fixture("grid-area1", True), world.move_arm(Pose(0.040, 0.030, 0.020)))),
        ("cam2 (1360 x 1024), a placed sphere", "cam2",
         lambda: (world.set_fixture("grid-area1", False), world.add_sphere(0.1103, 0.0398, 0.0),
                  world.move_arm(Pose(0.070, 0.030, 0.015)))),
        ("cam3 (2592 x 1944, on the arm), a sphere out of focus", "cam3",
         lambda: world.move_arm(Pose(0.085, 0.035, 0.0))),
    ]
    print("micro cell                                                  ms per frame   target")
    for label, name, setup in scenes:
        setup()
        world.capture(name, 0)  # the noise bank is drawn on first use
        ms = best_of(lambda name=name: world.capture(name, 1), repeat) * 1e3
        target = f"<= {TARGET_MS[label]:g} ms" if label in TARGET_MS else ""
        print(f"  {label:<56} {ms:8.1f}   {target}")


def other_cell(file: str, title: str, repeat: int) -> None:
    config, _ = load_cell_file(ROOT / "config" / file)
    world = build_world(config.sim)
    world.begin_step(0)
    print(title)
    for name in sorted(world.cameras):
        world.capture(name, 0)
        print(f"  {name:<56} {best_of(lambda name=name: world.capture(name, 1), repeat) * 1e3:8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=10)
    args = parser.parse_args()
    micro_cell(args.repeat)
    other_cell("sim-irb120-csm.yaml", "six-axis cell (1600 x 1200), the fixture in view", args.repeat)
    other_cell("sim-vr.yaml", "VR cell (640 x 480, 2x supersampled)", args.repeat)


if __name__ == "__main__":
    main()
