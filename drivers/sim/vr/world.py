"""The one simulated truth of the VR cell: where the cameras really are, the receptacle, the ORU in
the gripper, the arm's errors; images rendered from it; what a simulated operator does in it.

Calibration code never reads this module. Noise drawn during a run (robot
repeatability, image noise, click errors) comes from a generator keyed by the
run's step (`begin_step`), as in drivers/sim/micro/world.py, so a resumed run sees the
noise an uninterrupted one would have seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.projection import focal_px, layout_view, pinhole
from geometry.transforms import inverse, pose_matrix, view_matrix

from drivers.sim.base import WorldBase
from drivers.sim.vr.config import VrCamera, VrWorldConfig
from drivers.sim.vr.geometry import INCH, Solid, load_solid, rasterise
from drivers.sim.vr.render import face_shades, render


@dataclass
class TrueCamera:
    V: np.ndarray  # world -> camera
    f: float  # px
    config: VrCamera

    @property
    def size(self) -> tuple[int, int]:
        return self.config.resolution_px

    def project(self, X: np.ndarray) -> np.ndarray:
        p = np.asarray(X, float) @ self.V[:3, :3].T + self.V[:3, 3]
        w, h = self.size
        return pinhole(p, self.f, (w - 1) / 2, (h - 1) / 2)


def nominal_camera(config: VrWorldConfig, name: str, angle_deg: float | None = None,
                   view_width_in: float | None = None, look_at_in=None) -> tuple[np.ndarray, float]:
    """The nominal (V, f) of a camera for an inter-camera angle and, optionally, a zoom giving a view width
    and another point to look at."""
    cam = config.cameras[name]
    angle = config.inter_camera_angle_deg if angle_deg is None else angle_deg
    target = np.asarray(config.look_at_in if look_at_in is None else look_at_in) * INCH
    V = layout_view(target, cam.distance_m, config.side_azimuth_deg, config.side_elevation_deg,
                    angle if name == "top" else 0.0)
    width, height = cam.resolution_px
    view_width = None if view_width_in is None else view_width_in * INCH
    return V, float(focal_px(width, height, cam.distance_m, cam.vfov_deg, view_width))


def mounting_key(angle_deg, view_width_in, look_at_in) -> tuple:
    return (angle_deg, view_width_in, None if look_at_in is None else tuple(float(v) for v in look_at_in))


class VrWorld(WorldBase):
    def __init__(self, config: VrWorldConfig):
        super().__init__(config)
        truth = np.random.default_rng([config.seed, 0])
        self.model_solids = {"oru": load_solid(config.oru_model), "receptacle": load_solid(config.receptacle_model)}
        # the real objects differ from their models by manufacturing tolerance
        tol = config.model_tolerance_mm * 1e-3
        self.solids = {n: Solid(s.name, s.vertices + truth.normal(0, tol, s.vertices.shape), s.faces, s.normals, s.albedo)
                       for n, s in sorted(self.model_solids.items())}
        # the robot's wrist and gripper plate on the ORU's back face: not modelled by the calibration, it hides
        # part of the ORU and adds edges of its own, as the robot does in the seed's views
        self.gripper = _box_solid("gripper", config.robot.gripper_in)
        self.cameras: dict[str, TrueCamera] = {}
        self.mounting: dict[str, tuple] = {}  # the set-up each camera is mounted for
        for name in ("side", "top"):
            self.place_camera(name)
        rec_nominal = pose_matrix([0, 0, np.radians(config.receptacle_yaw_deg)], np.asarray(config.receptacle_in) * INCH)
        self.receptacle = rec_nominal @ _small_pose(truth, config.receptacle_error_in * INCH, config.receptacle_error_deg)
        r = config.robot
        self.grasp = _small_pose(truth, r.grasp_error_mm * 1e-3, r.grasp_error_deg)  # true ORU in the tool frame
        self.arm_error = _small_pose(truth, r.arm_error_mm * 1e-3, r.arm_error_deg)  # world-frame positioning error
        # start: the ORU (nominally at the tool frame) start_distance in front of the nominal receptacle
        self.commanded = rec_nominal @ pose_matrix(translation=(0, config.start_distance_in * INCH, 0))
        self.tool = self.arm_error @ self.commanded

    # -- truth -------------------------------------------------------------
    def place_camera(self, name: str, angle_deg: float | None = None, view_width_in: float | None = None,
                     look_at_in=None) -> None:
        """(Re)mount a camera at its nominal place for this set-up, with a placement error drawn for that set-up."""
        cam = self.config.cameras[name]
        self.mounting[name] = mounting_key(angle_deg, view_width_in, look_at_in)
        V, f = nominal_camera(self.config, name, angle_deg, view_width_in, look_at_in)
        key = [self.seed, 3, ("side", "top").index(name), int(round((angle_deg or 0) * 10)), int(round((view_width_in or 0) * 10))]
        rng = np.random.default_rng(key)
        C = -V[:3, :3].T @ V[:3, 3] + rng.uniform(-1, 1, 3) * cam.placement_mm * 1e-3
        R = Rotation.from_rotvec(np.radians(rng.uniform(-1, 1, 3) * cam.pointing_deg)).as_matrix() @ V[:3, :3]
        self.cameras[name] = TrueCamera(view_matrix(R, C), f * (1 + rng.uniform(-1, 1) * cam.focal_pct / 100), cam)

    def oru_pose(self) -> np.ndarray:
        return self.tool @ self.grasp

    def object_pose(self, name: str) -> np.ndarray:
        return self.oru_pose() if name == "oru" else self.receptacle

    def relative_truth(self) -> np.ndarray:
        """The true pose of the ORU in the receptacle frame."""
        return inverse(self.receptacle) @ self.oru_pose()

    # -- arm ---------------------------------------------------------------
    def move_arm(self, T_cmd: np.ndarray) -> None:
        r = self.config.robot
        distance = np.linalg.norm(T_cmd[:3, 3] - self.commanded[:3, 3])
        self.clock.advance(distance / (r.speed_mm_s * 1e-3) + r.settle_s)
        with self.lock:
            noise = pose_matrix(np.radians(self.rng.normal(0, r.repeatability_deg, 3)), self.rng.normal(0, r.repeatability_mm * 1e-3, 3))
            self.commanded = np.array(T_cmd, float)
            self.tool = self.arm_error @ self.commanded @ noise

    # -- images ------------------------------------------------------------
    def _polygons(self):
        polys, shades = [], []
        look = self.config.rendering
        for name, albedo in (("oru", look.oru_albedo), ("receptacle", look.receptacle_albedo), ("gripper", look.gripper_albedo)):
            solid = self.gripper if name == "gripper" else self.solids[name]
            M = self.tool if name == "gripper" else self.object_pose(name)
            if solid is None:
                continue
            world_v = solid.vertices @ M[:3, :3].T + M[:3, 3]
            polys += [world_v[f] for f in solid.faces]
            shade = face_shades(solid.normals @ M[:3, :3].T, albedo, look)
            shades.append(shade * solid.albedo if solid.albedo is not None else shade)
        return polys, np.concatenate(shades)

    def capture(self, name: str, frame_id: int) -> np.ndarray:
        with self.lock:
            cam = self.cameras[name]
            polys, shades = self._polygons()
            image = render(cam.V, cam.f, cam.config, self.config.rendering, polys, shades, self.rng)
            self.frame_truth[(name, frame_id)] = {
                "step": self.step, "V": cam.V.copy(), "f": cam.f, "oru": self.oru_pose(), "receptacle": self.receptacle.copy(),
                "relative": self.relative_truth(), "commanded": self.commanded.copy()}
        self.clock.advance(0.1)
        return image

    # -- what a simulated operator does --------------------------------------
    def clicks(self, camera: str, obj: str, model_points: np.ndarray, at_least: int, at_most: int = 8):
        """Visible model points clicked in the image (index, u, v), with the operator's pointing error."""
        cam = self.cameras[camera]
        solid_nominal, solid = self.model_solids[obj], self.solids[obj]
        M = self.object_pose(obj)
        pts = []
        for X in np.asarray(model_points, float):  # a model vertex stands for the real one
            d = np.linalg.norm(solid_nominal.vertices - X, axis=1)
            pts.append(solid.vertices[np.argmin(d)] if d.min() < 1e-4 else X)
        world = np.asarray(pts) @ M[:3, :3].T + M[:3, 3]
        width, height = cam.size
        polys, _ = self._polygons()
        zbuf, _ = rasterise(width, height, [p @ cam.V[:3, :3].T + cam.V[:3, 3] for p in polys], cam.f,
                            (width - 1) / 2, (height - 1) / 2)
        depth = world @ cam.V[2, :3] + cam.V[2, 3]
        uv = cam.project(world)
        visible = []
        for k, ((u, v), z) in enumerate(zip(uv, depth)):
            ui, vi = int(round(u)), int(round(v))
            if 2 <= ui < width - 2 and 2 <= vi < height - 2 and z <= zbuf[vi - 2:vi + 3, ui - 2:ui + 3].max() * 1.003:
                visible.append(k)
        if len(visible) < at_least:
            return []
        # well spread over the image, as the seed's operator does: farthest-point order from a random start
        with self.lock:
            order = [visible[int(self.rng.integers(len(visible)))]]
            while len(order) < min(at_most, len(visible)):
                rest = [k for k in visible if k not in order]
                dist = [min(np.linalg.norm(uv[k] - uv[j]) for j in order) for k in rest]
                order.append(rest[int(np.argmax(dist))])
            noisy = uv[order] + self.rng.normal(0, self.config.operator.click_sigma_px, (len(order), 2))
        self.clock.advance(2 * self.config.operator.seconds_per_click * len(order))
        return [(int(k), float(u), float(v)) for k, (u, v) in zip(order, noisy)]

    def hand_aligned_command(self, standoff_m: float) -> np.ndarray:
        """The arm command an operator reaches by jogging until the ORU stands aligned `standoff_m` in front
        of the receptacle (true alignment with the operator's small error)."""
        op = self.config.operator
        with self.lock:
            err = pose_matrix(np.radians(self.rng.normal(0, op.align_error_deg, 3)), self.rng.normal(0, op.align_error_in * INCH, 3))
        oru = self.receptacle @ pose_matrix(translation=(0, standoff_m, 0)) @ err
        # tool = arm_error @ cmd (noise aside) and oru = tool @ grasp
        return inverse(self.arm_error) @ oru @ inverse(self.grasp)


def _box_solid(name: str, extent) -> Solid | None:
    """A box (x0, x1, y0, y1, z0, z1 in inches, tool frame), faces counter-clockwise from outside."""
    if extent is None:
        return None
    x0, x1, y0, y1, z0, z1 = (v * INCH for v in extent)
    v = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)])
    faces = tuple(np.array(f[::-1]) for f in ([0, 2, 6, 4], [1, 5, 7, 3], [0, 4, 5, 1], [2, 3, 7, 6], [0, 1, 3, 2], [4, 6, 7, 5]))
    normals = np.array([np.cross(v[f][1] - v[f][0], v[f][2] - v[f][0]) for f in faces])
    return Solid(name, v, faces, normals / np.linalg.norm(normals, axis=1, keepdims=True))


def _small_pose(rng: np.random.Generator, metres: float, degrees: float) -> np.ndarray:
    return pose_matrix(np.radians(rng.uniform(-1, 1, 3) * degrees), rng.uniform(-1, 1, 3) * metres)
