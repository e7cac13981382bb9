"""The `sim:` section of a VR cell file (`world: vr`): layout, error budgets, rendering.

Nominal layout (what the cell's engineer knows, and what the VR routines start
from): the receptacle's pose, the point both cameras look at, the cameras'
directions, distances and fields of view. Hidden truth drawn from the seed within
the budgets: each camera's placement, pointing and focal length, the receptacle's
pose, the grasp of the ORU and the arm's small systematic error, the objects'
manufacturing deviations from their models.

Camera directions: the side camera sits at `side_azimuth_deg` (from +x toward +y)
and `side_elevation_deg` seen from the look-at point; the overhead camera's
direction is the side camera's turned by `inter_camera_angle_deg` toward "up and a
little in front" (geometry.camera_direction), so the angle between the two optical
axes is the inter-camera angle and at 90 deg the overhead camera looks down.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from drivers.sim.base import SimFaults, Strict

Triple = tuple[float, float, float]


class VrCamera(Strict):
    resolution_px: tuple[int, int] = Field((640, 480), description="(width, height)")
    distance_m: float = Field(..., gt=0.2, le=50, description="from the look-at point")
    vfov_deg: float = Field(..., gt=0.5, le=120, description="vertical field of view (nominal lens)")
    placement_mm: float = Field(40.0, ge=0, le=1000, description="+/- error of the true position per axis")
    pointing_deg: float = Field(1.0, ge=0, le=20, description="+/- error of the true orientation per axis")
    focal_pct: float = Field(4.0, ge=0, le=50, description="+/- error of the true focal length")
    noise_pct: float = Field(1.0, ge=0, le=20, description="sensor noise sigma, % of full scale")
    blur_px: float = Field(0.8, ge=0, le=10, description="Gaussian blur sigma")
    exposure_ms: float = Field(10.0, gt=0, le=10000, description="reported with each frame")


class VrRobot(Strict):
    grasp_error_mm: float = Field(3.0, ge=0, le=100, description="+/- error per axis of where the ORU sits in the gripper")
    grasp_error_deg: float = Field(0.05, ge=0, le=20)
    arm_error_mm: float = Field(2.0, ge=0, le=100, description="+/- systematic error of the arm's positioning per axis")
    arm_error_deg: float = Field(0.02, ge=0, le=20)
    repeatability_mm: float = Field(0.1, ge=0, le=10, description="Gaussian sigma per axis and move")
    repeatability_deg: float = Field(0.02, ge=0, le=5)
    gripper_in: tuple[float, float, float, float, float, float] | None = Field(
        None, description="wrist and gripper as a box (x0, x1, y0, y1, z0, z1) in the "
        "tool frame, on the ORU's back face; null: none")
    speed_mm_s: float = Field(50.0, gt=0, le=5000)
    settle_s: float = Field(0.5, ge=0, le=10)


class VrRendering(Strict):
    background: float = Field(0.05, ge=0, le=1, description="background level, fraction of full scale")
    light_dir: Triple = Field((0.3, 0.8, 0.5), description="direction toward the key light (world)")
    fill_dir: Triple = Field((-0.8, 0.2, -0.4), description="direction toward the fill light, so that faces turned "
                             "away from the key light still differ")
    fill: float = Field(0.35, ge=0, le=1, description="fill light strength relative to the key light")
    ambient: float = Field(0.25, ge=0, le=1)
    oru_albedo: float = Field(0.85, ge=0, le=1)
    receptacle_albedo: float = Field(0.7, ge=0, le=1)
    gripper_albedo: float = Field(0.45, ge=0, le=1)
    supersample: int = Field(2, ge=1, le=4, description="anti-aliasing: samples per pixel side")
    blooming: bool = Field(False, description="over-expose the brightest faces; their light bleeds over the edges")
    bloom_gain: float = Field(1.6, ge=1, le=5, description="exposure gain of faces brighter than 0.6 when blooming")
    bloom_px: float = Field(2.0, ge=0, le=10, description="how far saturated light bleeds")


class VrOperatorSim(Strict):
    click_sigma_px: float = Field(2.0, ge=0, le=20, description="error of each clicked image point")
    align_error_in: float = Field(0.01, ge=0, le=2, description="hand-alignment error sigma per axis (reference)")
    align_error_deg: float = Field(0.05, ge=0, le=10)
    seconds_per_click: float = Field(4.0, ge=0, le=600)


class VrWorldConfig(Strict):
    """The ORU insertion cell of seed 000 section V."""

    world: Literal["vr"] = Field("vr", description="which kind of simulated world")
    seed: int = Field(1, ge=0, description="the simulation seed: draws the hidden truth within this budget (cellctl run "
                      "--seed N overrides it for one run)")
    oru_model: str = Field("models/oru.json", description="edge model file (relative: to config/)")
    receptacle_model: str = Field("models/receptacle.json")
    model_tolerance_mm: float = Field(0.35, ge=0, le=20, description="sigma of each real vertex off its model")
    receptacle_in: Triple = Field((0.0, 0.0, 0.0), description="nominal receptacle position (world = robot base)")
    receptacle_yaw_deg: float = Field(0.0, ge=-180, le=180)
    receptacle_error_in: float = Field(1.0, ge=0, le=20, description="+/- error of its true position per axis")
    receptacle_error_deg: float = Field(2.0, ge=0, le=30)
    look_at_in: Triple = Field((0.0, 10.0, 0.0), description="where both cameras point (nominal)")
    side_azimuth_deg: float = Field(35.0, ge=-180, le=180)
    side_elevation_deg: float = Field(15.0, ge=-60, le=80)
    inter_camera_angle_deg: float = Field(50.0, gt=0, le=120)
    side: VrCamera = VrCamera(distance_m=7.5, vfov_deg=5.3)
    top: VrCamera = VrCamera(distance_m=3.5, vfov_deg=12.0, pointing_deg=0.7)
    start_distance_in: float = Field(20.0, ge=0, le=100, description="ORU front to receptacle entrance at start")
    robot: VrRobot = VrRobot()
    rendering: VrRendering = VrRendering()
    operator: VrOperatorSim = VrOperatorSim()
    faults: SimFaults = SimFaults()

    @property
    def cameras(self) -> dict[str, VrCamera]:
        return {"side": self.side, "top": self.top}
