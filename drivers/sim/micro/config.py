"""The `sim:` section of a cell file: the simulated world's error budget.

Every knob is named with its unit. The hidden truth (camera tilts, distortion,
principal points) is drawn from these budgets with the world's seed, so a seed
picks one plausible cell that calibration has to discover.
"""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field, ValidationError, model_validator

from drivers.sim.base import SimFaults, SimServer, Strict

__all__ = ["SimFaults", "SimServer"]  # shared by every world; kept importable from here

Pair = tuple[float, float]


def _check_range(name: str, pair: Pair) -> None:
    if pair[0] > pair[1]:
        raise ValueError(f"{name}: lower bound {pair[0]} is above upper bound {pair[1]}")


class SimRobot(Strict):
    """A 4-axis (x, y, z, alpha) precision robot, seed 001 section 4."""

    repeatability_xy_um: float = Field(1.7, ge=0, le=100, description="Gaussian sigma per horizontal axis")
    repeatability_z_um: float = Field(3.3, ge=0, le=100)
    repeatability_alpha_mdeg: float = Field(0.0, ge=0, le=100)
    quantisation_um: float = Field(0.1, ge=0, le=10, description="resolution of reported positions")
    scale_x: float = Field(1e-4, ge=-1e-2, le=1e-2, description="systematic x scale error")
    scale_y: float = Field(-0.8e-4, ge=-1e-2, le=1e-2)
    skew_urad: float = Field(50.0, ge=-1e4, le=1e4, description="non-orthogonality of the x and y axes")
    axis_offset_um: Pair = Field((-0.6, 213.7), description="rotation axis minus reported position (seed Table III c*)")


class SimNozzle(Strict):
    inner_diameter_um: float = Field(260.0, gt=0, le=5000)
    outer_diameter_um: float = Field(460.0, gt=0, le=10000)
    offset_um: Pair = Field((-68.7, 137.2), description="tip offset from the rotation axis at alpha=0 (seed Table VII)")
    compliance_mm: float = Field(0.5, ge=0, le=10, description="how far the spring-mounted nozzle can press on a part")

    @model_validator(mode="after")
    def _inner_inside_outer(self):
        if self.inner_diameter_um >= self.outer_diameter_um:
            raise ValueError("nozzle.inner_diameter_um must be below nozzle.outer_diameter_um")
        return self


class SimSpheres(Strict):
    diameter_mm: float = Field(1.0, gt=0, le=10)
    tolerance_mm: float = Field(0.2, ge=0, le=5, description="uniform +/- spread of the diameter")
    centring_sigma_um: float = Field(3.0, ge=0, le=100, description="auto-centring error on the nozzle")
    placement_sigma_um: float = Field(5.0, ge=0, le=500, description="shift when a released sphere meets the substrate")


class SimDistortion(Strict):
    """Brown-Conrady lens distortion drawn to displace the image corners by a chosen amount."""

    corner_displacement_px: Pair = Field((3.0, 8.0), description="range of the radial displacement at the corners")
    tangential_fraction: Pair = Field((0.05, 0.2), description="tangential part relative to the radial one")
    k2_fraction: Pair = Field((-0.3, 0.3), description="share of the corner displacement carried by k2 (r^4)")


class SimCamera(Strict):
    resolution_px: tuple[int, int] = Field(..., description="(width, height)")
    pixel_um: float = Field(..., gt=0, le=1000, description="spatial resolution at the focal plane")
    view: Literal["up", "down"] = Field("down", description="'up': from below through the glass (area1)")
    mirror: bool = Field(False, description="image seen through a mirror (left-right flipped)")
    mounted_on_arm: bool = False
    centre_mm: Pair = Field((0.0, 0.0), description="where the optical axis meets the focal plane (robot frame; "
                            "for a camera on the arm, relative to the rotation axis at alpha=0)")
    focus_z_mm: float = Field(0.0, description="height of the focal plane (on the arm: relative to the nozzle tip)")
    working_distance_mm: float = Field(200.0, gt=1, le=5000)
    yaw_deg: Pair = Field((-5.0, 5.0), description="range of the rotation about the optical axis")
    tilt_deg: Pair = Field((1.0, 2.0), description="range of the optical axis tilt from vertical")
    principal_offset_px: float = Field(5.0, ge=0, le=200, description="max principal point offset from centre")
    distortion: SimDistortion = SimDistortion()
    noise_pct: float = Field(1.0, ge=0, le=20, description="sensor noise sigma, % of full scale")
    blur_px: float = Field(1.0, ge=0, le=10, description="Gaussian blur sigma in focus")
    depth_of_field_mm: float = Field(1.0, gt=0, le=100)
    background: float = Field(0.08, ge=0, le=1, description="background level, fraction of full scale")
    feature_level: float = Field(0.8, ge=0, le=1, description="lit feature level, fraction of full scale")
    bit_depth: Literal[8, 16] = 8
    exposure_ms: float = Field(10.0, gt=0, le=10000)
    readout_ms: float = Field(60.0, ge=0, le=10000, description="transfer time per frame")

    @model_validator(mode="after")
    def _ranges(self):
        _check_range("tilt_deg", self.tilt_deg)
        _check_range("yaw_deg", self.yaw_deg)
        return self


