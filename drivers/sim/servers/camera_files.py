"""The simulated world written to files a real camera driver can read: image sequences and videos.

The world is filmed through its own fakes: a `SimArm` moves the tool through a list
of poses (limits checked, motion taking simulated time) and a `SimCamera` renders
each frame (`World.capture`), so the files show the same cell the in-process
cameras see, and the same scene seen through `drivers.cameras.uvc` (image
sequence or video) or `drivers.cameras.oak` (ReplayVideo) can be compared with it.

- Image sequence: lossless PNG, `frame_0000.png`, `frame_0001.png`, … in the
  camera's own depth (8- or 16-bit grayscale). Read back with OpenCV's CAP_IMAGES
  it is pixel-equal to the rendered frames.
- Video: FFV1 in an AVI container, grayscale, lossless for 8-bit cameras. depthai
  3.12's ReplayVideo (it decodes with its own FFMPEG-based OpenCV) plays it, as it
  plays MJPEG and MPEG-4 part 2 in .avi / .mp4; it does not open PNG-in-AVI, and it
  decodes a 16-bit video to 8 bits, so 16-bit frames go into the video as their
  high byte (the image sequence keeps all 16 bits).
- `poses.csv`: the commanded pose of every frame (what a robot log would hold; no
  hidden truth).

Frame i is rendered in world step `first_step + i` (`World.begin_step`), so the
same config renders the same frame again, which is how tests check the drivers
return the simulated frames unchanged.

From a shell: `python -m drivers.sim.servers.camera_files --cell config/sim-microcell.yaml
--camera cam1 --out /tmp/cam1` (or `serve(...)` from the CLI).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from drivers.interfaces import Pose
from drivers.limits import WorkspaceBox
from drivers.sim.devices import SimArm, SimArmSettings, SimCamera, SimCameraSettings
from drivers.sim.kinds import build_world

SEQUENCE_PATTERN = "frame_%04d.png"
VIDEO_NAME = "frames.avi"
VIDEO_FOURCC = "FFV1"  # lossless; played by depthai's ReplayVideo and by OpenCV


@dataclass
class CameraFiles:
    """What was written, and the frames as rendered (for comparison)."""

    camera: str
    sequence: str | None  # printf pattern of the PNG files, e.g. /tmp/x/frame_%04d.png
    video: str | None
    poses: list[Pose] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)
    first_step: int = 0

    @property
    def resolution(self) -> tuple[int, int]:
        height, width = self.images[0].shape[:2]
        return width, height


def view_positions(world_config, camera: str, n: int = 8, radius_fraction: float = 0.2) -> list[Pose]:
    """Poses that move the tool round a circle in the camera's view, at the height it is focused on.

    Fixed camera: round its view centre, tool tip in its focal plane, turning alpha as it goes.
    Camera on the arm: the arm circles over the supply (or its home) at the height that puts the
    working surface in focus, so the scene slides through the view."""
    if camera not in world_config.cameras:
        known = ", ".join(sorted(world_config.cameras)) or "none"
        raise ValueError(f"camera {camera!r}: no sim.cameras.{camera} (defined: {known})")
    if n < 1:
        raise ValueError(f"n: at least one position, got {n}")
    cam = world_config.cameras[camera]
    half_view_mm = 0.5 * min(cam.resolution_px) * cam.pixel_um * 1e-3
    if cam.mounted_on_arm:
        supply = world_config.supply
        cx, cy = (supply.position_mm if supply is not None else world_config.motion.home_mm[:2])
        cx, cy = cx - cam.centre_mm[0], cy - cam.centre_mm[1]  # the optical axis over the centre at alpha 0
        z_mm = world_config.floor_z_mm - cam.focus_z_mm
    else:
        cx, cy = cam.centre_mm
        z_mm = cam.focus_z_mm
    r = radius_fraction * half_view_mm
    poses = []
    for i in range(n):
        a = math.tau * i / n
        alpha = 0.0 if cam.mounted_on_arm else math.radians(30.0) * math.sin(a)  # turning to and fro
        poses.append(Pose((cx + r * math.cos(a)) * 1e-3, (cy + r * math.sin(a)) * 1e-3, z_mm * 1e-3, alpha))
    return poses


def render_frames(world, camera: str, poses: list[Pose], limits: WorkspaceBox | None = None,
                  first_step: int = 0, stop: threading.Event | None = None) -> CameraFiles:
    """Move the simulated arm through `poses` and capture one frame at each (nothing written).

    `limits`: the cell's workspace box; None: the box that just holds the poses."""
    arm = SimArm("arm", world, SimArmSettings(limits=limits or _box_around(poses)))
    cam = SimCamera(camera, world, SimCameraSettings(sim_camera=camera))
    arm.connect()
    cam.connect()
    out = CameraFiles(camera, None, None, first_step=first_step)
    try:
        for i, pose in enumerate(poses):
            if stop is not None and stop.is_set():
                break
            world.begin_step(first_step + i)
            arm.move_linear(pose)
            out.poses.append(pose)
            out.images.append(cam.capture().image)
    finally:
        arm.close()
        cam.close()
    return out


def write_sequence(images: list[np.ndarray], directory: str | os.PathLike,
                   pattern: str = SEQUENCE_PATTERN) -> str:
    """Lossless PNGs, 8- or 16-bit grayscale as given; returns the printf pattern of their paths."""
    if not images:
        raise ValueError("images: nothing to write")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for i, image in enumerate(images):
        _check_gray(image, i)
        final = directory / (pattern % i)
        partial = final.with_name(final.stem + ".partial.png")  # never a half-written frame under its name
        if not cv2.imwrite(str(partial), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"could not write {partial}")
        os.replace(partial, final)
    return str(directory / pattern)


