"""Benchmark of the virtual-grid pieces, each beside its OpenCV equivalent on the same data.

    .venv/bin/python tools/bench_virtual_grid.py [--repeat N]

- centroid: time per 2448x2050 frame of the simulated camera 1 (our sub-pixel centroid
  vs cv2.SimpleBlobDetector), with each one's error against the true centre;
- fit: time to fit 56 and 5,000 samples (our B1+B2 least squares vs the OpenCV baseline of
  calibration/baseline.py: cv2.calibrateCamera as the undistortion fit, then cv2.findHomography),
  with each one's map error.

Timings are printed, never asserted; tests assert accuracy only.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml

from calibration.baseline import OpenCVPlanarMap
from calibration.models.planar import fit_planar_map
from calibration.vision.centroid import blob_detector_centroid, find_blob
from drivers.interfaces import Pose
from drivers.sim.config import SimWorldConfig
from drivers.sim.truth import true_command_for_pixel
from drivers.sim.world import World

ROOT = Path(__file__).resolve().parents[1]


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def bench_centroid(world: World, repeat: int) -> None:
    rng = np.random.default_rng(0)
    frames, truths = [], []
    for k in range(10):
        world.begin_step(k)
        x, y = 0.040 + rng.uniform(-6e-3, 6e-3), 0.030 + rng.uniform(-5e-3, 5e-3)
        world.move_arm(Pose(x, y, 0.0))
        frames.append(world.capture("cam1", k + 1))
        truths.append(world.frame_truth[("cam1", k + 1)].features_px[0])
    ours = [find_blob(f) for f in frames]
    theirs = [blob_detector_centroid(f) for f in frames]
    err_ours = np.sqrt(np.mean([(b.u - t[0]) ** 2 + (b.v - t[1]) ** 2 for b, t in zip(ours, truths)]))
    err_cv = np.sqrt(np.mean([(b.u - t[0]) ** 2 + (b.v - t[1]) ** 2 for b, t in zip(theirs, truths)]))
    t_ours = np.mean([best_of(lambda f=f: find_blob(f), repeat) for f in frames])
    t_cv = np.mean([best_of(lambda f=f: blob_detector_centroid(f), repeat) for f in frames])
    print("centroid, 2448x2050 frame          time (ms)   RMS error (px)")
    print(f"  cellctl find_blob                 {t_ours * 1e3:8.1f}   {err_ours:.4f}")
    print(f"  cv2.SimpleBlobDetector            {t_cv * 1e3:8.1f}   {err_cv:.4f}")
    print(f"  ratio (ours / OpenCV)             {t_ours / t_cv:8.2f}   {err_ours / err_cv:.3f}")


def samples(world: World, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """n noisy (pixel, robot) pairs of camera 1 from the true map (no rendering: fit time only)."""
    cam = world.cameras["cam1"]
    uv = rng.uniform([150, 150], [cam.width - 150, cam.height - 150], size=(n, 2))
    xy = true_command_for_pixel(world, "cam1", uv, 0.0, 0.0) + rng.normal(0, 1.7e-6, (n, 2))
    return uv, xy


def bench_fit(world: World, repeat: int) -> None:
    rng = np.random.default_rng(1)
    cam = world.cameras["cam1"]
    size = (cam.width, cam.height)
    check_uv = rng.uniform([150, 150], [cam.width - 150, cam.height - 150], size=(500, 2))
    true_xy = true_command_for_pixel(world, "cam1", check_uv, 0.0, 0.0)
    print("\nfit                                time (ms)   map error mean / max (µm)")
    for n in (56, 5000):
        uv, xy = samples(world, n, rng)
        t_ours = best_of(lambda: fit_planar_map(uv, xy, size), repeat)
        ours = fit_planar_map(uv, xy, size)
        e_ours = np.linalg.norm(ours.map.pixel_to_plane(check_uv) - true_xy, axis=1) * 1e6
        t_cv = best_of(lambda: OpenCVPlanarMap(uv, xy, size), repeat)
        e_cv = np.linalg.norm(OpenCVPlanarMap(uv, xy, size).pixel_to_plane(check_uv) - true_xy, axis=1) * 1e6
        print(f"  cellctl B1+B2, n={n:<5}            {t_ours * 1e3:8.1f}   {e_ours.mean():.3f} / {e_ours.max():.3f}")
        print(f"  OpenCV homography+calib, n={n:<5}  {t_cv * 1e3:8.1f}   {e_cv.mean():.3f} / {e_cv.max():.3f}")
        print(f"  ratio (ours / OpenCV)             {t_ours / t_cv:8.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    sim = yaml.safe_load((ROOT / "config" / "sim-microcell.yaml").read_text())["sim"]
    world = World(SimWorldConfig(**dict(sim, seed=args.seed)))
    bench_centroid(world, args.repeat)
    bench_fit(world, args.repeat)


if __name__ == "__main__":
    main()
