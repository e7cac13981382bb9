"""The manual-motion verbs of the service: jog, move to a pose or a named position, the dead-man heartbeat, stop,
and the vacuum (`LocalService` takes them from `ManualVerbs`; cellctl/core/manual.py runs the moves).

Each is a command for the holder of the operator lock only (nobody holding it is not enough), audited when it is
asked (accepted or refused) and when its move ends (how far it went, and why it stopped). A move is checked whole
before anything moves: the axis and frame, the speed against the manual cap, the step against its largest, the
whole path against the workspace box and every segment against the joint limits. Refused: InvalidRequest naming
what and what is allowed, and nothing moved. Beside a job, or while its job holds the cell: Conflict naming it.
"""

from __future__ import annotations

import math
from dataclasses import replace

from drivers.interfaces import ChecksTargets, DeviceError, DeviceState, MotionRejected, Pose
from drivers.limits import WorkspaceBox

from cellctl.core.calibrated_arm import CalibratedArm
from cellctl.core.manual import SEGMENT_S, ManualMotion, manual_speed
from cellctl.core.manual_path import (
    AXES,
    FRAMES,
    PathError,
    check_in_box,
    segments,
    stepped,
    to_box_edge,
)
from cellctl.errors import Conflict, InvalidRequest, NotFound
from cellctl.service.export import ARM_TARGET
from cellctl.service.interface import Caller