class SimMotion(Strict):
    speed_mm_s: float = Field(100.0, gt=0, le=5000)
    accel_mm_s2: float = Field(1000.0, gt=0, le=1e5)
    rot_speed_deg_s: float = Field(360.0, gt=0, le=1e4)
    rot_accel_deg_s2: float = Field(3600.0, gt=0, le=1e6)
    settle_s: float = Field(0.25, ge=0, le=10)
    realtime_factor: float = Field(0.0, ge=0, le=10, description="0: moves return at once; 1: take their real time")
    home_mm: tuple[float, float, float] = (0.0, 0.0, 20.0)


class SimDotGrid(Strict):
    """A printed calibration grid of dark dots on a white plate (seed 001 sections 6.1.1, 6.2.1).

    Placed and removed by the (simulated) operator; where it lands is drawn from the seed."""

    rows: int = Field(7, ge=2, le=100)
    cols: int = Field(8, ge=2, le=100)
    pitch_mm: float = Field(2.0, gt=0, le=100)
    dot_diameter_mm: float = Field(1.0, gt=0, le=50)
    pitch_tolerance_um: float = Field(5.0, ge=0, le=1000, description="uniform +/- error of each dot position")
    centre_mm: Pair = Field(..., description="where the operator lays it, roughly (robot frame)")
    z_mm: float = Field(..., description="height of the printed plane")
    placement_mm: float = Field(0.3, ge=0, le=50, description="+/- error of where the operator lays it")
    rotation_deg: float = Field(2.0, ge=0, le=180, description="+/- error of its orientation")
    plate_level: float = Field(0.8, ge=0, le=1, description="white plate, fraction of full scale")
    dot_level: float = Field(0.1, ge=0, le=1)


class SimSupply(Strict):
    """A feeder that presents one sphere at a fixed place, refilled whenever one is taken."""

    position_mm: Pair
    surface_z_mm: float = 0.0


class CameraDrift(Strict):
    """A camera that moved after its calibration: its old map now reads a point at p as T(p), T a similarity
    about the camera's view centre (`centre_mm`, for a camera on the arm in the arm's frame at alpha = 0)."""

    map_shift_um: Pair = Field((0.0, 0.0), description="T's translation (x, y)")
    rotation_urad: float = Field(0.0, ge=-1e5, le=1e5, description="T's rotation about the view centre")
    scale_ppm: float = Field(0.0, ge=-1e5, le=1e5, description="T's scale change about the view centre")
    from_cell_time_s: float | None = Field(None, ge=0, description="in force from this cell time (default: the "
                                           "drift section's, else from the start)")


class NozzleDrift(Strict):
    """A nozzle replaced or bent: its tip offset from the rotation axis changed (at alpha = 0)."""

    offset_change_um: Pair = Field((0.0, 0.0), description="added to nozzle.offset_um")
    from_cell_time_s: float | None = Field(None, ge=0)


class SimDrift(Strict):
    """What changed in the cell since it was calibrated (`sim.drift`): keys are camera names, `nozzle` and
    `from_cell_time_s` (when all of them come into force; default: from the start of the run). The world moves
    the camera or changes the nozzle itself; no calibration is touched, so a check sees what a real cell shows."""

    model_config = ConfigDict(extra="allow", frozen=True)

    from_cell_time_s: float = Field(0.0, ge=0)
    nozzle: NozzleDrift | None = None

    @model_validator(mode="before")
    @classmethod
    def _cameras(cls, data):
        if not isinstance(data, dict):
            return data
        known = set(cls.model_fields)
        return {k: (v if k in known else _camera_drift(k, v)) for k, v in data.items()}

    @property
    def cameras(self) -> dict[str, CameraDrift]:
        return dict(self.model_extra or {})

    def in_force(self, knob: CameraDrift | NozzleDrift | None, now_s: float) -> bool:
        if knob is None:
            return False
        start = knob.from_cell_time_s if knob.from_cell_time_s is not None else self.from_cell_time_s
        return now_s >= start


def _camera_drift(name: str, value) -> CameraDrift:
    """One camera's entry of `sim.drift`, its errors named by camera and knob (it sits outside the declared fields)."""
    if isinstance(value, CameraDrift):
        return value
    try:
        return CameraDrift.model_validate({} if value is None else value)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'value'}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"{name}: {problems} (knobs: {', '.join(CameraDrift.model_fields)})") from None


class SimWorldConfig(Strict):
    """The micro work-cell of seed 001: a 4-axis precision robot, a vacuum nozzle, spheres, three cameras."""

    world: Literal["micro-cell"] = Field("micro-cell", description="which kind of simulated world")
    seed: int = Field(1, ge=0, description="the simulation seed: draws the hidden truth within this budget (cellctl run "
                      "--seed N overrides it for one run)")
    robot: SimRobot = SimRobot()
    motion: SimMotion = SimMotion()
    nozzle: SimNozzle = SimNozzle()
    spheres: SimSpheres = SimSpheres()
    cameras: dict[str, SimCamera] = Field(default_factory=dict)
    dot_grids: dict[str, SimDotGrid] = Field(default_factory=dict)
    supply: SimSupply | None = None
    floor_z_mm: float = Field(0.0, description="height of the working surfaces a released sphere comes to rest on")
    faults: SimFaults = SimFaults()
    drift: SimDrift = SimDrift()
    servers: list[SimServer] = Field(default_factory=list, description="protocol simulators started with the cell")

    @model_validator(mode="after")
    def _drift_of_known_cameras(self):
        unknown = sorted(set(self.drift.cameras) - set(self.cameras))
        if unknown:
            raise ValueError(f"drift: no camera {', '.join(map(repr, unknown))} in sim.cameras "
                             f"(allowed keys: {', '.join(['from_cell_time_s', 'nozzle', *sorted(self.cameras)])})")
        return self
