"""The simulated hand-eye cell: the true UR5e, the true cameras and their mounts, the boards they see.

Static truth (drawn once from the seed within the cell file's budgets): the arm's DH and joint-zero errors on top
of UR's published table; each camera's intrinsics, distortion and true mount; each board's true pose and printing
scale. Dynamic state: the commanded joints, where the flange really is (true kinematics plus repeatability noise),
a simulated clock, and what moved since the calibration (`sim.drift`: a camera bumped on its mount, a board moved;
`mount_now`), which calibration-check has to find.

A frame is rendered by tracing every pixel back through the camera's exact inverse (distortion, perspective) to
each board's plane, where it reads the printed ChArUco pattern (cv2.aruco's own image of the board, at a pyramid
level matched to the pixel's footprint, so a board far away is not aliased); then blur, sensor noise and
quantisation. Noise during a run comes from a generator keyed by the run's step (`begin_step`), so a resumed
run sees the noise of an uninterrupted one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from geometry import ur
from geometry.charuco import BoardDrawing
from geometry.transforms import inverse, look_at

from drivers.sim.base import WorldBase
from drivers.sim.optics import TrueCamera
from drivers.sim.render import quantise
from drivers.sim.ur5e_handeye.config import HandEyeBoard, HandEyeCamera, HandEyeWorldConfig
from drivers.sim.ur5e_handeye.footprint import RayBounds
from drivers.sim.ur5e_handeye.parts import cup_position, draw_parts, paint_parts, part_under

TEXELS_PER_SQUARE = 240  # the finest level of a board's printed pattern
PYRAMID_LEVELS = 6


@dataclass(frozen=True)
class TrueArm:
    """The real UR5e: UR's table with every a and d off by a drawn error, every joint zero off by another."""

    dh: tuple[tuple[float, float, float], ...]
    zero_offsets: np.ndarray  # rad, added to the encoder's angle

    def flange(self, q) -> np.ndarray:
        return ur.forward(np.asarray(q, dtype=float) + self.zero_offsets, self.dh)


def draw_true_arm(rng: np.random.Generator, length_mm: float, joint_deg: float) -> TrueArm:
    rows = []
    for a, d, alpha in ur.UR5E_DH:
        da, dd = rng.uniform(-1, 1, 2) * length_mm * 1e-3
        rows.append((a + da, d + dd, alpha))
    return TrueArm(tuple(rows), np.radians(rng.uniform(-1, 1, 6) * joint_deg))


@dataclass
class Board:
    """A printed board as it really is: where it lies (in the base or the flange frame), how large it was printed,
    and its pattern as a pyramid of images (level k: 2^k texels merged)."""

    name: str
    config: HandEyeBoard
    pose: np.ndarray  # T_base_board (table) or T_flange_board (flange), true
    scale: float  # true printed size over nominal
    charuco: cv2.aruco.CharucoBoard = field(repr=False)
    pyramid: list[np.ndarray] = field(repr=False)

    @property
    def texel_m(self) -> float:
        """Size of a finest-level texel on the true print."""
        return self.config.square_mm * 1e-3 * self.scale / TEXELS_PER_SQUARE

    def true_corners(self) -> np.ndarray:
        """(n, 3) chessboard corners in the board frame as printed (m), in cv2.aruco's id order."""
        return self.charuco.getChessboardCorners().astype(float) * self.scale


def drawing(cfg: HandEyeBoard) -> BoardDrawing:
    """The board as its drawing says (nominal sizes): what the calibration also builds from the cell file."""
    return BoardDrawing(tuple(cfg.squares), cfg.square_mm * 1e-3, cfg.marker_mm * 1e-3, cfg.dictionary,
                        cfg.first_marker)