class ManualVerbs:
    """Mixed into LocalService: uses its config, worker, lock, hub, calibration store and `_command`."""

    _manual_runner: ManualMotion | None = None

    @property
    def _runner(self) -> ManualMotion:
        if self._manual_runner is None:
            worker = self.worker
            self._manual_runner = ManualMotion(worker, self._hub.publish if self._hub is not None else
                                               (lambda kind, data: None))
        return self._manual_runner

    # -- reads -----------------------------------------------------------------------------------------
    def manual(self) -> dict:
        s = self.config.manual
        arm = self.worker.cells.cell.arm
        box = self._box()
        return {"speed_pct": s.speed_pct, "speed_mm_s": manual_speed(arm, s.speed_pct) * 1e3,
                "max_step_mm": s.max_step_mm, "max_step_deg": s.max_step_deg,
                "heartbeat_timeout_s": s.heartbeat_timeout_s, "segment_s": SEGMENT_S,
                "axes": list(AXES) if self._six_axis() else ["x", "y", "z", "rz"], "frames": list(FRAMES),
                "box": box.model_dump() if box is not None else None,
                "positions": {name: p.model_dump(exclude_none=True) for name, p in s.positions.items()},
                "gripper": self.config.gripper is not None, **self._runner.status()}

    # -- motion -----------------------------------------------------------------------------------------
    def jog(self, caller: Caller, axis: str, distance: float | None = None, direction: int = 1,
            frame: str = "cell", speed_pct: float | None = None) -> dict:
        s = self.config.manual
        held = distance is None
        rotation = axis in ("rx", "ry", "rz")
        unit = "deg" if rotation else "mm"
        what = (f"{axis} {'+' if direction > 0 else '-'} held ({frame} frame)" if held
                else f"{axis} {distance:+.3f} {unit} ({frame} frame)")
        detail = {"axis": axis, "distance": distance, "direction": direction, "frame": frame, "speed_pct": speed_pct}
        with self._command(caller, "jog", "arm", detail, check_lock=False) as entry:
            if axis not in AXES:
                raise InvalidRequest(f"axis: {axis!r} is not an axis (allowed: {', '.join(AXES)})")
            if frame not in FRAMES:
                raise InvalidRequest(f"frame: {frame!r} is not a frame (allowed: {', '.join(FRAMES)})")
            if held and direction not in (1, -1):
                raise InvalidRequest(f"direction: {direction!r} (allowed: 1 or -1)")
            if not held:
                limit = s.max_step_deg if rotation else s.max_step_mm
                if not (math.isfinite(distance) and 0 < abs(distance) <= limit):
                    raise InvalidRequest(f"distance: {distance} {unit} (allowed: 0 < |distance| <= {limit} {unit}, "
                                         f"manual.max_step_{unit}); nothing moved")
            amount = (math.radians(distance) if rotation else distance * 1e-3) if not held else None

            def end_of(start: Pose) -> Pose:
                if held:
                    return to_box_edge(start, axis, direction, frame, self._box() or _NO_BOX)
                return stepped(start, axis, amount, frame)

            motion = self._start(caller, "jog-hold" if held else "jog", what, end_of, speed_pct, held)
            entry["target"] = f"arm (manual move {motion['motion']})"
            return motion

    def move_to(self, caller: Caller, pose: dict | None = None, position: str | None = None,
                speed_pct: float | None = None) -> dict:
        s = self.config.manual
        detail = {"pose": pose, "position": position, "speed_pct": speed_pct}
        with self._command(caller, "move-to", "arm", detail, check_lock=False) as entry:
            if (pose is None) == (position is None):
                raise InvalidRequest("give a pose (x_mm, y_mm, z_mm, alpha_deg or quaternion_wxyz) or a named "
                                     "position, exactly one")
            if position is not None:
                if position not in s.positions:
                    raise NotFound(f"position: no position {position!r} in the cell file's manual.positions "
                                   f"(defined: {', '.join(sorted(s.positions)) or 'none'})")
                pose = s.positions[position].model_dump()
            target = _pose_of(pose)
            what = f"to {position}" if position else "to " + ", ".join(
                f"{k}={v:.3f}" for k, v in pose.items() if isinstance(v, (int, float)))

            def end_of(start: Pose) -> Pose:
                if target.orientation is not None and start.orientation is None:
                    raise PathError("quaternion_wxyz: this arm turns about the vertical only; give alpha_deg")
                return target

            motion = self._start(caller, "move-to", what, end_of, speed_pct, held=False)
            entry["target"] = f"arm (manual move {motion['motion']})"
            return motion

    def manual_alive(self, caller: Caller, motion_id: int) -> dict:
        """The dead-man heartbeat of a move (not audited: several a second). A refused one (the lock lost) is not
        taken, so the move stops by itself."""
        self._lock.check_held(caller.lock, "a manual move's heartbeat")
        try:
            return self._runner.heartbeat(motion_id)
        except KeyError:
            raise NotFound(f"no manual move {motion_id} (the last: {self._last_id()})") from None

    def manual_stop(self, caller: Caller, motion_id: int | None = None) -> dict:
        """Stop the manual move now (anyone with the token may stop the arm: stopping is always allowed)."""
        with self._command(caller, "stop manual move", f"manual move {motion_id or 'current'}", check_lock=False):
            try:
                got = self._runner.stop(motion_id)
            except KeyError:
                raise NotFound(f"no manual move {motion_id} (the last: {self._last_id()})") from None
            return got or {"motion": None, "state": "idle"}

    def vacuum(self, caller: Caller, on: bool) -> dict:
        verb = "grip" if on else "release"
        with self._command(caller, verb, "gripper", check_lock=False):
            self._lock.check_held(caller.lock, f"{verb} (manual)")
            if self.config.gripper is None:
                raise NotFound("this cell has no gripper (the cell file has no gripper section)")
            with self.worker.manual_claim(caller.who, verb) as cell:
                gripper = cell.gripper
                try:
                    if on:
                        gripper.grip()
                    else:
                        gripper.release()
                    status = gripper.status()
                except DeviceError as exc:
                    raise Conflict(f"gripper: {exc}") from None
            return {"vacuum": "on" if on else "off", "object_detected": status.object_detected,
                    "vacuum_kpa": status.vacuum_kpa, "gripping": status.gripping}

    # -- the parts -------------------------------------------------------------------------------------
    def _start(self, caller: Caller, kind: str, what: str, end_of, speed_pct: float | None, held: bool) -> dict:
        s = self.config.manual
        self._lock.check_held(caller.lock, f"a manual move ({what})")
        pct = s.speed_pct if speed_pct is None else speed_pct
        if not (isinstance(pct, (int, float)) and math.isfinite(pct) and 0 < pct <= s.speed_pct):
            raise InvalidRequest(f"speed_pct: {speed_pct} (allowed: 0 < speed_pct <= {s.speed_pct}, the manual cap "
                                 "manual.speed_pct); nothing moved")
        claim = self.worker.manual_claim(caller.who, kind)
        cell = claim.__enter__()
        try:
            arm = self._arm_of(cell)
            if arm.state is not DeviceState.READY:
                raise Conflict(f"arm: {arm.state.value}; reconnect it (cellctl status, POST /cell/reconnect) first")
            start = arm.pose()
            try:
                end = end_of(start)
                check_in_box(end, self._box())
            except PathError as exc:
                raise InvalidRequest(f"{exc}; nothing moved") from None
            speed = manual_speed(arm, pct)
            path = segments(start, end, speed, SEGMENT_S)
            if not path and held:
                raise InvalidRequest(f"{what}: the arm is at the edge of the workspace box already; nothing moved")
            check = arm.calibrated_joints if isinstance(arm, CalibratedArm) else (
                arm.check_target if isinstance(arm, ChecksTargets) else (lambda target: None))
            try:
                for seg in path[:1] if held else path:  # a held jog is checked segment by segment as it goes
                    check(seg.target)
            except MotionRejected as exc:
                raise InvalidRequest(f"{what}: {exc}") from None
            except DeviceError as exc:
                raise Conflict(f"arm: {exc}") from None

            def ended(motion) -> None:
                self._audit(replace(caller, via="manual move end"), "manual move end", f"manual move {motion.id}",
                            {"what": motion.what, "moved_mm": round(motion.public()["moved_mm"], 4),
                             "stopped_by": motion.stopped_by, "coast_s": motion.coast_s}, motion.state)

            return self._runner.start(caller.who, kind, what, start, path, speed, held,
                                      s.heartbeat_timeout_s, claim, arm, check, ended)
        except BaseException:
            claim.__exit__(None, None, None)
            raise

    def _arm_of(self, cell):
        """The arm as a job moves it: through the active `arm` calibration when there is one."""
        model = self.calstore.active_models().get(ARM_TARGET)
        return CalibratedArm(cell.arm, model) if model else cell.arm

    def _box(self) -> WorkspaceBox | None:
        limits = self.config.arm.options.get("limits")
        return WorkspaceBox.model_validate(limits) if limits else None

    def _six_axis(self) -> bool:
        pose = self.worker.idle_pose()
        return bool(pose and pose.get("orientation_wxyz"))

    def _last_id(self):
        last = self._runner.last
        return last.id if last else "none yet"