def write_video(images: list[np.ndarray], path: str | os.PathLike, fps: float = 10.0) -> str:
    """An FFV1 grayscale video (AVI or MKV) that depthai's ReplayVideo and OpenCV play; 8-bit
    frames exactly, 16-bit frames as their high byte (ReplayVideo decodes 8 bits only)."""
    if not images:
        raise ValueError("images: nothing to write")
    if not 0 < fps <= 1000:
        raise ValueError(f"fps: between 0 and 1000, got {fps}")
    path = Path(path)
    if path.suffix.lower() not in (".avi", ".mkv"):
        raise ValueError(f"video {str(path)!r}: use .avi or .mkv (FFV1 in those containers is what ReplayVideo plays)")
    height, width = images[0].shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.stem + ".partial" + path.suffix)
    writer = cv2.VideoWriter(str(partial), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*VIDEO_FOURCC), float(fps),
                             (width, height), isColor=False)
    if not writer.isOpened():
        raise OSError(f"OpenCV cannot write an {VIDEO_FOURCC} video to {partial} (no FFMPEG in this OpenCV?)")
    try:
        for i, image in enumerate(images):
            _check_gray(image, i)
            if image.shape[:2] != (height, width):
                raise ValueError(f"images[{i}]: {image.shape[1]}x{image.shape[0]}, the video is {width}x{height}")
            writer.write(image if image.dtype == np.uint8 else (image >> 8).astype(np.uint8))
    except BaseException:
        writer.release()
        partial.unlink(missing_ok=True)
        raise
    writer.release()
    os.replace(partial, path)
    return str(path)


def write_camera_files(world, camera: str, out_dir: str | os.PathLike, poses: list[Pose] | None = None,
                       n: int = 8, sequence: bool = True, video: bool = True, fps: float = 10.0,
                       limits: WorkspaceBox | None = None, first_step: int = 0,
                       stop: threading.Event | None = None) -> CameraFiles:
    """Render `camera`'s view of `world` while the arm moves (default: `view_positions`) and write
    the image sequence, the video and poses.csv into `out_dir`."""
    if poses is None:
        poses = view_positions(world.config, camera, n)
    files = render_frames(world, camera, poses, limits, first_step, stop)
    if not files.images:
        return files
    out_dir = Path(out_dir)
    if sequence:
        files.sequence = write_sequence(files.images, out_dir)
    if video:
        files.video = write_video(files.images, out_dir / VIDEO_NAME, fps)
    _write_poses(files.poses, out_dir / "poses.csv")
    return files


def serve(world_config, out_dir: str | os.PathLike, camera: str | None = None, n: int = 8, fps: float = 10.0,
          limits: WorkspaceBox | None = None, stop: threading.Event | None = None) -> CameraFiles:
    """Entry point for `cellctl sim camera-files`: build the world, write the files, return (not a server:
    files need no port; `stop` ends the rendering between frames)."""
    world = build_world(world_config)
    camera = camera or min(world_config.cameras)
    return write_camera_files(world, camera, out_dir, n=n, fps=fps, limits=limits, stop=stop)


def main(argv: list[str] | None = None) -> int:
    import yaml

    from drivers.sim.micro.config import SimWorldConfig

    parser = argparse.ArgumentParser(description="Write a simulated camera's frames as PNGs and an FFV1 video.")
    parser.add_argument("--cell", required=True, help="cell file with a sim: section (e.g. config/sim-microcell.yaml)")
    parser.add_argument("--camera", help="camera of the sim section (default: the first)")
    parser.add_argument("--out", required=True, help="directory to write into")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--fps", type=float, default=10.0)
    args = parser.parse_args(argv)
    data = yaml.safe_load(Path(args.cell).read_text())
    limits = (data.get("arm") or {}).get("limits")
    files = serve(SimWorldConfig(**data["sim"]), args.out, args.camera, args.frames, args.fps,
                  WorkspaceBox(**limits) if limits else None)
    print(f"{len(files.images)} frames of {files.camera} ({files.resolution[0]}x{files.resolution[1]}): "
          f"{files.sequence}, {files.video}")
    return 0


def _check_gray(image: np.ndarray, index: int) -> None:
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"images[{index}]: expected a 2-D uint8/uint16 grayscale frame, "
                         f"got shape {image.shape} {image.dtype}")


def _box_around(poses: list[Pose]) -> WorkspaceBox:
    if not poses:
        raise ValueError("poses: at least one pose")
    xyz = np.array([[p.x, p.y, p.z] for p in poses]) * 1e3
    alpha = np.degrees([p.alpha for p in poses])

    def edge(values):
        return float(np.min(values)) - 1.0, float(np.max(values)) + 1.0

    return WorkspaceBox(x_mm=edge(xyz[:, 0]), y_mm=edge(xyz[:, 1]), z_mm=edge(xyz[:, 2]), alpha_deg=edge(alpha))


def _write_poses(poses: list[Pose], path: Path) -> None:
    partial = path.with_name(path.name + ".partial")
    with open(partial, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["frame", "x_mm", "y_mm", "z_mm", "alpha_deg"])
        for i, p in enumerate(poses):
            out.writerow([i, f"{p.x * 1e3:.4f}", f"{p.y * 1e3:.4f}", f"{p.z * 1e3:.4f}", f"{math.degrees(p.alpha):.4f}"])
    os.replace(partial, path)


if __name__ == "__main__":
    raise SystemExit(main())
