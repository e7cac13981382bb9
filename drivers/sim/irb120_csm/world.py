"""The simulated IRB 120 CSM cell: the true robot, the true cameras, the fixture they see.

Static truth (drawn once from the seed within the cell file's budgets): the robot's DH errors and joint
zero offsets, each camera's pose, intrinsics and distortion. Dynamic state: the commanded joints, where
the fixture really is (true kinematics plus repeatability noise), a simulated clock.

Noise during a run (repeatability, sensor noise) comes from a generator keyed by the run's step
(`begin_step`), as in drivers/sim/micro/world.py, so a resumed run sees exactly the noise of an uninterrupted one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from geometry.irb120 import IRB120_DH
from geometry.projection import unit_direction
from geometry.transforms import rotation

from drivers.sim.base import WorldBase
from drivers.sim.irb120_csm.config import SixAxisCamera, SixAxisWorldConfig
from drivers.sim.irb120_csm.kinematics import ArmKinematics, draw_true_dh
from drivers.sim.optics import TrueCamera
from drivers.sim.render import NoiseBank, quantise


@dataclass(frozen=True)
class PlanarDisc:
    """A printed disc (optionally with a centre disc of another level) on the fixture plate."""

    centre: np.ndarray  # world (m)
    normal: np.ndarray  # plate normal, facing the viewer side
    u_axis: np.ndarray  # a unit vector in the plate
    radius: float
    level: float
    inner_radius: float = 0.0
    inner_level: float = 0.0


@dataclass
class MoveRecord:
    """Where one move really left the fixture (truth for the report)."""

    step: int | None
    joints: np.ndarray  # commanded
    rotation: np.ndarray
    translation: np.ndarray  # actual fixture origin (with repeatability noise)


@dataclass
class FrameTruth:
    camera: str
    frame_id: int
    step: int | None
    features_px: dict[str, np.ndarray] = field(default_factory=dict)  # true projected centres by feature name


class SixAxisWorld(WorldBase):
    def __init__(self, config: SixAxisWorldConfig):
        super().__init__(config)
        truth_rng = np.random.default_rng([config.seed, 0])
        r, f = config.robot, config.fixture
        self.tool_m = (f.d7_mm * 1e-3, f.a7_mm * 1e-3)
        self.true_dh = draw_true_dh(truth_rng, r.dh_length_error_mm, r.joint_offset_error_deg)
        self.true_arm = ArmKinematics(self.true_dh, self.tool_m)
        self.nominal_arm = ArmKinematics(IRB120_DH, self.tool_m)  # what the controller believes
        centre = np.asarray(config.workspace_centre_mm) * 1e-3
        self.cameras: dict[str, TrueCamera] = {
            name: draw_camera(cam, centre, truth_rng) for name, cam in sorted(config.cameras.items())}
        noise_rng = np.random.default_rng([config.seed, 3])
        self._noise = {name: NoiseBank(cam.width, cam.height, config.cameras[name].noise_pct, 8, noise_rng)
                       for name, cam in self.cameras.items()}
        for bank in self._noise.values():  # drawn now, in this order: every camera's noise fixed by the seed
            bank.draw()
        self.joints = np.radians(np.asarray(r.home_deg, dtype=float))
        R, t = self.true_arm.fixture_pose(self.joints)
        self.fixture_rotation, self.fixture_translation = R, t
        self.moves: list[MoveRecord] = []

    # -- arm ---------------------------------------------------------------
    def move_joints(self, q, settle: bool = True) -> None:
        """Go to joints q (already checked by the controller) and settle (not at a via point: `settle` False);
        the fixture lands within the robot's repeatability of where the true kinematics put it."""
        q = np.asarray(q, dtype=float)
        r = self.config.robot
        travel = float(np.max(np.abs(q - self.joints), initial=0.0))
        self.clock.advance(np.degrees(travel) / r.speed_deg_s + (r.settle_s if settle else 0.0))
        with self.lock:
            R, t = self.true_arm.fixture_pose(q)
            t = t + self.rng.normal(0.0, r.repeatability_mm * 1e-3, 3)
            self.joints, self.fixture_rotation, self.fixture_translation = q.copy(), R, t
            self.moves.append(MoveRecord(self.step, q.copy(), R, t))

    def reported_joints(self) -> np.ndarray:
        """Commanded joints to encoder resolution: the controller cannot see its own geometry errors."""
        res = np.radians(self.config.robot.encoder_resolution_deg)
        return np.round(self.joints / res) * res if res > 0 else self.joints.copy()

    def fixture_point(self, p_fixture_m, rotation_=None, translation=None) -> np.ndarray:
        R = self.fixture_rotation if rotation_ is None else rotation_
        t = self.fixture_translation if translation is None else translation
        return R @ np.asarray(p_fixture_m, dtype=float) + t

    def feature_points(self, rotation_=None, translation=None) -> dict[str, np.ndarray]:
        """True world positions of the white circle and the three black circles."""
        f = self.config.fixture
        points = {"white": self.fixture_point(np.asarray(f.white_mm) * 1e-3, rotation_, translation)}
        for i, b in enumerate(f.black_mm, start=1):
            points[f"black{i}"] = self.fixture_point(np.asarray(b) * 1e-3, rotation_, translation)
        return points

    def discs(self) -> list[tuple[str, PlanarDisc]]:
        f = self.config.fixture
        R = self.fixture_rotation
        normal, u_axis = -R[:, 2], R[:, 0]  # the plate faces -z7
        plate = PlanarDisc(self.fixture_point(np.asarray(f.plate_centre_mm) * 1e-3), normal, u_axis,
                           f.plate_diameter_mm * 0.5e-3, f.plate_level)
        r = f.diameter_mm * 0.5e-3
        out = [("plate", plate)]
        for name, p in self.feature_points().items():
            outer, inner = (f.light_level, f.dark_level) if name == "white" else (f.dark_level, f.light_level)
            out.append((name, PlanarDisc(p, normal, u_axis, r, outer, r / 3, inner)))
        return out

    # -- cameras -----------------------------------------------------------
    def capture(self, name: str, frame_id: int) -> np.ndarray:
        cfg = self.config.cameras[name]
        with self.lock:
            camera = self.cameras[name]
            discs = self.discs()
            image = render(camera, cfg, [d for _, d in discs], self.rng, self._noise[name])
            truth = FrameTruth(name, frame_id, self.step,
                               {n: camera.project(d.centre)[0] for n, d in discs if n != "plate"})
            self.frame_truth[(name, frame_id)] = truth
        self.clock.advance((cfg.exposure_ms + cfg.readout_ms) * 1e-3)
        return image


