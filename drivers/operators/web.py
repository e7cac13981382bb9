"""The web operator: a person at the daemon's console (or any API client) as the cell's Operator.

`operator: {backend: web}` in the cell file. Every verb the routines ask of an
operator (`request`, and the VR verbs `click_points`, `align_by_hand`,
`mount_camera` of calibration/routines/vr/_common.py) posts one pending request on
the cell's *desk* and blocks the worker until it is answered through the API
(cellctl/http/operator_api.py), withdrawn (the job aborted, paused now, or the
daemon stopping: the cell's `stop()`), or it times out (`timeout_s`).

Why a desk beside the device: the daemon builds a fresh Cell (and so a fresh
operator device) for every simulated job, but its API and event stream stay; the
desk is the one thing both see. There is one desk per calibration store (one store,
one daemon), found with `desk_for(store_dir)`; cell.py hands it to the device it
builds (through the driver context's store_dir), the API router attaches the daemon's event hub to it.
Outside a daemon nothing serves the desk and a request fails at once, clearly.

What a person answered is kept, so a resumed job never asks twice (cellctl/core/orchestrator.py's
`RecordsAnswers`): every request's answer (clicks, done, declined), who gave it and how long it
waited goes, with the step's samples, into the run folder (column `operator`); a step replayed on a
fresh simulated world takes its answers from there and asks nobody, and a step skipped on resume hands
back what it established (the cameras' mounting). The time a request waits is cell time: a simulated
cell's clock counts it (a real cell's wall clock does anyway).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.interfaces import DeviceError, DeviceState, Frame, MotionStopped, NotConnected

COLOURS = {"oru": "#50dc50", "receptacle": "#ff50ff"}  # as the VR overlays draw them
OTHER_COLOUR = "#40c8ff"
INCH = 0.0254


class OperatorDeclined(DeviceError):
    """The operator said they cannot do what was asked; the job faults and can be resumed after acknowledging."""


class OperatorTimeout(DeviceError):
    """Nobody answered the operator request in time."""


class AnswerRefused(ValueError):
    """An answer that does not fit the pending request, so nothing changed; `problems`: (field, problem) pairs.
    `not_pending`: the request is not pending, or asks for the other kind of answer (the service says Conflict);
    else a field of the answer is wrong (the service says InvalidRequest)."""

    def __init__(self, problems: list[tuple[str, str]], not_pending: bool):
        super().__init__("; ".join(f"{f}: {p}" for f, p in problems))
        self.problems, self.not_pending = problems, not_pending


@dataclass
class OperatorRequest:
    id: int
    kind: str  # request | click_points | align_by_hand | mount_camera
    instruction: str
    timeout_s: float
    details: dict = field(default_factory=dict)  # JSON-able: camera, object, projected points, ...
    image: np.ndarray | None = None  # the frame clicks are for
    posted: float = field(default_factory=time.time)  # wall clock, for people
    outcome: str | None = None  # answered | declined | withdrawn | timed-out
    answer: Any = None
    by: str = ""
    reason: str = ""
    posted_monotonic: float = field(default_factory=time.monotonic)  # what its time left counts from

    @property
    def answer_with(self) -> str:
        return "clicks" if self.kind == "click_points" else "confirm"

    def public(self) -> dict:
        base = f"/operator/requests/{self.id}"
        out = {"id": self.id, "kind": self.kind, "answer_with": self.answer_with, "instruction": self.instruction,
               "posted": self.posted, "timeout_s": self.timeout_s,
               "expires_in_s": round(max(self.posted_monotonic + self.timeout_s - time.monotonic(), 0.0), 1), **self.details}
        if self.kind == "click_points":
            out.update(frame_url=f"{base}/frame.png", answer_url=f"{base}/clicks")
        else:
            out.update(done_url=f"{base}/done")
        out["decline_url"] = f"{base}/decline"
        return out

    def summary(self) -> dict:
        """What the event stream says about it (no point lists)."""
        keep = ("camera", "object", "frame_id", "at_least", "fixture")
        return {"request": self.id, "kind": self.kind, "instruction": self.instruction,
                **{k: self.details[k] for k in keep if k in self.details},
                **({"outcome": self.outcome} if self.outcome else {}), **({"reason": self.reason} if self.reason else {})}


class OperatorDesk:
    """At most one pending operator request; the worker thread waits on it, API threads answer it."""

    def __init__(self):
        self._cond = threading.Condition()
        self._pending: OperatorRequest | None = None
        self._next_id = 1
        self._announce: Callable[[str, dict], None] | None = None
        self.last: OperatorRequest | None = None

    def attach(self, announce: Callable[[str, dict], None]) -> None:
        """Served from now on: `announce(state, summary)` is told of every request posted and ended."""
        self._announce = announce

    @property
    def served(self) -> bool:
        return self._announce is not None

    def pending(self) -> OperatorRequest | None:
        """The request waiting for an answer (not one answered a moment ago that the worker has yet to take)."""
        with self._cond:
            req = self._pending
            return req if req is not None and req.outcome is None else None

    def ask(self, kind: str, instruction: str, timeout_s: float, image=None, stopped=lambda: False,
            **details) -> OperatorRequest:
        """Post a request and wait until it ends (any outcome); returns it with its outcome and answer.

        `stopped()` is asked as the request is posted, under the lock `withdraw` takes: a stop that comes
        just before is seen, one just after finds the request to withdraw."""
        with self._cond:
            if stopped():
                raise MotionStopped("the job was stopped; the operator is not asked")
            if self._pending is not None:
                raise DeviceError(f"operator request {self._pending.id} is still pending; one at a time")
            req = OperatorRequest(self._next_id, kind, instruction, timeout_s, details, image)
            self._next_id += 1
            self._pending = req
        self._tell("waiting", req)
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while req.outcome is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    req.outcome = "timed-out"
                    break
                self._cond.wait(left)
            self._end(req)
        self._tell(req.outcome, req)
        return req

    def withdraw(self, request_id: int | None = None, reason: str = "") -> None:
        """End the pending request (the one given, if any) unanswered: the job was stopped."""
        with self._cond:
            req = self._pending
            if req is None or (request_id is not None and req.id != request_id) or req.outcome:
                return
            req.outcome, req.reason = "withdrawn", reason
            self._cond.notify_all()

    def answer_clicks(self, request_id: int, clicks: list[tuple[int, float, float]], by: str) -> OperatorRequest:
        with self._cond:
            req = self._answerable(request_id, "clicks")
            req.answer = check_clicks(req, clicks)  # raises before anything changes
            req.outcome, req.by = "answered", by
            self._cond.notify_all()
            return req

    def confirm(self, request_id: int, by: str) -> OperatorRequest:
        with self._cond:
            req = self._answerable(request_id, "confirm")
            req.outcome, req.by = "answered", by
            self._cond.notify_all()
            return req

    def decline(self, request_id: int, by: str, reason: str) -> OperatorRequest:
        with self._cond:
            req = self._answerable(request_id, None)
            req.outcome, req.by, req.reason = "declined", by, reason
            self._cond.notify_all()
            return req

    def _answerable(self, request_id: int, answer_with: str | None) -> OperatorRequest:
        req = self._pending
        if req is None or req.id != request_id or req.outcome is not None:
            now = f"the pending one is {req.id}" if req is not None and req.outcome is None else "none is pending"
            raise AnswerRefused([("request", f"operator request {request_id} is not pending (answered, "
                                              f"withdrawn or timed out, or never posted); {now}")], not_pending=True)
        if answer_with is not None and req.answer_with != answer_with:
            how = "POST its clicks to /clicks" if req.answer_with == "clicks" else "POST /done when it is done"
            raise AnswerRefused([("request", f"operator request {request_id} is a {req.kind} request: {how} "
                                              "(or /decline)")], not_pending=True)
        return req

    def _end(self, req: OperatorRequest) -> None:
        if self._pending is req:
            self._pending = None
        self.last = req
        req.image = None  # the frame is served only while its request is pending

    def _tell(self, state: str, req: OperatorRequest) -> None:
        if self._announce is not None:
            try:
                self._announce(state, req.summary())
            except Exception:  # noqa: BLE001, S110 - an event lost must not fail the job
                pass


def check_clicks(req: OperatorRequest, clicks) -> list[tuple[int, float, float]]:
    """The pairs as the routine wants them, or AnswerRefused naming every bad field."""
    n = req.details["n_points"]
    width, height = req.details["image_size"]
    obj, at_least = req.details["object"], req.details["at_least"]
    problems, seen = [], {}
    for i, (k, u, v) in enumerate(clicks):
        if not 0 <= k < n:
            problems.append((f"clicks.{i}.model_index", f"{k} is not a point of the {obj} model (allowed: 0 to {n - 1})"))
        elif k in seen:
            problems.append((f"clicks.{i}.model_index", f"model point {k} is already paired in clicks.{seen[k]}; "
                                                        "each model point at most once"))
        else:
            seen[k] = i
        for name, value, size in (("u", u, width), ("v", v, height)):
            if not -0.5 <= value <= size - 0.5:
                problems.append((f"clicks.{i}.{name}", f"{value:g} is outside the {width} x {height} image "
                                                       f"(allowed: -0.5 to {size - 0.5:g}, pixel centres at integers)"))
    if len(clicks) < at_least:
        pairs = "1 pair" if len(clicks) == 1 else f"{len(clicks)} pairs"
        problems.append(("clicks", f"{pairs} given; at least {at_least} are needed (decline the request "
                                   "if fewer points can be seen)"))
    if problems:
        raise AnswerRefused(problems, not_pending=False)
    return [(int(k), float(u), float(v)) for k, u, v in clicks]


_DESKS: dict[str, OperatorDesk] = {}
_DESKS_MUTEX = threading.Lock()


def desk_for(store_dir: str | Path) -> OperatorDesk:
    """The operator desk of the cell whose calibrations are kept in `store_dir` (one per daemon)."""
    key = str(Path(store_dir).expanduser().resolve())
    with _DESKS_MUTEX:
        return _DESKS.setdefault(key, OperatorDesk())


# -- the device ------------------------------------------------------------------------------------

# what identifies a request of each verb in its recorded answer (a replayed step must ask the same)
IDENTITY = {"request": ("instruction", "fixture", "present"), "click_points": ("camera", "object"),
            "align_by_hand": ("standoff_m",), "mount_camera": ("camera", "inter_camera_angle_deg", "view_width_in",
                                                                "look_at_in")}


def identity(kind: str, instruction: str, details: dict) -> dict:
    known = dict(details, instruction=instruction)
    return {k: known.get(k) for k in IDENTITY.get(kind, ("instruction",))}


def mounting(angle_deg, view_width_in, look_at_in) -> tuple:
    """The key of a camera's set-up (None everywhere: the cell's nominal layout)."""
    return angle_deg, view_width_in, None if look_at_in is None else tuple(float(v) for v in look_at_in)


class WebOperatorSettings(BaseModel):
    """`operator: {backend: web, timeout_s: 1800}`: how long a request waits before the job faults."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    timeout_s: float = Field(1800.0, gt=0, le=7 * 86400, description="seconds an operator request waits for an "
                             "answer before the job faults (acknowledge and resume to ask again)")


