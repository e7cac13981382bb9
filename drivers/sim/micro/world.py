"""The one simulated truth that every fake reads and changes.

Static truth (drawn once from the seed within the cell file's budget): each
camera's intrinsics, pose and distortion; the robot's systematic errors; the
nozzle's offset from the rotation axis. Dynamic state: the arm, the held and the
placed spheres, a simulated clock. Calibration code never sees this module; only
the fakes, the tests and the `truth` section of a simulated report do.

Randomness that happens during a run (repeatability, sensor noise) is drawn from
a generator keyed by the run's step (`begin_step`), so a run resumed from its
persisted samples sees exactly the noise an uninterrupted run would have seen.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from geometry.transforms import rotation

from drivers.interfaces import Pose
from drivers.sim.base import WorldBase
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.optics import TrueCamera, draw_true_camera
from drivers.sim.render import Disc, NoiseBank, render


@dataclass(frozen=True)
class RobotTruth:
    """Systematic errors of the 4-axis robot: commanded xy -> actual rotation axis xy is A @ xy + axis_offset."""

    A: np.ndarray
    nozzle_offset: np.ndarray  # m, tip minus rotation axis at alpha = 0
    axis_offset: np.ndarray = field(default_factory=lambda: np.zeros(2))  # m

    def actual_xy(self, commanded_xy) -> np.ndarray:
        return np.asarray(commanded_xy, dtype=float) @ self.A.T + self.axis_offset

    def commanded_xy(self, actual_xy) -> np.ndarray:
        return np.linalg.solve(self.A, (np.asarray(actual_xy, dtype=float) - self.axis_offset).T).T

    def tip_offset(self, alpha: float) -> np.ndarray:
        return rotation([0, 0, 1], alpha)[:2, :2] @ self.nozzle_offset


@dataclass(eq=False)  # spheres are things: two are the same only if they are one
class Sphere:
    centre: np.ndarray
    radius: float


@dataclass
class _ArmState:
    commanded: Pose
    axis: np.ndarray  # actual rotation-axis point at the nozzle tip height (m)
    alpha: float  # actual rotation (rad)


@dataclass
class FrameTruth:
    camera: str
    frame_id: int
    step: int | None  # the run step it was taken in (begin_step key)
    features_px: list[np.ndarray] = field(default_factory=list)  # true projected centres


class World(WorldBase):
    def __init__(self, config: SimWorldConfig):
        super().__init__(config, config.motion.realtime_factor)
        truth_rng = np.random.default_rng([config.seed, 0])
        self.cameras: dict[str, TrueCamera] = {
            name: draw_true_camera(cam, truth_rng) for name, cam in sorted(config.cameras.items())
        }
        self._noise = {name: NoiseBank(cam.width, cam.height, config.cameras[name].noise_pct,
                                       config.cameras[name].bit_depth, np.random.default_rng([config.seed, 3, i]))
                       for i, (name, cam) in enumerate(sorted(self.cameras.items()))}
        r = config.robot
        skew = r.skew_urad * 1e-6
        self.robot = RobotTruth(
            A=np.array([[1 + r.scale_x, np.sin(skew)], [0.0, 1 + r.scale_y]]),
            nozzle_offset=np.asarray(config.nozzle.offset_um) * 1e-6,
            axis_offset=np.asarray(r.axis_offset_um) * 1e-6,
        )
        home = config.motion.home_mm
        start = Pose(home[0] * 1e-3, home[1] * 1e-3, home[2] * 1e-3, 0.0)
        self.arm = _ArmState(start, self._actual_axis(start, noise=False), 0.0)
        self.held: Sphere | None = None
        self._held_local = np.zeros(2)  # auto-centring error of the held sphere, in the nozzle's frame
        self.spheres: list[Sphere] = []
        self.dot_grids = {name: _lay_grid(g, truth_rng) for name, g in sorted(config.dot_grids.items())}
        self.fixtures_present: set[str] = set()
        self._refill_supply()

    # -- arm ---------------------------------------------------------------
    def _actual_axis(self, target: Pose, noise: bool = True) -> np.ndarray:
        r = self.config.robot
        scale = self.faults.arm_motion_scale
        if scale is not None:  # fault knob: every displacement from home is `scale` of the commanded one
            home = np.asarray(self.config.motion.home_mm[:2]) * 1e-3
            target = Pose(*(home + scale * (np.array([target.x, target.y]) - home)), target.z, target.alpha)
        xy = self.robot.actual_xy([target.x, target.y])
        z = target.z
        if noise:
            xy = xy + self.rng.normal(0.0, r.repeatability_xy_um * 1e-6, 2)
            z = z + self.rng.normal(0.0, r.repeatability_z_um * 1e-6)
        return np.array([xy[0], xy[1], z])

    def motion_time(self, start: Pose, target: Pose, speed: float | None = None) -> float:
        """Seconds a move takes at the arm's speed, or at `speed` (m/s) when slower (a manual move)."""
        m = self.config.motion
        v = m.speed_mm_s * 1e-3 if speed is None else min(speed, m.speed_mm_s * 1e-3)
        linear = _trapezoid(float(np.linalg.norm(target.xyz - start.xyz)), v, m.accel_mm_s2 * 1e-3)
        turn = _trapezoid(abs(target.alpha - start.alpha), np.radians(m.rot_speed_deg_s), np.radians(m.rot_accel_deg_s2))
        return max(linear, turn)

    def move_arm(self, target: Pose, stop: threading.Event | None = None, speed: float | None = None,
                 settle: bool = True) -> bool:
        """Move and settle (not at a via point: `settle` False); False if `stop` cut the move short (the arm then
        stands part way)."""
        start = self.arm.commanded
        duration = self.motion_time(start, target, speed)
        done = self.clock.advance(duration, stop)
        if done < 1.0:  # stopped part way along the straight line (time fraction ~ path fraction)
            f = done
            target = Pose(*(a + f * (b - a) for a, b in ((start.x, target.x), (start.y, target.y),
                                                          (start.z, target.z), (start.alpha, target.alpha))))
        with self.lock:
            alpha_noise = self.rng.normal(0.0, np.radians(self.config.robot.repeatability_alpha_mdeg * 1e-3))
            self.arm = _ArmState(target, self._actual_axis(target), target.alpha + alpha_noise)
            self._carry_held()
        if settle:
            self.clock.advance(self.config.motion.settle_s)
        return done >= 1.0

    def reported_pose(self) -> Pose:
        """What the controller reports: the commanded pose to encoder resolution (it cannot see its own errors)."""
        q = self.config.robot.quantisation_um * 1e-6
        c = self.arm.commanded
        if q > 0:
            return Pose(*(round(v / q) * q for v in (c.x, c.y, c.z)), alpha=c.alpha)
        return c

    def tip_offset(self, alpha: float) -> np.ndarray:
        """The nozzle tip's offset from the rotation axis at alpha, now (a nozzle drift changes it)."""
        offset = self.robot.tip_offset(alpha)
        drift = self.config.drift
        if drift.in_force(drift.nozzle, self.clock.now()):
            offset = offset + rotation([0, 0, 1], alpha)[:2, :2] @ (np.asarray(drift.nozzle.offset_change_um) * 1e-6)
        return offset

    def nozzle_tip(self) -> np.ndarray:
        offset = self.tip_offset(self.arm.alpha)
        return self.arm.axis + np.array([offset[0], offset[1], 0.0])

    # -- gripper -----------------------------------------------------------
    def add_sphere(self, x: float, y: float, z_surface: float, diameter: float | None = None) -> Sphere:
        """A sphere lying on a surface at height z_surface (its centre one radius above)."""
        s = self.config.spheres
        d = diameter if diameter is not None else s.diameter_mm * 1e-3 + self.rng.uniform(-1, 1) * s.tolerance_mm * 1e-3
        sphere = Sphere(np.array([x, y, z_surface + d / 2]), d / 2)
        self.spheres.append(sphere)
        return sphere

    def _refill_supply(self) -> None:
        supply = self.config.supply
        if supply is None:
            return
        x, y = (v * 1e-3 for v in supply.position_mm)
        if not any(np.hypot(s.centre[0] - x, s.centre[1] - y) < 0.5e-3 for s in self.spheres):
            self.add_sphere(x, y, supply.surface_z_mm * 1e-3)

    def set_fixture(self, name: str, present: bool) -> None:
        if name not in self.dot_grids:
            raise KeyError(f"no fixture {name!r} in the simulated world (defined: {', '.join(self.dot_grids) or 'none'})")
        (self.fixtures_present.add if present else self.fixtures_present.discard)(name)

    def grip(self) -> bool:
        """Vacuum on: pick the sphere right under the tip, auto-centred with a small error."""
        with self.lock:
            if self.held is not None:
                return True
            tip = self.nozzle_tip()
            reach = self.config.nozzle.outer_diameter_um * 1e-6
            press = self.config.nozzle.compliance_mm * 1e-3
            for sphere in self.spheres:
                top = sphere.centre[2] + sphere.radius
                # touching (within 50 µm) or pressing on it, which the nozzle's spring mount allows
                if np.hypot(*(sphere.centre[:2] - tip[:2])) < reach and top - press <= tip[2] <= top + 50e-6:
                    self.spheres.remove(sphere)
                    self.held = sphere
                    self._carry_held(centring=True)
                    self._refill_supply()
                    return True
            return False

    def release(self) -> None:
        """Vacuum off: the sphere comes to rest on the floor below, shifted a little by the contact."""
        with self.lock:
            if self.held is not None:
                sphere, self.held = self.held, None
                shift = self.rng.normal(0.0, self.config.spheres.placement_sigma_um * 1e-6, 2)
                floor = self.config.floor_z_mm * 1e-3
                sphere.centre = np.array([*(sphere.centre[:2] + shift), floor + sphere.radius])
                self.spheres.append(sphere)

    @property
    def held_offset(self) -> np.ndarray:
        """Where the held sphere's centre sits off the nozzle's now: it is held by vacuum, so it turns with the tool."""
        return rotation([0, 0, 1], self.arm.alpha)[:2, :2] @ self._held_local

    def _carry_held(self, centring: bool = False) -> None:
        if self.held is None:
            return
        if centring:
            drawn = self.rng.normal(0.0, self.config.spheres.centring_sigma_um * 1e-6, 2)
            self._held_local = rotation([0, 0, 1], -self.arm.alpha)[:2, :2] @ drawn
        tip = self.nozzle_tip()
        x, y = tip[:2] + self.held_offset
        self.held.centre = np.array([x, y, tip[2] - self.held.radius])

    # -- cameras -----------------------------------------------------------
    def camera_now(self, name: str) -> TrueCamera:
        """The true camera, moved by its drift once that is in force, and with the arm if it is mounted on it."""
        cam = self.cameras[name]
        drift = self.config.drift
        knob = drift.cameras.get(name)
        if drift.in_force(knob, self.clock.now()):
            cam = _drifted(cam, knob, self.config.cameras[name])
        if not self.config.cameras[name].mounted_on_arm:
            return cam
        turn = rotation([0, 0, 1], self.arm.alpha)
        return cam.moved(self.arm.axis + turn @ cam.C, turn @ cam.R_cw)

    def features(self) -> list[Disc]:
        """Everything a camera can see: the nozzle's end face, held and placed spheres."""
        n = self.config.nozzle
        if self.held is None:
            discs = [Disc(self.nozzle_tip(), n.outer_diameter_um * 0.5e-6, n.inner_diameter_um * 0.5e-6)]
        else:  # the held sphere hides the nozzle's end face
            discs = [Disc(self.held.centre.copy(), self.held.radius)]
        discs += [Disc(s.centre.copy(), s.radius) for s in self.spheres]
        for name in sorted(self.fixtures_present):
            discs += self.dot_grids[name].discs()
        return discs

    def capture(self, name: str, frame_id: int) -> np.ndarray:
        cfg = self.config.cameras[name]
        with self.lock:
            camera = self.camera_now(name)
            discs = [d for d in self.features() if not (cfg.mounted_on_arm and d.inner_radius > 0)]
            image = render(camera, cfg, discs, self.rng, self._noise[name])
            truth = FrameTruth(name, frame_id, self.step, [camera.project(d.centre)[0] for d in discs])
            self.frame_truth[(name, frame_id)] = truth
        self.clock.advance((cfg.exposure_ms + cfg.readout_ms) * 1e-3)
        return image


