"""The `sim:` section of the hand-eye cell (`world: ur5e-handeye`): the arm's error budget, the cameras, the boards.

Units are in the key names. Every hidden quantity (the arm's DH errors, where each camera really is and what its
lens does, where each board really lies and how it was printed) is drawn within these budgets from the seed, so
every seed is another plausible cell the calibration has to find.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from drivers.sim.base import SimFaults, SimServer, Strict, serve_only
from drivers.sim.ur5e_handeye.parts import HandEyeGripper, HandEyePart

Triple = tuple[float, float, float]
Range = tuple[float, float]


class UrRobot(Strict):
    """How far the true UR5e is from its published DH table (geometry/ur.py), and how well it repeats. The
    default is a factory-calibrated arm; an uncalibrated one is off by about ten times as much."""

    dh_length_error_mm: float = Field(0.1, ge=0, le=20, description="uniform +/- error of every DH a and d")
    joint_offset_error_deg: float = Field(0.01, ge=0, le=5, description="uniform +/- error of every joint zero")
    repeatability_mm: float = Field(0.01, ge=0, le=5, description="Gaussian sigma per axis of the reached flange")
    encoder_resolution_deg: float = Field(1e-4, ge=0, le=0.1, description="resolution of reported joint angles")
    home_deg: tuple[float, float, float, float, float, float] = Field(
        (0.0, -90.0, 90.0, -90.0, -90.0, 0.0), description="joints at start-up (tool pointing down)")
    joint_limits_deg: tuple[Range, Range, Range, Range, Range, Range] = Field(
        ((-360.0, 360.0),) * 6, description="per joint (min, max); the UR5e turns every joint +/-360 deg")
    reach_mm: float = Field(850.0, gt=0, le=2000, description="the flange never goes farther from the shoulder")
    speed_deg_s: float = Field(60.0, gt=0, le=1000, description="joint speed of moves (simulated time)")
    settle_s: float = Field(0.3, ge=0, le=10)


class HandEyeCamera(Strict):
    """A camera on the flange (`mount: flange`, the wrist camera) or fixed in the cell (`mount: fixed`).

    Its nominal pose is what the engineer would say of it (the drawing of the bracket, where the stand was
    put); the true one is off by amounts drawn within `pose_error_mm` / `pose_error_deg`."""

    mount: Literal["flange", "fixed"]
    resolution_px: tuple[int, int] = Field((2448, 2048), description="(width, height); 5 MP by default")
    pixel_um: float = Field(3.45, gt=0, le=50)
    focal_mm: float = Field(8.0, gt=0, le=200, description="lens focal length (nominal)")
    focal_error_pct: float = Field(1.0, ge=0, le=20, description="uniform +/- error of the true focal length")
    principal_offset_px: float = Field(15.0, ge=0, le=500, description="max principal point offset from centre")
    corner_distortion_px: Range = Field((5.0, 20.0), description="radial displacement at the image corners")
    tangential_fraction: float = Field(0.1, ge=0, le=1, description="tangential part relative to the radial one")
    position_mm: Triple = Field(..., description="flange: in the flange frame; fixed: in the base frame")
    look_at_mm: Triple | None = Field(None, description="fixed: the point it aims at (base frame)")
    roll_deg: float = Field(0.0, ge=-180, le=180, description="flange: turn of the image about the flange axis")
    pose_error_mm: float = Field(2.0, ge=0, le=100, description="uniform +/- error of the true position per axis")
    pose_error_deg: float = Field(1.0, ge=0, le=30, description="uniform +/- error of the true orientation per axis")
    noise_pct: float = Field(1.0, ge=0, le=20, description="sensor noise sigma, % of full scale")
    blur_px: float = Field(0.7, ge=0, le=10, description="Gaussian blur sigma (the lens and the focus)")
    background: float = Field(0.35, ge=0, le=1, description="grey level of what is not a board")
    exposure_ms: float = Field(10.0, gt=0, le=10000)
    readout_ms: float = Field(60.0, ge=0, le=10000)
    bit_depth: Literal[8, 16] = 8

    @model_validator(mode="after")
    def _aim(self):
        if (self.mount == "fixed") != (self.look_at_mm is not None):
            raise ValueError("look_at_mm: a fixed camera needs the point it aims at; a flange camera looks along "
                             "the flange axis and takes none")
        return self


class HandEyeBoard(Strict):
    """A printed ChArUco board (cv2.aruco), on the table (`mount: table`, pose in the base frame) or on a bracket on
    the flange (`mount: flange`, pose in the flange frame). The pose is the board's origin (its first chessboard
    corner's outer square corner, OpenCV's convention) and a turn about its normal; the true pose is off by amounts
    drawn within the error budgets, the printing by up to `scale_error_pct`."""

    mount: Literal["table", "flange"]
    squares: tuple[int, int] = Field((12, 9), description="(x, y) chessboard squares")
    square_mm: float = Field(20.0, gt=0, le=500)
    marker_mm: float = Field(15.0, gt=0, le=500)
    dictionary: Literal["DICT_4X4_250", "DICT_5X5_250", "DICT_6X6_250"] = "DICT_5X5_250"
    first_marker: int = Field(0, ge=0, le=249, description="id of its first marker (two boards in one view need "
                              "ids of their own)")
    position_mm: Triple = Field(..., description="the board origin (table: base frame; flange: flange frame)")
    rotation_deg: Triple = Field((0.0, 0.0, 0.0), description="xyz Euler angles of the board frame (its z: the "
                                 "normal out of the back of the print, OpenCV's board convention)")
    pose_error_mm: float = Field(5.0, ge=0, le=200)
    pose_error_deg: float = Field(2.0, ge=0, le=30)
    scale_error_pct: float = Field(0.05, ge=0, le=5, description="uniform +/- printing scale error")
    white: float = Field(0.85, ge=0, le=1)
    black: float = Field(0.08, ge=0, le=1)

    @model_validator(mode="after")
    def _marker(self):
        if not self.marker_mm < self.square_mm:
            raise ValueError(f"marker_mm {self.marker_mm} must be smaller than square_mm {self.square_mm}")
        if not self.black < self.white:
            raise ValueError("black must be darker than white")
        markers = self.squares[0] * self.squares[1] // 2
        if self.first_marker + markers > 250:
            raise ValueError(f"first_marker {self.first_marker}: its {markers} markers run past the dictionary's 250")
        return self


class MountDrift(Strict):
    """A camera bumped, or a board moved, after its calibration (`sim.drift.NAME`): its true mount (a flange camera's
    or the flange board's in the flange frame, a fixed camera's or the table board's in the base frame) moved by
    `translation_mm` and turned by the rotation vector `rotation_deg` about its own origin (a camera: its optical
    centre), both along that parent frame's axes. No calibration is touched: a check sees what a real cell shows."""

    translation_mm: Triple = Field((0.0, 0.0, 0.0), description="the move (x, y, z) in the parent frame")
    rotation_deg: Triple = Field((0.0, 0.0, 0.0), description="the turn as a rotation vector (x, y, z; its length "
                                 "the angle), about the mount's own origin")
    from_cell_time_s: float | None = Field(None, ge=0, description="in force from this cell time (default: from the "
                                           "start of the run)")

    @model_validator(mode="after")
    def _small(self):
        if max(abs(v) for v in self.translation_mm) > 100:
            raise ValueError(f"translation_mm {list(self.translation_mm)}: each within +/-100 mm")
        if max(abs(v) for v in self.rotation_deg) > 30:
            raise ValueError(f"rotation_deg {list(self.rotation_deg)}: each within +/-30 deg")
        return self

    def in_force(self, now_s: float) -> bool:
        return now_s >= (self.from_cell_time_s or 0.0)


class HandEyeWorldConfig(Strict):
    """A UR5e with a wrist camera and a camera over the table, a ChArUco board on the table and one on the flange."""

    world: Literal["ur5e-handeye"] = Field(..., description="which kind of simulated world")
    seed: int = Field(1, ge=0, description="the simulation seed: draws the hidden truth within this budget (cellctl run "
                      "--seed N overrides it for one run)")
    robot: UrRobot = UrRobot()
    cameras: dict[str, HandEyeCamera] = Field(..., min_length=1)
    boards: dict[str, HandEyeBoard] = Field(..., min_length=1)
    parts: dict[str, HandEyePart] = Field(default_factory=dict, description="parts on the table (table-pick)")
    gripper: HandEyeGripper = HandEyeGripper()
    faults: SimFaults = SimFaults()
    drift: dict[str, MountDrift] = Field(default_factory=dict, description="what moved since the calibration: a "
                                         "camera's or a board's name -> its move (the knob calibration-check finds)")
    servers: list[SimServer] = Field(default_factory=list, description="protocol simulators started with the cell "
                                     "(ur: the UR5e through ur-rtde)")

    @model_validator(mode="after")
    def _servers(self):
        serve_only(self.servers, "ur", "the hand-eye cell")
        return self

    @model_validator(mode="after")
    def _one_board_each(self):
        for place in ("table", "flange"):
            on = [name for name, b in self.boards.items() if b.mount == place]
            if len(on) > 1:
                raise ValueError(f"boards: {', '.join(on)} are all on the {place}; one board per place")
        taken: dict[int, str] = {}
        for name, b in sorted(self.boards.items()):
            for i in range(b.first_marker, b.first_marker + b.squares[0] * b.squares[1] // 2):
                if i in taken and self.boards[taken[i]].dictionary == b.dictionary:
                    raise ValueError(f"boards.{name}.first_marker: marker {i} is also on board {taken[i]}; give "
                                     "each board ids of its own")
                taken[i] = name
        return self

    @model_validator(mode="after")
    def _drift_of_known_mounts(self):
        both = sorted(set(self.cameras) & set(self.boards) & set(self.drift))
        if both:
            raise ValueError(f"drift: {', '.join(both)} names both a camera and a board; rename one")
        unknown = sorted(set(self.drift) - set(self.cameras) - set(self.boards))
        if unknown:
            raise ValueError(f"drift: no camera or board {', '.join(map(repr, unknown))} (allowed keys: "
                             f"{', '.join(sorted([*self.cameras, *self.boards]))})")
        return self
