"""The `sim:` section of a six-axis CSM cell (`world: irb120-csm`): hidden-error budgets, cameras, fixture.

Units are in the key names. The true robot and cameras are drawn within these budgets from the seed,
so every seed is another plausible cell that CSM has to cope with without calibrating it.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from drivers.sim.base import SimFaults, SimServer, Strict, serve_only

Triple = tuple[float, float, float]


class SixAxisRobot(Strict):
    """How far the true IRB 120 is from its catalogue DH table, and how well it repeats."""

    dh_length_error_mm: float = Field(0.5, ge=0, le=20, description="uniform +/- error of every DH d and a")
    joint_offset_error_deg: float = Field(0.05, ge=0, le=5, description="uniform +/- error of every joint zero")
    repeatability_mm: float = Field(0.01, ge=0, le=5, description="Gaussian sigma per axis of the reached point")
    encoder_resolution_deg: float = Field(1e-4, ge=0, le=0.1, description="resolution of reported joint angles")
    home_deg: tuple[float, float, float, float, float, float] = Field((0, 0, 0, 0, 90, 0),
                                                                      description="joints at start-up")
    speed_deg_s: float = Field(60.0, gt=0, le=1000, description="joint speed of moves (simulated time)")
    settle_s: float = Field(0.2, ge=0, le=10)


class SixAxisFixture(Strict):
    """The end-effector fixture of seed Fig. 3: printed circles on a plate, in the seventh DH frame.

    The plate lies in the frame-7 x-y plane facing -z7 (up when the tool points down). The black
    circles carry a white centre of 1/3 their diameter and the white circle a black one, so a string
    of pixels through a centre reads dark:light:dark (or light:dark:light) as d:1:d."""

    d7_mm: float = Field(40.0, ge=-500, le=500, description="DH d of the seventh frame (along the flange axis)")
    a7_mm: float = Field(0.0, ge=-500, le=500, description="DH a of the seventh frame")
    white_mm: Triple = Field((0.0, 0.0, 0.0), description="white circle centre in frame 7")
    black_mm: tuple[Triple, Triple, Triple] = Field(((40.0, 0.0, 0.0), (55.0, 15.0, 0.0), (55.0, -15.0, 0.0)),
                                                    description="black circle centres in frame 7")
    diameter_mm: float = Field(14.0, gt=0, le=200, description="outer diameter of every circle")
    plate_diameter_mm: float = Field(110.0, gt=0, le=1000)
    plate_centre_mm: Triple = Field((30.0, 0.0, 0.0))
    plate_level: float = Field(0.55, ge=0, le=1, description="plate grey, fraction of full scale")
    dark_level: float = Field(0.06, ge=0, le=1)
    light_level: float = Field(0.92, ge=0, le=1)


class SixAxisCamera(Strict):
    """A fixed perspective camera looking at the workspace centre from `distance_mm` away."""

    resolution_px: tuple[int, int] = Field((1600, 1200), description="(width, height)")
    azimuth_deg: float = Field(..., ge=-360, le=360, description="direction of the camera from the workspace centre")
    elevation_deg: float = Field(45.0, ge=0, le=90)
    distance_mm: float = Field(1200.0, gt=100, le=10000)
    field_mm: float = Field(600.0, gt=10, le=5000, description="extent of the image height at the aim point")
    aim_error_deg: float = Field(1.0, ge=0, le=20, description="uniform +/- error of pan, tilt and roll")
    principal_offset_px: float = Field(10.0, ge=0, le=200, description="max principal point offset from centre")
    corner_distortion_px: tuple[float, float] = Field((4.0, 10.0), description="radial displacement at the corners")
    tangential_fraction: float = Field(0.1, ge=0, le=1, description="tangential part relative to the radial one")
    noise_pct: float = Field(1.0, ge=0, le=20, description="sensor noise sigma, % of full scale")
    blur_px: float = Field(0.8, ge=0, le=10, description="Gaussian blur sigma")
    background: float = Field(0.15, ge=0, le=1)
    exposure_ms: float = Field(10.0, gt=0, le=10000)
    readout_ms: float = Field(40.0, ge=0, le=10000)


class SixAxisWorldConfig(Strict):
    """An ABB IRB 120 with a feature fixture, watched by two uncalibrated cameras (seed 002 section II.A)."""

    world: Literal["irb120-csm"] = Field(..., description="which kind of simulated world")
    seed: int = Field(1, ge=0, description="the simulation seed: draws the hidden truth within this budget (cellctl run "
                      "--seed N overrides it for one run)")
    robot: SixAxisRobot = SixAxisRobot()
    fixture: SixAxisFixture = SixAxisFixture()
    workspace_centre_mm: Triple = Field((350.0, 0.0, 200.0), description="where both cameras aim (robot frame)")
    cameras: dict[str, SixAxisCamera] = Field(..., min_length=1)
    faults: SimFaults = SimFaults()
    servers: list[SimServer] = Field(default_factory=list, description="protocol simulators started with the cell "
                                     "(abb only: the IRB 120's controller link)")

    @model_validator(mode="after")
    def _abb_only(self):
        serve_only(self.servers, "abb", "the IRB 120 cell (no gripper, a six-axis ABB arm)")
        return self

    @model_validator(mode="after")
    def _levels(self):
        f = self.fixture
        if not f.dark_level < f.plate_level < f.light_level:
            raise ValueError("fixture: need dark_level < plate_level < light_level for the d:1:d marks")
        return self