def _drifted(cam: TrueCamera, knob, cfg) -> TrueCamera:
    """The camera moved so that what it sees at p it used to see at T(p) = c + (1 + s) R(theta) (p - c) + t
    (c: its view centre): its old calibration now reads p as T(p). A pinhole's view does not change when the
    scene and the camera move by one similarity, so the camera moved by T's inverse does exactly that."""
    c = np.array([cfg.centre_mm[0] * 1e-3, cfg.centre_mm[1] * 1e-3, cfg.focus_z_mm * 1e-3])
    t = np.array([*knob.map_shift_um, 0.0]) * 1e-6
    turn = rotation([0, 0, 1], knob.rotation_urad * 1e-6)
    scale = 1.0 + knob.scale_ppm * 1e-6
    centre = c + turn.T @ (cam.C - c - t) / scale  # T^-1(C)
    return cam.moved(centre, turn.T @ cam.R_cw)


@dataclass(frozen=True)
class LaidGrid:
    """A dot grid as the operator laid it: true dot centres (with their pitch errors)."""

    config: object
    dots: np.ndarray  # (rows * cols, 3) m, row-major from the first row
    centre: np.ndarray

    def discs(self) -> list[Disc]:
        g = self.config
        extent = np.hypot(g.cols, g.rows) * g.pitch_mm * 1e-3
        plate = Disc(self.centre, extent, 0.0, level=g.plate_level)
        dot = (g.dot_level - g.plate_level)
        return [plate] + [Disc(d, g.dot_diameter_mm * 0.5e-3, 0.0, contrast=dot) for d in self.dots]