_NO_BOX = WorkspaceBox(x_mm=(-1e4, 1e4), y_mm=(-1e4, 1e4), z_mm=(-1e4, 1e4))


def _pose_of(fields: dict) -> Pose:
    """A typed pose (x_mm, y_mm, z_mm and alpha_deg or quaternion_wxyz), checked field by field."""
    allowed = {"x_mm", "y_mm", "z_mm", "alpha_deg", "quaternion_wxyz"}
    unknown = sorted(set(fields) - allowed)
    if unknown:
        raise InvalidRequest(f"pose: unknown field(s) {', '.join(unknown)} (allowed: {', '.join(sorted(allowed))})")
    values = {}
    for name in ("x_mm", "y_mm", "z_mm"):
        v = fields.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InvalidRequest(f"pose.{name}: {v!r} (allowed: a finite number of mm)")
        values[name] = float(v) * 1e-3
    alpha = fields.get("alpha_deg", 0.0) or 0.0
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not -360 <= alpha <= 360:
        raise InvalidRequest(f"pose.alpha_deg: {alpha!r} (allowed: -360 to 360)")
    q = fields.get("quaternion_wxyz")
    if q is not None:
        if (not isinstance(q, (list, tuple)) or len(q) != 4
                or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in q)
                or abs(math.hypot(*q) - 1.0) > 1e-3):
            raise InvalidRequest(f"pose.quaternion_wxyz: {q!r} (allowed: four numbers w, x, y, z of norm 1)")
        q = tuple(float(v) for v in q)
    return Pose(values["x_mm"], values["y_mm"], values["z_mm"], math.radians(alpha), q)

