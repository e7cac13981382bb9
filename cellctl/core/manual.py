"""Manual motion: a person jogs the arm, moves it to a typed or named pose, switches the vacuum.

Every manual move (the service checks the operator lock and audits it; this module does the rest):
- runs while no job runs or holds the cell, one at a time (`Worker.manual_claim`); no job starts meanwhile;
- goes at the manual speed: `manual.speed_pct` of the arm's own speed limit (its `max_speed_m_s` where the driver
  has one), never above 250 mm/s, the reduced speed ISO 10218-1 allows beside a person;
- is checked before anything moves: the whole path against the workspace box, and every segment against the joint
  limits (through the active arm calibration, or the driver's own check), so a jog beyond them moves nothing;
- is sent in segments of SEGMENT_S of motion, paced to the clock, each one only while its client's heartbeat is
  fresh: the dead-man. A released button or key stops it at once (the arm's stop() and no further segment); a
  closed tab or a dropped link stops it within `manual.heartbeat_timeout_s` and one segment.
A held jog has no end of its own: it goes toward the box edge (or half a turn) and is checked segment by
segment, stopping where the next would leave the limits.

On a real arm each segment is a short linear move of its own; a controller's streaming interface (UR speedL, ABB
EGM) would make a smoother jog and is not used yet.
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from dataclasses import dataclass, field

from drivers.interfaces import DeviceError, MotionRejected, Pose, SpeedLimited

from cellctl.core.manual_path import Segment, pose_fields

log = logging.getLogger("cellctl.core.manual")

SEGMENT_S = 0.05  # seconds of motion per segment: what a released button may still move, at most
REDUCED_SPEED_M_S = 0.25  # ISO 10218-1: the reduced speed for manual motion beside a person
DEFAULT_ARM_LIMIT_M_S = REDUCED_SPEED_M_S  # an arm that does not say its own limit
PROGRESS_EVERY_S = 0.2  # a `manual` event while a move runs


def manual_speed(arm, speed_pct: float) -> float:
    """The manual speed (m/s): `speed_pct` of the arm's limit, never above the reduced speed."""
    limit = arm.max_speed_m_s if isinstance(arm, SpeedLimited) else DEFAULT_ARM_LIMIT_M_S
    return min(limit * speed_pct / 100.0, REDUCED_SPEED_M_S)


@dataclass
class Motion:
    """One manual move, as the service and the events show it."""

    id: int
    kind: str  # jog, jog-hold, move-to
    what: str  # in words: "x +1.000 mm (cell frame)"
    by: str
    speed_mm_s: float
    start: Pose
    segments: list[Segment]
    held: bool  # a held jog: ends when released (or at the limits)
    heartbeat_timeout_s: float
    state: str = "moving"  # moving, done, stopped, refused, failed
    stopped_by: str | None = None  # released, heartbeat lost, limit, fault, end
    reason: str = ""
    pose: Pose | None = None
    sent: int = 0
    last_heartbeat: float = field(default_factory=time.monotonic)
    stop_asked: float | None = None  # monotonic time the stop was asked (released), or the last heartbeat (lost)
    coast_s: float | None = None  # motion after the stop was asked, s
    sent_at: list[tuple[float, float]] = field(default_factory=list)  # (start, seconds) of each segment sent
    stop_event: threading.Event = field(default_factory=threading.Event)

    def public(self) -> dict:
        now = self.pose or self.start
        return {"motion": self.id, "kind": self.kind, "what": self.what, "by": self.by, "state": self.state,
                "stopped_by": self.stopped_by, "reason": self.reason, "speed_mm_s": self.speed_mm_s,
                "start": pose_fields(self.start), "pose": pose_fields(self.pose or self.start),
                "moved_mm": math.dist(self.start.xyz, now.xyz) * 1e3,
                "delta_mm": [float(v) * 1e3 for v in now.xyz - self.start.xyz],
                "segments": len(self.segments), "sent": self.sent, "coast_s": self.coast_s,
                "heartbeat_timeout_s": self.heartbeat_timeout_s}


def motion_after(sent: list[tuple[float, float]], asked: float) -> float:
    """Seconds of motion after `asked`: of each segment sent, the part of its motion [start, start + seconds] that
    lies after it (an upper bound: a stop cuts the segment under way short on a real arm). A stalled loop sends
    nothing meanwhile, so a stall is no motion."""
    return sum(max(0.0, min(seconds, start + seconds - asked)) for start, seconds in sent)


