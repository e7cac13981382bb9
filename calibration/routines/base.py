"""What every routine is: plan -> collect -> fit -> verify, over the driver interfaces.

A routine is stateless. `plan` turns parameters into a deterministic list of
steps; `execute` performs one step on the devices and returns one sample (a flat
row, persisted by the orchestrator before the next step); `fit` is a pure
function from samples to a model with its statistics and its report tables, the
same function that `cellctl fit` runs on a recorded samples file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Protocol, TypedDict, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.interfaces import Arm, Camera, Gripper, Operator

from calibration.errors import CalibrationInputError, UnknownName


@dataclass(frozen=True)
class Area:
    """A working area as the cell file describes it (robot frame; the engineer's rough knowledge)."""

    name: str
    camera: str
    centre: tuple[float, float]  # m
    size: tuple[float, float]  # m, approximately the camera's field of view
    z: float  # m, tool height that puts the feature in focus
    alpha_cal: float  # rad, constant rotation used for calibration


@dataclass
class Devices:
    """The cell's devices as a routine sees them: interfaces only."""

    arm: Arm
    cameras: dict[str, Camera]
    gripper: Gripper | None = None
    areas: dict[str, Area] = field(default_factory=dict)
    calibrations: dict[str, dict] = field(default_factory=dict)  # active model per target (camera, tool)
    operator: Operator | None = None

    def calibration(self, target: str, needed_by: str) -> dict:
        try:
            return self.calibrations[target]
        except KeyError:
            raise CalibrationInputError(
                f"{needed_by} needs an active calibration of {target!r}; none is stored "
                f"(active: {', '.join(sorted(self.calibrations)) or 'none'}). Calibrate {target} first."
            ) from None

    def area(self, name: str) -> Area:
        try:
            return self.areas[name]
        except KeyError:
            raise UnknownName(f"no area {name!r} in the cell file (defined: {', '.join(sorted(self.areas)) or 'none'})") from None

    def camera(self, name: str) -> Camera:
        try:
            return self.cameras[name]
        except KeyError:
            raise UnknownName(f"no camera {name!r} in the cell file (defined: {', '.join(sorted(self.cameras))})") from None


@dataclass(frozen=True)
class Step:
    index: int
    action: str
    args: dict[str, Any]

    def to_dict(self) -> dict:
        return {"index": self.index, "action": self.action, "args": self.args}

    @classmethod
    def from_dict(cls, d: dict) -> "Step":
        return cls(int(d["index"]), str(d["action"]), dict(d["args"]))


@dataclass
class StepResult:
    """One step's sample row, or rows (flat, CSV-ready), and the frames it took (saved if asked)."""

    row: dict[str, Any] | list[dict[str, Any]]
    frames: list = field(default_factory=list)

    @property
    def rows(self) -> list[dict[str, Any]]:
        return self.row if isinstance(self.row, list) else [self.row]


class Table(TypedDict, total=False):
    """A report table, as the CLI, report.md and the console show it. Cells are str, int, float or None
    ("-"); a float is shown as the routine rounded it (4 significant digits if it did not)."""

    title: str
    columns: list[str]
    rows: list[list]
    note: str  # optional, shown under the table


class Chart(TypedDict, total=False):
    """A line chart of a report: one line per series, each a list of [x, y] points."""

    name: str  # file name (name.png beside report.md)
    title: str
    x_label: str
    y_label: str
    series: dict[str, list[list[float]]]
    log_y: bool


@dataclass
class FitOutcome:
    """A fitted model and everything the report shows about it."""

    model: dict  # JSON-safe, enough to use the calibration
    stats: dict  # e.g. {"calibration": {...}, "verification": {...}}
    rejected: list[dict] = field(default_factory=list)
    plot: dict = field(default_factory=dict)  # arrays for the residual plot (report.plot_residuals)
    tables: list[Table] = field(default_factory=list)  # in the order the report shows them
    charts: list[Chart] = field(default_factory=list)
    summary: dict = field(default_factory=dict)  # keys result.json shows at its top (a check's verdict)
    calibrations: dict[str, "NewVersion"] = field(default_factory=dict)  # target -> a version to store


@dataclass
class NewVersion:
    """A calibration a routine proposes besides its own output (a check's touch-up): stored as a new version of
    its target, with the version it was derived from."""

    model: dict
    stats: dict
    parent: int | None  # the calibration id it corrects


class Params(BaseModel):
    """Base of every routine's parameters: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class PlanarFitParams(Params):
    """The B1+B2 model's options, for routines that fit one (defaults: at most the full model of appendix B)."""

    radial_terms: int = Field(2, ge=0, le=3, description="radial distortion terms fitted (k2, k4, k6: 0 to 3)")
    tangential: bool = Field(True, description="fit the tangential distortion (p1, p2)")
    fit_centre: bool = Field(True, description="fit the distortion centre (false: the image centre)")
    outlier_sigma: float = Field(4.0, gt=1, le=100, description="samples whose residual exceeds this many "
                                 "robust sigmas are rejected")
    loss: Literal["linear", "soft_l1", "huber"] = Field("soft_l1", description="robust loss of the fit (linear: "
                                                        "plain least squares)")
    select_model: bool = Field(True, description="free the distortion centre and keep the higher radial terms only "
                               "where the samples support them (BIC and Wald tests); false: fit every term above")

    def model_options(self):
        from calibration.models.planar import PlanarModelOptions

        return PlanarModelOptions(radial_terms=self.radial_terms, tangential=self.tangential,
                                  fit_centre=self.fit_centre, outlier_sigma=self.outlier_sigma, loss=self.loss,
                                  select_model=self.select_model)


class Routine(Protocol):
    """What the rest of the system needs from a routine; found by its file in its family's folder
    (`routines/__init__.py`).

    The CLI, the HTTP API, the console and report.md know routines only through this: a new routine
    needs no change elsewhere."""

    name: ClassVar[str]
    """The name `cellctl run NAME` and `POST /jobs` take (its file's name, "_" for "-")."""
    truth: ClassVar[str | None]
    """"module:function" judging a simulated run's fit against the hidden world (cellctl.truth), or None. A
    name, not an import: calibration never reads the simulator, only the runner of a simulated cell does."""
    Params: ClassVar[type[Params]]
    """Its parameters (pydantic, unknown keys refused); the console builds its form from their JSON schema."""
    sample_columns: ClassVar[tuple[str, ...]]
    """The columns of samples.csv: every row `execute` returns stays within them."""
    fit_columns: ClassVar[tuple[str, ...]]
    """The columns `cellctl fit NAME --samples FILE` requires of a recorded file."""
    # optional: small_params: ClassVar[dict], parameters of a short run that still takes every kind of step
    # (the contract test over every routine runs with them, not with the defaults)

    def plan(self, params: Params, devices: Devices) -> list[Step]:
        """The steps, deterministic for given parameters and cell; refuses (CalibrationInputError) before
        anything moves when an input is missing."""

    def inputs(self, params: Params, devices: Devices) -> list[str]:
        """Targets whose active calibrations the routine uses (recorded with the run)."""

    def output(self, params: Params, devices: Devices) -> str | None:
        """The target the routine calibrates (its result becomes that target's new version), if any."""

    def execute(self, step: Step, params: Params, devices: Devices, history: list[dict]) -> StepResult:
        """One step; `history` holds the samples already collected (persisted), for steps that depend on them."""

    def fit(self, samples: list[dict], params: Params, resolutions: dict[str, tuple[int, int]] | None = None) -> FitOutcome:
        """The model, its statistics, its residual plot and its report tables (with the seed's figures it
        reproduces), from the samples alone. `resolutions`: (width, height) per camera when known (offline
        files may not know)."""


@runtime_checkable
class ChoosesArmCalibration(Protocol):
    """A routine that may move the arm without the active `arm` calibration (iso9283's `moves: controller`, the arm
    as it came). Every other routine's moves go through it when one is active (cellctl/core/runs.py)."""

    def through_arm_calibration(self, params: Params) -> bool:
        """Whether this run's moves go through the active arm calibration."""


@runtime_checkable
class JudgesCalibrations(Protocol):
    """A routine whose fit judges the calibrations it used (a check): its fit needs their models too, so it is
    `judge` (`fit` on samples alone refuses)."""

    def judge(self, samples: list[dict], params: Params, calibrations: dict[str, dict],
              resolutions: dict[str, tuple[int, int]] | None = None) -> FitOutcome:
        """The fit, given the models (with their `calibration_id`) of the targets `inputs` names."""

    def alarm(self, result: dict) -> dict | None:
        """What the operator must be told of a judged run's result (the console's health alarm), or None when
        the calibrations hold."""


@runtime_checkable
class Previews(Protocol):
    """A routine that plans its own motion (poses it chose): what it will do can be shown before anything moves
    (`cellctl plan`), from its parameters and the camera's image size alone."""

    def preview(self, params: Params, image_size: tuple[int, int] | None) -> list[Table]:
        """The plan as report tables; CalibrationInputError, saying why, for a plan that would be refused."""


@runtime_checkable
class ChecksTargets(Protocol):
    """A routine whose parameters name places the cell file and the active calibrations decide on (a target in an
    area): the service asks it at submit, so a job that could not run is refused before it is queued, and its plan
    asks it again before anything moves."""

    def check_targets(self, params: Params, areas: dict[str, Area], calibrations: dict[str, dict],
                      arm_limits: dict | None = None) -> None:
        """Raise CalibrationInputError naming the parameter and what is allowed. `arm_limits`: the cell file's
        workspace box ({"x_mm": (min, max), ...}), when known."""


@runtime_checkable
class TargetsAccuracy(Protocol):
    """A routine with an accuracy target (`target_um`): its plan's calibration steps are a budget in an
    information-first order, and it stops collecting them once the target is met (calibration/routines/targeted.py).

    After each calibration step (`budget(step)`) the orchestrator asks `enough` with the samples of the steps done
    so far, in plan order; once it says yes, the remaining calibration steps are skipped and the verification steps
    (never in the budget) run. The answer is a pure function of those samples, so a resumed or replayed run makes
    the same decision at the same step."""

    def budget(self, step: Step) -> bool:
        """Whether `step` is a calibration step a met target may skip (verification steps never are)."""

    def enough(self, samples: list[dict], params: Params) -> bool:
        """Whether the predicted verification accuracy, with its confidence, meets the target, from `samples`."""


@runtime_checkable
class Pipelines(Protocol):
    """A routine whose steps split where a real cell can overlap them: the processing of one step's capture runs
    (in a worker thread) while the arm makes the next step's move (cellctl/core/orchestrator.py `collect`).

    Each step is `approach` (the move to where it measures), `capture` (the device work there) and `measure`
    (processing alone, no device access); `execute` stays equal to the three in a row (`execute_split`). `history`
    is the samples persisted when the part runs: for a step that `overlaps`, `approach` runs before the previous
    step's rows are in it, so such an approach must not depend on them (and the whole plan is approached in
    order: an approach may be made and not captured, when the target was met meanwhile)."""

    def approach(self, step: Step, params: Params, devices: Devices, history: list[dict]) -> None:
        """Device commands only: the move to where `step` measures (nothing, for a step that does not split)."""

    def capture(self, step: Step, params: Params, devices: Devices, history: list[dict]) -> Any:
        """The device work at that place (the pose read, the frame taken), and whatever `measure` needs of the
        devices (a camera's resolution, an active calibration): `measure` never touches them."""

    def measure(self, step: Step, captured: Any, params: Params, history: list[dict]) -> StepResult:
        """The step's rows from what `capture` returned: pure processing, safe in a worker thread."""

    def overlaps(self, step: Step) -> bool:
        """Whether `step`'s approach may run while the previous step's measurement is processed."""


def execute_split(routine: Pipelines, step: Step, params: Params, devices: Devices, history) -> StepResult:
    """A Pipelines routine's `execute`: its step's approach, capture and measure in a row."""
    history = list(history)
    routine.approach(step, params, devices, history)
    return routine.measure(step, routine.capture(step, params, devices, history), params, history)


def image_residuals(planar_map, uv: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Residuals to draw over the image: pointing from where the robot point projects to where it was
    seen, with length the radial error in plane units (so the plot's directions match the picture)."""
    toward = uv - planar_map.plane_to_pixel(xy)
    length = np.linalg.norm(planar_map.pixel_to_plane(uv) - xy, axis=1)
    norm = np.linalg.norm(toward, axis=1)
    return toward / np.where(norm > 0, norm, 1.0)[:, None] * length[:, None]
