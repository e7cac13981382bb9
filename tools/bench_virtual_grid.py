"""Benchmark of the virtual-grid pieces, each beside its OpenCV equivalent on the same data.

    .venv/bin/python tools/bench_virtual_grid.py [--repeat N] [--fit-repeat N] [--draws N]

- centroid: time per 2448x2050 frame of the simulated camera 1 (our sub-pixel centroid
  vs cv2.SimpleBlobDetector), with each one's error against the true centre;
- fit: time to fit 56, 500 and 5,000 samples (our B1+B2 least squares vs the OpenCV baseline of
  calibration/baseline.py: cv2.calibrateCamera as the undistortion fit, then cv2.findHomography),
  with each one's map error against the true map, the time ratio, and the growth of each one's
  time per sample from n=56 (1.0 = linear; above it, worse than linear);
- accuracy over draws: the same fits on --draws fresh draws of the noise and the sample pixels,
  since one draw of 56 noisy samples decides little.

Timings are best-of-N (the machine may be shared; a fit round averages many calls), printed, never asserted; tests assert accuracy only.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml
from bench_timing import best_of  # tools/bench_timing.py

from drivers.interfaces import Pose
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.micro.truth import true_command_for_pixel
from drivers.sim.micro.world import World

from calibration.baseline import OpenCVPlanarMap
from calibration.models.planar import fit_planar_map
from calibration.vision.centroid import blob_detector_centroid, find_blob

ROOT = Path(__file__).resolve().parents[1]
SIZES = (56, 500, 5000)


def calls_in(fn, budget: float = 0.05) -> int:
    """How many calls of fn take about `budget` seconds: a sub-millisecond fit is timed over many calls."""
    t = time.perf_counter()
    fn()
    return max(1, int(budget / max(time.perf_counter() - t, 1e-6)))


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


def map_errors(uv, xy, size, check_uv, true_xy) -> tuple[np.ndarray, np.ndarray]:
    """Each fit's map error (µm) at the check pixels: ours, OpenCV's."""
    ours = fit_planar_map(uv, xy, size).map.pixel_to_plane(check_uv)
    theirs = OpenCVPlanarMap(uv, xy, size).pixel_to_plane(check_uv)
    return (np.linalg.norm(ours - true_xy, axis=1) * 1e6, np.linalg.norm(theirs - true_xy, axis=1) * 1e6)


def bench_fit(world: World, repeat: int, draws: int) -> None:
    rng = np.random.default_rng(1)
    cam = world.cameras["cam1"]
    size = (cam.width, cam.height)
    check_uv = rng.uniform([150, 150], [cam.width - 150, cam.height - 150], size=(500, 2))
    true_xy = true_command_for_pixel(world, "cam1", check_uv, 0.0, 0.0)
    # drawn in this order so that n=56 and 5,000 keep the samples of the earlier two-size benchmark
    data = {n: samples(world, n, rng) for n in (56, 5000, 500)}
    print("\nfit: time (ms), ratio, growth of the time per sample from n=56 (1.0 = linear),")
    print("     map error against the true map, mean / max (µm)")
    print("     n   cellctl   OpenCV   ratio   growth ours / OpenCV   error cellctl     error OpenCV")
    first = None
    for n in SIZES:
        uv, xy = data[n]
        ours = lambda uv=uv, xy=xy: fit_planar_map(uv, xy, size)  # noqa: E731 - a timed call, named for the table
        theirs = lambda uv=uv, xy=xy: OpenCVPlanarMap(uv, xy, size)  # noqa: E731 - the same
        t_ours, t_cv = best_of(ours, repeat, calls_in(ours)), best_of(theirs, repeat, calls_in(theirs))
        e_ours, e_cv = map_errors(uv, xy, size, check_uv, true_xy)
        first = first or (n, t_ours, t_cv)
        g_ours = (t_ours / n) / (first[1] / first[0])
        g_cv = (t_cv / n) / (first[2] / first[0])
        print(f"  {n:5d}  {t_ours * 1e3:8.2f} {t_cv * 1e3:8.2f}  {t_ours / t_cv:6.2f}   {g_ours:6.3f} / {g_cv:6.3f}"
              f"     {e_ours.mean():.3f} / {e_ours.max():.3f}    {e_cv.mean():.3f} / {e_cv.max():.3f}")
    if draws:
        print(f"\naccuracy over {draws} draws of the samples: mean map error (µm), mean over the draws ± its standard")
        print("error; and the draws where ours is at least as good")
        rng = np.random.default_rng(2)
        for n in SIZES:
            means = np.array([[e.mean() for e in map_errors(*samples(world, n, rng), size, check_uv, true_xy)]
                              for _ in range(draws)])
            m, se = means.mean(axis=0), means.std(axis=0, ddof=1) / np.sqrt(draws)
            print(f"  n={n:<5d}  cellctl {m[0]:.3f} ± {se[0]:.3f}   OpenCV {m[1]:.3f} ± {se[1]:.3f}   "
                  f"ours <= OpenCV in {int(np.sum(means[:, 0] <= means[:, 1]))} of {draws}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--fit-repeat", type=int, default=7, help="rounds of the fit timings (best of)")
    parser.add_argument("--draws", type=int, default=20, help="noise draws for the accuracy section (0: skip it)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    sim = yaml.safe_load((ROOT / "config" / "sim-microcell.yaml").read_text())["sim"]
    world = World(SimWorldConfig(**dict(sim, seed=args.seed)))
    bench_centroid(world, args.repeat)
    bench_fit(world, args.fit_repeat, args.draws)


if __name__ == "__main__":
    main()