def draw_board(name: str, cfg: HandEyeBoard, rng: np.random.Generator) -> Board:
    nominal = np.eye(4)
    nominal[:3, :3] = Rotation.from_euler("xyz", cfg.rotation_deg, degrees=True).as_matrix()
    nominal[:3, 3] = np.asarray(cfg.position_mm) * 1e-3
    error = np.eye(4)
    error[:3, :3] = Rotation.from_rotvec(np.radians(rng.uniform(-1, 1, 3) * cfg.pose_error_deg)).as_matrix()
    error[:3, 3] = rng.uniform(-1, 1, 3) * cfg.pose_error_mm * 1e-3
    scale = 1.0 + rng.uniform(-1, 1) * cfg.scale_error_pct / 100
    charuco = drawing(cfg).board()
    sx, sy = cfg.squares
    image = charuco.generateImage((sx * TEXELS_PER_SQUARE, sy * TEXELS_PER_SQUARE), marginSize=0, borderBits=1)
    level = (cfg.black + image.astype(np.float32) / 255 * (cfg.white - cfg.black)).astype(np.float32)
    pyramid = [level]
    for _ in range(PYRAMID_LEVELS - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    return Board(name, cfg, nominal @ error, scale, charuco, pyramid)


@dataclass
class Camera:
    """A true camera: its lens (a TrueCamera at the origin) and its true mount (T_flange_camera or T_base_camera),
    with every pixel's ray (undistorted normalised coordinates), computed once."""

    name: str
    config: HandEyeCamera
    lens: TrueCamera
    mount: np.ndarray
    rays: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    bounds: RayBounds | None = field(default=None, repr=False)

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        if self.rays is None:
            w, h = self.config.resolution_px
            x, y = self.lens.undistort_grid(np.arange(w, dtype=float), np.arange(h, dtype=float))
            self.rays = (x.astype(np.float32), y.astype(np.float32))
        return self.rays

    def ray_bounds(self) -> RayBounds:
        """The rays' extent per row and column (footprint.py), computed once."""
        if self.bounds is None:
            self.bounds = RayBounds(*self.pixel_rays())
        return self.bounds

    def posed(self, T_base_camera: np.ndarray) -> TrueCamera:
        return self.lens.moved(T_base_camera[:3, 3], T_base_camera[:3, :3])


def nominal_mount(cfg: HandEyeCamera) -> np.ndarray:
    """The mount as the engineer would state it: a flange camera `position_mm` from the flange, looking along the
    flange axis, its image turned by roll_deg; a fixed camera at position_mm aiming at look_at_mm."""
    if cfg.mount == "flange":
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", cfg.roll_deg, degrees=True).as_matrix()
        T[:3, 3] = np.asarray(cfg.position_mm) * 1e-3
        return T
    return inverse(look_at(np.asarray(cfg.position_mm) * 1e-3, np.asarray(cfg.look_at_mm) * 1e-3,
                           right=(0.0, -1.0, 0.0)))


def draw_camera(name: str, cfg: HandEyeCamera, rng: np.random.Generator) -> Camera:
    width, height = cfg.resolution_px
    f = cfg.focal_mm / (cfg.pixel_um * 1e-3) * (1 + rng.uniform(-1, 1) * cfg.focal_error_pct / 100)
    angle = rng.uniform(0, 2 * np.pi)
    offset = cfg.principal_offset_px * math.sqrt(rng.uniform()) * np.array([math.cos(angle), math.sin(angle)])
    cx, cy = (width - 1) / 2 + offset[0], (height - 1) / 2 + offset[1]
    r_corner = math.hypot(width / 2, height / 2) / f
    shift = rng.uniform(*cfg.corner_distortion_px) * rng.choice([-1.0, 1.0])
    k1 = 0.8 * shift / (f * r_corner**3)
    k2 = 0.2 * shift / (f * r_corner**5)
    angle = rng.uniform(0, 2 * np.pi)
    p1, p2 = abs(shift) * cfg.tangential_fraction / (3 * f * r_corner**2) * np.array([math.cos(angle), math.sin(angle)])
    error = np.eye(4)
    error[:3, :3] = Rotation.from_rotvec(np.radians(rng.uniform(-1, 1, 3) * cfg.pose_error_deg)).as_matrix()
    error[:3, 3] = rng.uniform(-1, 1, 3) * cfg.pose_error_mm * 1e-3
    lens = TrueCamera(width, height, f, f, cx, cy, k1, k2, p1, p2, np.eye(3), np.zeros(3), 0.3)
    return Camera(name, cfg, lens, nominal_mount(cfg) @ error)


@dataclass
class MoveRecord:
    """Where one move really left the flange (truth for the report)."""

    step: int | None
    joints: np.ndarray  # commanded (rad)
    flange: np.ndarray  # T_base_flange, true (repeatability noise included)


@dataclass
class FrameTruth:
    camera: str
    frame_id: int
    step: int | None
    T_base_camera: np.ndarray
    T_base_flange: np.ndarray
    corners_px: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # board -> (ids, uv) in view


class HandEyeWorld(WorldBase):
    def __init__(self, config: HandEyeWorldConfig):
        super().__init__(config)
        truth_rng = np.random.default_rng([config.seed, 0])
        r = config.robot
        self.true_arm = draw_true_arm(truth_rng, r.dh_length_error_mm, r.joint_offset_error_deg)
        self.cameras = {name: draw_camera(name, cam, truth_rng) for name, cam in sorted(config.cameras.items())}
        self.boards = {name: draw_board(name, b, truth_rng) for name, b in sorted(config.boards.items())}
        self.joints = np.radians(np.asarray(r.home_deg, dtype=float))
        self.flange = self.true_arm.flange(self.joints)
        self.moves: list[MoveRecord] = []
        # parts on the table, from their own stream (the truth above stays what it was for every seed)
        self.parts = draw_parts(config.parts, np.random.default_rng([config.seed, 3]))
        self.held: str | None = None  # the part on the vacuum cup
        self.picks: list[dict] = []  # truth of every grip: step, part, the cup's miss from its centre (m)
        self.placements: list[dict] = []  # truth of every release: step, part, where it lies (m)

    # -- arm ---------------------------------------------------------------
    def move_joints(self, q) -> None:
        """Go to joints q (already checked by the controller) and settle; the flange lands within the arm's
        repeatability of where the true kinematics put it."""
        q = np.asarray(q, dtype=float)
        r = self.config.robot
        travel = float(np.max(np.abs(q - self.joints), initial=0.0))
        self.clock.advance(math.degrees(travel) / r.speed_deg_s + r.settle_s)
        with self.lock:
            T = self.true_arm.flange(q)
            T[:3, 3] += self.rng.normal(0.0, r.repeatability_mm * 1e-3, 3)
            self.joints, self.flange = q.copy(), T
            if self.held is not None:  # the part rides the cup, its top face against it
                self.parts[self.held].centre = cup_position(T, self.config.gripper)
            self.moves.append(MoveRecord(self.step, q.copy(), T.copy()))

    def reported_joints(self) -> np.ndarray:
        """Commanded joints to encoder resolution: the controller cannot see its own geometry errors."""
        res = math.radians(self.config.robot.encoder_resolution_deg)
        return np.round(self.joints / res) * res if res > 0 else self.joints.copy()

    # -- the vacuum cup (drivers.sim.devices.SimGripper) ---------------------
    def grip(self) -> bool:
        """Seal on the part under the cup, if the cup came down on its top near enough its centre."""
        with self.lock:
            if self.held is not None:
                return True
            cup = cup_position(self.flange, self.config.gripper)
            part, miss = part_under(self.parts.values(), cup, self.config.gripper)
            self.picks.append({"step": self.step, "part": part.name if part else None, "miss_m": miss})
            if part is not None:
                self.held = part.name
                part.centre = cup
            return part is not None

    def release(self) -> None:
        """Let go: the part drops onto the table under the cup."""
        with self.lock:
            if self.held is None:
                return
            part = self.parts[self.held]
            part.centre = np.array([*part.centre[:2], part.config.height_mm * 1e-3])
            self.placements.append({"step": self.step, "part": part.name, "centre": part.centre.copy()})
            self.held = None

    # -- where things are ----------------------------------------------------
    def camera_pose(self, name: str, flange: np.ndarray | None = None) -> np.ndarray:
        """T_base_camera, true, with the flange where it is now (or at `flange`)."""
        cam = self.cameras[name]
        mount = self.mount_now(name)
        if cam.config.mount == "fixed":
            return mount
        return (self.flange if flange is None else flange) @ mount

    def board_pose(self, name: str, flange: np.ndarray | None = None) -> np.ndarray:
        """T_base_board, true."""
        board = self.boards[name]
        pose = self.mount_now(name)
        if board.config.mount == "table":
            return pose
        return (self.flange if flange is None else flange) @ pose

    def mount_now(self, name: str) -> np.ndarray:
        """A camera's mount (T_flange_camera or T_base_camera) or a board's pose (T_base_board or T_flange_board)
        as it truly is now: as drawn, moved by its `sim.drift` knob once that is in force (turned about its own
        origin and shifted, along the parent frame's axes)."""
        T = (self.cameras[name].mount if name in self.cameras else self.boards[name].pose).copy()
        knob = self.config.drift.get(name)
        if knob is None or not knob.in_force(self.clock.now()):
            return T
        T[:3, :3] = Rotation.from_rotvec(np.radians(knob.rotation_deg)).as_matrix() @ T[:3, :3]
        T[:3, 3] += np.asarray(knob.translation_mm) * 1e-3
        return T

    # -- cameras -----------------------------------------------------------
    def capture(self, name: str, frame_id: int) -> np.ndarray:
        cfg = self.config.cameras[name]
        with self.lock:
            T_base_camera = self.camera_pose(name)
            image, corners = self.render(name, T_base_camera)
            self.frame_truth[(name, frame_id)] = FrameTruth(name, frame_id, self.step, T_base_camera,
                                                            self.flange.copy(), corners)
        self.clock.advance((cfg.exposure_ms + cfg.readout_ms) * 1e-3)
        return image

    def render(self, name: str, T_base_camera: np.ndarray) -> tuple[np.ndarray, dict]:
        """The frame `name` takes from T_base_camera, and the true pixel of every board corner in view."""
        cam = self.cameras[name]
        cfg = cam.config
        w, h = cfg.resolution_px
        x, y = cam.pixel_rays()
        image = np.full((h, w), cfg.background, dtype=np.float32)
        depth = np.full((h, w), np.inf, dtype=np.float32)
        corners = {}
        for board in self.boards.values():
            T = inverse(T_base_camera) @ self.board_pose(board.name)  # T_camera_board
            if (inverse(T)[2, 3]) >= 0:
                continue  # the camera is behind the print (its face looks toward the board's -z)
            self._paint(board, T, x, y, image, depth, cam.ray_bounds())
            ids, uv = self.corner_pixels(name, board.name, T_base_camera)
            if len(ids):
                corners[board.name] = (ids, uv)
        paint_parts(self.parts.values(), inverse(T_base_camera), x, y, image, depth, cam.ray_bounds())
        if cfg.blur_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), cfg.blur_px)
        if cfg.noise_pct > 0:
            image += self.rng.standard_normal(image.shape, dtype=np.float32) * np.float32(cfg.noise_pct / 100)
        return quantise(image, cfg.bit_depth), corners

    def _paint(self, board: Board, T_camera_board: np.ndarray, x, y, image, depth,
               bounds: RayBounds | None = None) -> None:
        """Each pixel whose ray meets the print, nearer than what it already shows, takes the print's grey there.
        With the rays' `bounds`, only the pixels that can see the print are traced (footprint.py: the same frame,
        sooner)."""
        sx, sy = board.config.squares
        width_m, height_m = sx * TEXELS_PER_SQUARE * board.texel_m, sy * TEXELS_PER_SQUARE * board.texel_m
        f_px = self.cameras_f(x)
        if bounds is not None:
            outline = np.array([[0.0, 0.0, 0.0], [width_m, 0.0, 0.0], [width_m, height_m, 0.0], [0.0, height_m, 0.0]])
            window = bounds.window(outline @ T_camera_board[:3, :3].T + T_camera_board[:3, 3])
            if window is None:
                return  # out of view
            x, y, image, depth = x[window], y[window], image[window], depth[window]  # views: painted in place
        H = np.column_stack([T_camera_board[:3, 0], T_camera_board[:3, 1], T_camera_board[:3, 3]])
        G = np.linalg.inv(H).astype(np.float32)  # normalised image coordinates -> board plane (homogeneous)
        wgt = G[2, 0] * x + G[2, 1] * y + G[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = 1.0 / wgt  # depth of the plane along each ray (negative: behind the camera)
            bx = (G[0, 0] * x + G[0, 1] * y + G[0, 2]) * z
            by = (G[1, 0] * x + G[1, 1] * y + G[1, 2]) * z
        hit = (z > 0) & (z < depth) & (bx >= 0) & (bx < width_m) & (by >= 0) & (by < height_m)
        if not hit.any():
            return
        # the texels one pixel spans at the board's centre of view picks the pyramid level (no aliasing far away)
        centre = T_camera_board[:3, :3] @ np.array([width_m / 2, height_m / 2, 0.0]) + T_camera_board[:3, 3]
        texels_per_px = centre[2] / f_px / board.texel_m
        k = int(np.clip(math.floor(math.log2(max(texels_per_px, 1.0))), 0, PYRAMID_LEVELS - 1))
        # finest texel i is centred at (i + 0.5) texel_m; pyrDown centres level k's texel j on finest texel 2^k j
        scale, half = np.float32(1.0 / (board.texel_m * 2**k)), np.float32(0.5 / 2**k)
        map_u = bx * scale - half
        map_v = by * scale - half
        map_u[~hit] = -10
        map_v[~hit] = -10
        printed = cv2.remap(board.pyramid[k], map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        image[hit] = printed[hit]
        depth[hit] = z[hit]

    @staticmethod
    def cameras_f(x: np.ndarray) -> float:
        """Focal length (px) from the rays: the spacing of neighbouring pixels' normalised x at the image centre."""
        h, w = x.shape
        return float(1.0 / (x[h // 2, w // 2 + 1] - x[h // 2, w // 2]))

    def corner_pixels(self, name: str, board: str, T_base_camera) -> tuple[np.ndarray, np.ndarray]:
        """The ids and true pixels of `board`'s corners in front of camera `name` posed at T_base_camera and
        inside its image."""
        cam, b = self.cameras[name], self.boards[board]
        T = self.board_pose(board)
        p = b.true_corners() @ T[:3, :3].T + T[:3, 3]
        in_front = (p - T_base_camera[:3, 3]) @ T_base_camera[:3, 2] > 0
        uv = cam.posed(T_base_camera).project(p)
        w, h = cam.config.resolution_px
        inside = in_front & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        return np.flatnonzero(inside), uv[inside]