class WebOperator:
    """The Operator protocol plus the VR verbs, answered by a person through the daemon's API."""

    Settings = WebOperatorSettings

    def __init__(self, name: str, settings: WebOperatorSettings, desk: OperatorDesk, context=None):
        self.name, self.settings, self.desk = name, settings, desk
        self._context = context  # the cell's DriverContext: a simulated world's clock counts the waits
        self._state = DeviceState.CREATED
        self._stopped = False  # stop() came while no request was pending: the step's next request is refused
        self._mounted: dict[str, tuple] = {}  # camera -> the set-up the operator last confirmed (None: nominal)
        self._answers: list[dict] = []  # what was answered since the step began (kept with its samples)
        self._replaying: list[dict] | None = None  # a replayed step's recorded answers, taken in order

    @classmethod
    def create(cls, name: str, options: dict, context) -> WebOperator:
        """The desk of the cell's store (the daemon serves it); without a store, a desk of its own that
        nothing serves."""
        desk = desk_for(context.store_dir) if context.store_dir is not None else OperatorDesk()
        return cls(name, cls.Settings(**options), desk, context)

    @property
    def state(self) -> DeviceState:
        return self._state

    def connect(self) -> None:
        self._stopped = False
        self._state = DeviceState.READY

    def close(self) -> None:
        self.desk.withdraw(reason=f"{self.name} closed")
        self._state = DeviceState.CLOSED

    def stop(self) -> None:
        """The job is stopping (abort, pause now, shutdown): withdraw the pending request, ask no more this step."""
        self._stopped = True  # before withdraw takes the desk's lock (see OperatorDesk.ask)
        self.desk.withdraw(reason="the job was stopped")

    def begin_step(self) -> None:
        """A new step starts (cell.py): a stop of the previous one no longer applies; its answers are
        collected afresh."""
        self._stopped = False
        self._answers = []
        self._replaying = None

    # -- answers kept with the samples (cellctl/core/orchestrator.py: RecordsAnswers) ------------------------

    def answers(self) -> list[dict]:
        """What was answered since the step began, in order: verb, what it was about, outcome, the clicks,
        who answered, how long it waited (s)."""
        return [dict(a) for a in self._answers]

    def replay(self, answers: list[dict] | None) -> None:
        """The step is replayed (a fresh simulated world): its requests take these recorded answers, in
        order, and nobody is asked; None: ask as usual (a run folder from before answers were kept)."""
        self._replaying = None if answers is None else [dict(a) for a in answers]

    def recall(self, answers: list[dict]) -> None:
        """The steps done before the resume are skipped (a real cell): take in what their answers (in plan
        order) established, the cameras' mounting. A camera this operator has seen confirmed since it was
        built (this daemon's life) is left as it knows it: that confirmation is newer than the run's."""
        recalled = {}
        for a in answers:
            if a.get("verb") == "mount_camera" and a.get("outcome") == "answered":
                recalled[a["camera"]] = mounting(a.get("inter_camera_angle_deg"), a.get("view_width_in"),
                                                 a.get("look_at_in"))
        for camera, key in recalled.items():
            self._mounted.setdefault(camera, key)

    # -- the verbs ----------------------------------------------------------------------------------

    def request(self, instruction: str, fixture: str | None = None, present: bool | None = None) -> None:
        self._confirm(self._ask("request", instruction, fixture=fixture, present=present))

    def click_points(self, camera: str, frame: Frame, obj: str, model_points, at_least: int = 5,
                     projected=None, edges=None) -> list[tuple[int, float, float]]:
        """The operator's (model index, u, v) pairs on `frame`; [] when they decline (too few points visible)."""
        if projected is None:
            raise ValueError(f"{self.name}: click_points needs the model points projected into the image "
                             "(projected=...): the console draws them for the operator to pick")
        pts = np.asarray(projected, float)
        n = len(np.asarray(model_points))
        if pts.shape != (n, 2):
            raise ValueError(f"{self.name}: projected must be {n} x 2 pixels, one per model point; got {pts.shape}")
        height, width = frame.image.shape[:2]
        # a point the estimate puts behind the camera cannot be drawn: it is left out of the overlay, not the model
        points = [{"index": i, "u": round(float(u), 2), "v": round(float(v), 2)}
                  for i, (u, v) in enumerate(pts) if np.isfinite(u) and np.isfinite(v) and max(abs(u), abs(v)) < 1e6]
        edge_list = [[int(a), int(b)] for a, b in (edges if edges is not None else ())]
        req = self._ask("click_points",
                        f"{obj} in the {camera} view: click a model point on the overlay, then where that point is "
                        f"in the image; at least {at_least} pairs, spread over the object, then Submit.",
                        image=frame.image, camera=camera, frame_id=frame.frame_id, object=obj, at_least=int(at_least),
                        image_size=[int(width), int(height)], n_points=n, model_points=points, edges=edge_list,
                        colour=COLOURS.get(obj, OTHER_COLOUR))
        if req.outcome == "declined":
            return []
        self._confirm(req)
        return list(req.answer)

    def align_by_hand(self, arm, standoff_m: float) -> None:
        self._confirm(self._ask("align_by_hand", f"Jog the arm until the ORU stands aligned {standoff_m / INCH:.2f} in "
                                                 f"({standoff_m:.4f} m) in front of the receptacle, then press Done.",
                                standoff_m=float(standoff_m)))

    def mount_camera(self, camera: str, inter_camera_angle_deg: float | None = None,
                     view_width_in: float | None = None, look_at_in=None) -> None:
        """Asked only when the camera is not mounted so already (the cell starts in its nominal layout)."""
        key = mounting(inter_camera_angle_deg, view_width_in, look_at_in)
        if self._mounted.get(camera, (None, None, None)) == key:
            return
        what = [f"an inter-camera angle of {inter_camera_angle_deg:g} deg" if inter_camera_angle_deg is not None
                else "its nominal place",
                f"zoomed to a view {view_width_in:g} in wide" if view_width_in is not None else "its nominal zoom",
                f"aimed at {list(key[2])} in" if key[2] is not None else "aimed at the nominal look-at point"]
        self._confirm(self._ask("mount_camera", f"Mount camera {camera} at {what[0]}, {what[1]}, {what[2]}; then "
                                                f"press Done.", camera=camera,
                                inter_camera_angle_deg=inter_camera_angle_deg, view_width_in=view_width_in,
                                look_at_in=None if key[2] is None else list(key[2])))
        self._mounted[camera] = key

    # -- plumbing -----------------------------------------------------------------------------------

    def _ask(self, kind: str, instruction: str, image=None, **details) -> OperatorRequest:
        if self._state is not DeviceState.READY:
            raise NotConnected(f"{self.name}: not connected (state {self._state.value})")
        if self._replaying is not None:
            return self._replayed(kind, instruction, details)
        if not self.desk.served:
            raise NotConnected(f"{self.name}: backend 'web' is answered through the daemon (cellctl serve: its web "
                               "console or /operator in its API); nothing serves operator requests in this process")
        start = time.monotonic()
        try:
            req = self.desk.ask(kind, instruction, self.settings.timeout_s, image=image,
                                stopped=lambda: self._stopped, **details)
        except MotionStopped as exc:
            raise MotionStopped(f"{self.name}: {exc}") from None
        waited = time.monotonic() - start
        self._count(waited)
        answer = {"verb": kind, **identity(kind, instruction, details), "request": req.id, "outcome": req.outcome,
                  "by": req.by, "waited_s": waited}
        if req.reason:
            answer["reason"] = req.reason
        if kind == "click_points" and req.outcome == "answered":
            answer["clicks"] = [[k, u, v] for k, u, v in req.answer]
        self._answers.append(answer)
        return req

    def _replayed(self, kind: str, instruction: str, details: dict) -> OperatorRequest:
        """The request as it was answered when the step first ran (its record), asking nobody."""
        wanted = identity(kind, instruction, details)
        if not self._replaying:
            raise DeviceError(f"{self.name}: replaying a step of a resumed run, it asks again ({kind}: "
                              f"{instruction}) but no answer was recorded for it with the step's samples; the run "
                              "cannot be resumed exactly")
        rec = self._replaying.pop(0)
        if rec.get("verb") != kind or any(rec.get(k) != v for k, v in wanted.items()):
            raise DeviceError(f"{self.name}: replaying a step of a resumed run, it asks {kind} {wanted} where the "
                              f"answers recorded with its samples have {rec.get('verb')} "
                              f"{ {k: rec.get(k) for k in wanted} }; the run cannot be resumed exactly")
        self._count(float(rec.get("waited_s") or 0.0))
        self._answers.append(rec)
        answer = None
        if kind == "click_points":
            answer = [(int(k), float(u), float(v)) for k, u, v in rec.get("clicks", ())]
        return OperatorRequest(int(rec.get("request") or 0), kind, instruction, self.settings.timeout_s,
                               dict(details), outcome=rec.get("outcome", "answered"), answer=answer,
                               by=rec.get("by", ""), reason=rec.get("reason", ""))

    def _count(self, seconds: float) -> None:
        """The wait is cell time: on a simulated cell its clock counts it (a real cell's wall clock has)."""
        world = self._context.existing_world if self._context is not None else None
        if world is not None:
            world.clock.add_waited(seconds)

    def _confirm(self, req: OperatorRequest) -> None:
        if req.outcome == "answered":
            return
        if req.outcome == "declined":
            raise OperatorDeclined(f"{self.name}: the operator declined request {req.id} ({req.instruction})"
                                   + (f": {req.reason}" if req.reason else ""))
        if req.outcome == "withdrawn":
            raise MotionStopped(f"{self.name}: operator request {req.id} withdrawn ({req.reason or 'stopped'})")
        raise OperatorTimeout(f"{self.name}: no answer to operator request {req.id} within {req.timeout_s:g} s "
                              f"({req.instruction}); acknowledge and resume to ask again")