class ManualMotion:
    """Runs manual moves on a thread of their own, one at a time, and keeps the last one for status."""

    def __init__(self, worker, publish):
        self.worker, self.publish = worker, publish
        self._ids = itertools.count(1)
        self._mutex = threading.Lock()
        self.current: Motion | None = None
        self.last: Motion | None = None

    def status(self) -> dict:
        with self._mutex:
            cur, last = self.current, self.last
        return {"current": cur.public() if cur else None, "last": last.public() if last else None}

    def start(self, by: str, kind: str, what: str, start: Pose, segments: list[Segment], speed_m_s: float,
              held: bool, heartbeat_timeout_s: float, claim, arm, check_segment, on_end) -> dict:
        """Start a checked path on its thread; `claim` is the worker's manual claim, already entered (released
        when the move ends), `check_segment` refuses a segment beyond the limits (MotionRejected), `on_end`
        audits the end."""
        motion = Motion(next(self._ids), kind, what, by, speed_m_s * 1e3, start, segments, held,
                        heartbeat_timeout_s)
        with self._mutex:
            self.current = motion
        thread = threading.Thread(target=self._run, args=(motion, claim, arm, check_segment, on_end),
                                  name=f"cellctl-manual-{motion.id}", daemon=True)
        thread.start()
        return motion.public()

    def heartbeat(self, motion_id: int) -> dict:
        """The client is still there (and still holds the button): the move may go on."""
        motion = self._motion(motion_id)
        if motion.state == "moving":
            motion.last_heartbeat = time.monotonic()
        return motion.public()

    def stop(self, motion_id: int | None = None) -> dict | None:
        """Stop now (a released button, or `cellctl` interrupted); the arm stands where it stopped."""
        with self._mutex:
            motion = self.current
        if motion is None or (motion_id is not None and motion.id != motion_id):
            last = self.last
            if motion_id is not None and (last is None or last.id != motion_id):
                raise KeyError(motion_id)
            return last.public() if last else None
        if motion.stop_asked is None:
            motion.stop_asked = time.monotonic()
            motion.stopped_by = "released"
        motion.stop_event.set()
        try:
            self.worker.cells.cell.arm.stop()  # a segment under way stops now (always safe)
        except Exception:  # noqa: BLE001 - stop is best effort here; no further segment is sent either way
            log.exception("stopping the arm after a release")
        return motion.public()

    def _motion(self, motion_id: int) -> Motion:
        with self._mutex:
            for m in (self.current, self.last):
                if m is not None and m.id == motion_id:
                    return m
        raise KeyError(motion_id)

    # -- the thread ---------------------------------------------------------------------------------
    def _run(self, motion: Motion, claim, arm, check_segment, on_end) -> None:
        try:
            self._send(motion, arm, check_segment)
        except Exception as exc:  # noqa: BLE001 - any failure ends the move, reported and audited
            log.exception("manual move failed", extra={"motion": motion.id})
            motion.state, motion.stopped_by, motion.reason = "failed", "fault", f"{type(exc).__name__}: {exc}"
        finally:
            try:
                motion.pose = arm.pose()
            except Exception:  # noqa: BLE001 - a faulted arm: its last known pose stays
                pass
            claim.__exit__(None, None, None)
            with self._mutex:
                self.current, self.last = None, motion
            self._announce(motion)
            on_end(motion)

    def _send(self, motion: Motion, arm, check_segment) -> None:
        last_event = 0.0
        for segment in motion.segments:
            now = time.monotonic()
            if motion.stop_event.is_set():
                break
            if now - motion.last_heartbeat >= motion.heartbeat_timeout_s:
                motion.stopped_by, motion.stop_asked = "heartbeat lost", motion.last_heartbeat
                break
            if motion.held:  # a held jog is checked as it goes: it stops where the next segment would leave
                try:
                    check_segment(segment.target)
                except MotionRejected as exc:
                    motion.stopped_by, motion.reason = "limit", str(exc)
                    break
            try:
                arm.move_linear(segment.target, motion.speed_mm_s * 1e-3)
            except MotionRejected as exc:  # the controller's own check: nothing of this segment moved
                motion.stopped_by, motion.reason = "limit", str(exc)
                break
            except DeviceError:
                if motion.stop_event.is_set():  # our own stop cut the segment short
                    break
                raise
            finally:
                motion.sent += 1
                motion.sent_at.append((now, segment.seconds))
            motion.pose = segment.target
            self.worker.cells.last_pose = dict(pose_fields(segment.target), read_at=time.time())
            # paced to the clock: a simulated arm moves at once, a real one takes its time; either way the next
            # segment is sent no sooner than this one would end at the manual speed
            motion.stop_event.wait(max(0.0, now + segment.seconds - time.monotonic()))
            if time.monotonic() - last_event >= PROGRESS_EVERY_S:
                last_event = time.monotonic()
                self._announce(motion)
        else:
            motion.stopped_by = motion.stopped_by or "end"
        if motion.stop_asked is not None:  # how long the arm moved on after it was asked to stop (or lost its client)
            motion.coast_s = motion_after(motion.sent_at, motion.stop_asked)
        motion.state = "done" if motion.stopped_by == "end" else ("refused" if motion.sent == 0 and
                                                                  motion.stopped_by == "limit" else "stopped")
        if not motion.reason:
            motion.reason = {"end": "arrived", "released": "released: stopped where it was",
                             "heartbeat lost": f"no heartbeat from its client for {motion.heartbeat_timeout_s} s: "
                                               "stopped (the dead-man)",
                             }.get(motion.stopped_by, motion.stopped_by or "")

    def _announce(self, motion: Motion) -> None:
        try:
            self.publish("manual", motion.public())
        except Exception:  # noqa: BLE001 - an event never stops the arm's loop
            log.exception("publishing a manual event")
