"""What every simulated world shares: the strict model of its `sim:` section, its fault knobs, its clock,
its step-keyed noise, and the `SimWorld` protocol the fakes and the protocol simulators rely on.

The three worlds (the micro cell in world.py, six_axis/, vr/) differ in what they simulate, not in how
a run drives them, so that part is written once here.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers.sim.protocols import SIMULATORS  # the protocol simulators a cell can start (SimServer.protocol)


class Strict(BaseModel):
    """A cell file section: unknown keys are errors, and a validated section never changes."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class RandomFaults(Strict):
    """Faults drawn at random, for a soak (tools/soak.py): each arm move, capture and grip of the process draws
    once from one stream of `seed` (drivers/sim/fault_dice.py) that every world the process builds shares, so a
    job's fresh world (its resumption) meets new draws, not the same fault again as a count knob would."""

    seed: int = Field(0, ge=0)
    link_drop: float = Field(0.0, ge=0, le=0.2, description="per arm move: the link to the arm drops")
    protective_stop: float = Field(0.0, ge=0, le=0.2, description="per arm move: the arm stops in a protective stop")
    capture_timeout: float = Field(0.0, ge=0, le=0.2, description="per capture: no frame arrives")
    corrupt_frame: float = Field(0.0, ge=0, le=0.2, description="per capture: the frame arrives truncated")
    vacuum_loss: float = Field(0.0, ge=0, le=0.2, description="per grip that holds a part: the part is lost")


class SimFaults(Strict):
    """Fault injection, off by default. Counts are 1-based calls of that device."""

    random: RandomFaults | None = Field(None, description="faults drawn at random, for a soak")

    arm_drop_after_moves: int | None = Field(None, ge=1)
    protective_stop_after_moves: int | None = Field(None, ge=1)
    camera_timeout_after_captures: int | None = Field(None, ge=1)
    corrupt_frame_every: int | None = Field(None, ge=1)
    vacuum_loss_after_grips: int | None = Field(None, ge=1)
    # what a device self-test (cellctl commission) finds, one knob per finding:
    arm_motion_scale: float | None = Field(None, ge=0.5, le=1.5, description="the arm moves this fraction of each "
                                           "commanded displacement from its home (wrong units or gear ratio) and "
                                           "reports what it was commanded (micro-cell world)")
    camera_scale: dict[str, float] = Field(default_factory=dict, description="camera -> its image magnified by this "
                                           "about the image centre (a lens of another focal length than assumed)")
    camera_blur_px: dict[str, float] = Field(default_factory=dict, description="camera -> extra Gaussian blur "
                                             "sigma, px (the lens out of focus)")
    camera_gain: dict[str, float] = Field(default_factory=dict, description="camera -> its grey levels times this, "
                                          "clipped at full scale (over- or under-exposed)")
    gripper_blocked: bool = Field(False, description="the nozzle is blocked: vacuum builds with nothing held")
    gripper_no_air: bool = Field(False, description="no vacuum supply: the vacuum never builds")

    @model_validator(mode="after")
    def _camera_knobs(self):
        for knob, (lo, hi) in {"camera_scale": (0.5, 2.0), "camera_blur_px": (0.0, 50.0),
                               "camera_gain": (0.0, 20.0)}.items():
            for camera, value in getattr(self, knob).items():
                if not lo <= value <= hi:
                    raise ValueError(f"faults.{knob}.{camera}: {value}; allowed: {lo} to {hi}")
        return self


def serve_only(servers, protocol: str, cell: str) -> None:
    """ValueError naming the first of a cell's `sim.servers` that speaks another protocol than the one it serves."""
    for i, server in enumerate(servers):
        if server.protocol != protocol:
            raise ValueError(f"servers[{i}].protocol: {server.protocol!r} has nothing to serve in {cell}; allowed: "
                             f"{protocol}")


