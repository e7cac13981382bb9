"""Frames per second through each camera backend that runs without hardware.

- sim: the in-process simulated camera (renders every frame);
- uvc-png: UvcCamera on the rendered frames as a PNG sequence (CAP_IMAGES);
- uvc-ffv1: UvcCamera on the same frames as an FFV1 video;
- oak-replay: OakCamera on the FFV1 video through depthai's ReplayVideo (host only);
- genicam-viky: GenICamCamera on the genicam wheel's simulated producer (400x400 Mono8),
  free-run at its maximum rate (200 Hz) and at its default (20 Hz).

Usage: .venv/bin/python tools/bench_cameras.py [--camera cam2] [--frames 40]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.limits import WorkspaceBox
from drivers.registry import DriverContext, backend_class
from drivers.sim.kinds import build_world
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.servers.camera_files import view_positions, write_camera_files


def rate(camera, frames: int) -> tuple[float, str]:
    camera.connect()
    try:
        camera.capture(timeout_s=5.0)  # first frame: start-up, not counted
        start = time.perf_counter()
        for _ in range(frames):
            frame = camera.capture(timeout_s=5.0)
        elapsed = time.perf_counter() - start
    finally:
        camera.close()
    h, w = frame.image.shape[:2]
    return frames / elapsed, f"{w}x{h} {frame.image.dtype}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--camera", default="cam2", help="camera of the micro cell's sim section")
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args()
    data = yaml.safe_load((ROOT / "config" / "sim-microcell.yaml").read_text())
    config = SimWorldConfig(**data["sim"])
    limits = WorkspaceBox(**data["arm"]["limits"])
    context = DriverContext(sim_config=config)
    n_files = args.frames + 1

    results = []
    sim = backend_class("camera", "sim").create(args.camera, {"sim_camera": args.camera}, context)
    results.append(("sim (renders)", *rate(sim, args.frames)))
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        files = write_camera_files(build_world(config), args.camera, tmp, view_positions(config, args.camera, n_files),
                                   limits=limits)
        write_s = time.perf_counter() - start
        uvc = backend_class("camera", "uvc")
        results.append(("uvc-png", *rate(uvc.create("c", {"source": files.sequence}), args.frames)))
        results.append(("uvc-ffv1", *rate(uvc.create("c", {"source": files.video}), args.frames)))
        oak = backend_class("camera", "oak")
        results.append(("oak-replay", *rate(oak.create("c", {"replay": files.video, "fps": 1000}), args.frames)))
    spec = importlib.util.find_spec("genicam")
    viky = Path(spec.submodule_search_locations[0]) / "viky.cti" if spec else None
    if viky and viky.is_file():
        genicam = backend_class("camera", "genicam")
        for hz in (200.0, 20.0):
            options = {"producer": str(viky), "serial": "0", "pixel_format": "Mono8", "frame_rate_hz": hz}
            results.append((f"genicam-viky {hz:g} Hz", *rate(genicam.create("c", options), min(args.frames, 40))))
    print(f"writing {n_files} frames of {args.camera} (render + PNG + FFV1): {write_s:.2f} s")
    print(f"{'backend':<22} {'frames/s':>9}  frame")
    for name, fps, shape in results:
        print(f"{name:<22} {fps:9.1f}  {shape}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