def draw_camera(cfg: SixAxisCamera, aim: np.ndarray, rng: np.random.Generator) -> TrueCamera:
    """A camera `distance_mm` from the aim point in the given direction, its aim, principal point and
    lens distortion off by amounts drawn within the budget."""
    width, height = cfg.resolution_px
    direction = unit_direction(cfg.azimuth_deg, cfg.elevation_deg)
    distance = cfg.distance_mm * 1e-3
    C = aim + distance * direction
    z = -direction
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R_cw = np.column_stack([x, np.cross(z, x), z])  # image u right, v down, z forward
    err = np.radians(rng.uniform(-1, 1, 3) * cfg.aim_error_deg)
    R_cw = rotation(x, err[0]) @ rotation(np.cross(z, x), err[1]) @ R_cw @ rotation([0, 0, 1], err[2])
    f = distance * height / (cfg.field_mm * 1e-3)
    angle = rng.uniform(0, 2 * np.pi)
    offset = cfg.principal_offset_px * np.sqrt(rng.uniform()) * np.array([np.cos(angle), np.sin(angle)])
    cx, cy = (width - 1) / 2 + offset[0], (height - 1) / 2 + offset[1]
    r_corner = np.hypot(width / 2, height / 2) / f
    shift = rng.uniform(*cfg.corner_distortion_px) * rng.choice([-1.0, 1.0])
    k1 = 0.8 * shift / (f * r_corner**3)
    k2 = 0.2 * shift / (f * r_corner**5)
    angle = rng.uniform(0, 2 * np.pi)
    p1, p2 = abs(shift) * cfg.tangential_fraction / (3 * f * r_corner**2) * np.array([np.cos(angle), np.sin(angle)])
    return TrueCamera(width, height, f, f, cx, cy, k1, k2, p1, p2, R_cw, C, distance)