class SimServer(Strict):
    """A protocol simulator started with the cell, on loopback, sharing the cell's simulated world, so the
    cell's real driver of that protocol runs against the same truth as the simulated cameras."""

    protocol: Literal[tuple(SIMULATORS)]
    host: str = Field("127.0.0.1", description="loopback address to bind (UR: 127.0.0.x, its ports are fixed)")
    port: int | None = Field(None, ge=0, le=65535, description="default: the protocol's standard port; 0: a free one")
    serial_port: str | None = Field(None, description="epick only: serve RTU on this serial device (e.g. one end "
                                                      "of a socat pty pair) instead of RTU over TCP")
    options: dict = Field(default_factory=dict, description="protocol-specific simulator settings (fault knobs)")

    @model_validator(mode="after")
    def _serial_is_epick(self):
        if self.serial_port is not None and self.protocol != "epick":
            raise ValueError(f"serial_port: only the epick simulator speaks on a serial port, not {self.protocol}")
        return self


class SimClock:
    """Simulated cell time; optionally also spent as wall time (realtime_factor > 0)."""

    def __init__(self, realtime_factor: float = 0.0):
        self._t = 0.0
        self.realtime_factor = realtime_factor

    def now(self) -> float:
        return self._t

    def advance(self, seconds: float, stop: threading.Event | None = None) -> float:
        """Spend `seconds`; with real time on, return early (the fraction spent) once `stop` is set."""
        if self.realtime_factor <= 0 or stop is None:
            if self.realtime_factor > 0:
                time.sleep(seconds * self.realtime_factor)
            self._t += seconds
            return 1.0
        start = time.monotonic()
        wall = seconds * self.realtime_factor
        stopped = stop.wait(wall)
        spent = min((time.monotonic() - start) / wall, 1.0) if (stopped and wall > 0) else 1.0
        self._t += seconds * spent
        return spent

    def add_waited(self, seconds: float) -> None:
        """Count time that already passed as wall time: a person answering an operator request (the web
        console, a terminal). A real cell waits as long, so it is cell time; it is never spent again as wall
        time, whatever the realtime factor."""
        self._t += max(float(seconds), 0.0)


@runtime_checkable
class SimWorld(Protocol):
    """A simulated world as the fakes, the protocol simulators and a sim cell use it."""

    config: Any  # its `sim:` section: `cameras` by name, `faults` (SimFaults)
    seed: int
    clock: SimClock
    faults: SimFaults
    frame_truth: dict  # (camera, frame_id) -> what that frame truly shows

    def begin_step(self, key: int) -> None:
        """Draw the noise of run step `key` from its own stream, so a resumed run equals an uninterrupted one."""

    def capture(self, camera: str, frame_id: int) -> np.ndarray:
        """Render `camera`'s view now, keep its truth under (camera, frame_id) and spend its exposure time."""

    def set_fixture(self, name: str, present: bool) -> None:
        """The operator lays (or removes) a fixture; KeyError if the world has none of that name."""


@runtime_checkable
class MotionTimed(Protocol):
    """An arm that can say how long a move will take in wall time (a simulated one: its world's clock)."""

    def wall_seconds(self, start, target) -> float: ...


class WorldBase:
    """The part of SimWorld every world implements the same way."""

    def __init__(self, config, realtime_factor: float = 0.0):
        self.config = config
        self.seed = config.seed
        self.faults: SimFaults = config.faults
        self.clock = SimClock(realtime_factor)
        self.lock = threading.RLock()
        self.rng = np.random.default_rng([config.seed, 1])  # noise before the first step
        self.step: int | None = None
        self.frame_truth: dict = {}

    def begin_step(self, key: int) -> None:
        with self.lock:
            self.step = int(key)
            self.rng = np.random.default_rng([self.seed, 2, self.step])

    def set_fixture(self, name: str, present: bool) -> None:
        raise KeyError(f"no fixture {name!r} in the simulated world (defined: none)")