def _lay_grid(g, rng: np.random.Generator) -> LaidGrid:
    turn = np.radians(rng.uniform(-g.rotation_deg, g.rotation_deg))
    centre = np.array([*(np.asarray(g.centre_mm) * 1e-3 + rng.uniform(-1, 1, 2) * g.placement_mm * 1e-3),
                       g.z_mm * 1e-3])
    jj, ii = np.meshgrid(np.arange(g.cols), np.arange(g.rows))
    local = np.column_stack([(jj.ravel() - (g.cols - 1) / 2), (ii.ravel() - (g.rows - 1) / 2)]) * g.pitch_mm * 1e-3
    local += rng.uniform(-1, 1, local.shape) * g.pitch_tolerance_um * 1e-6
    c, s = np.cos(turn), np.sin(turn)
    xy = local @ np.array([[c, s], [-s, c]]) + centre[:2]
    return LaidGrid(g, np.column_stack([xy, np.full(len(xy), centre[2])]), centre)


def _trapezoid(distance: float, vmax: float, amax: float) -> float:
    """Time of a rest-to-rest move with a trapezoidal (or triangular) speed profile."""
    if distance <= 0:
        return 0.0
    if distance < vmax * vmax / amax:
        return 2.0 * np.sqrt(distance / amax)
    return distance / vmax + vmax / amax