def render(camera: TrueCamera, cfg: SixAxisCamera, discs: list[PlanarDisc], rng: np.random.Generator,
           bank: NoiseBank) -> np.ndarray:
    """An 8-bit frame: background, the plate and its printed circles traced through the true camera (perspective
    and distortion), anti-aliased edges, blur, sensor noise."""
    h, w = camera.height, camera.width
    image = bank.frame(cfg.background, rng)  # fresh noise is drawn where the fixture is, below
    if not discs or np.dot(discs[0].normal, camera.C - discs[0].centre) <= 0:
        return image  # the plate's back faces the camera (or nothing to draw)
    plate = discs[0]
    side = np.cross(plate.normal, plate.u_axis)
    ring = plate.centre + plate.radius * np.array([np.cos(a) * plate.u_axis + np.sin(a) * side
                                                   for a in np.linspace(0, 2 * np.pi, 24, endpoint=False)])
    corners = camera.project(ring)
    pad = 4 * cfg.blur_px + 4
    u0, v0 = np.floor(corners.min(axis=0) - pad).astype(int)
    u1, v1 = np.ceil(corners.max(axis=0) + pad).astype(int) + 1
    cu0, cu1, cv0, cv1 = max(u0, 0), min(u1, w), max(v0, 0), min(v1, h)
    if cu0 >= cu1 or cv0 >= cv1:
        return image
    x, y = camera.undistort_grid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
    rays = np.stack([x, y, np.ones_like(x)], axis=-1) @ camera.R_cw.T
    t = ((plate.centre - camera.C) @ plate.normal) / (rays @ plate.normal)
    hits = camera.C + t[..., None] * rays
    patch = np.full(x.shape, cfg.background, dtype=np.float32)
    for disc in discs:
        d = hits - disc.centre
        rho = np.sqrt(np.einsum("ijk,ijk->ij", d, d))
        scale = _metres_per_px(rho)
        patch = _paint(patch, rho, scale, disc.radius, disc.level)
        if disc.inner_radius > 0:
            patch = _paint(patch, rho, scale, disc.inner_radius, disc.inner_level)
    if cfg.blur_px > 0:
        patch = cv2.GaussianBlur(patch, (0, 0), sigmaX=cfg.blur_px, borderType=cv2.BORDER_REPLICATE)
    if cfg.noise_pct > 0:
        patch += rng.standard_normal(patch.shape, dtype=np.float32) * np.float32(cfg.noise_pct / 100)
    image[cv0:cv1, cu0:cu1] = quantise(patch[cv0 - v0:cv1 - v0, cu0 - u0:cu1 - u0])
    return image


def _metres_per_px(rho: np.ndarray) -> np.ndarray:
    """How fast the in-plane distance changes per pixel: turns an edge distance into pixels."""
    gv, gu = np.gradient(rho)
    return np.maximum(np.hypot(gu, gv), 1e-12)


def _paint(patch: np.ndarray, rho: np.ndarray, scale: np.ndarray, radius: float, level: float) -> np.ndarray:
    coverage = np.clip((radius - rho) / scale + 0.5, 0.0, 1.0).astype(np.float32)
    return patch * (1 - coverage) + np.float32(level) * coverage
