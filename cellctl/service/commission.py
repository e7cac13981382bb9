"""The device self-test (`cellctl commission`): each device of a cell checked in order, each finding with its fix.

In the spirit of OpenPnP's Issues & Solutions, for a person commissioning a cell:

1. link: the device connects (a device that is not connected is connected once: the time it took, or why it
   did not, with the options to check), what it says it is (version), how long a reading takes (latency);
2. readings: the arm's pose and joints (inside its workspace box?), the gripper's vacuum at rest, a frame of
   each camera (its size);
3. motion, only when the operator confirmed it (`move`): the arm moves 5 mm along x (or the first of -x, +y,
   -y whose target lies in the workspace box and the arm's own limits) slowly and back; each camera that sees
   something move reports how far, from the images (the bright features it finds: nozzle, spheres, a board's
   squares), in mm when its scale is known (its active planar calibration, else the size of the area it serves
   over its pixels), and whether the view came back;
4. grip with nothing held: the vacuum must build on an open nozzle without detecting an object;
5. each camera's focus (the blur of the sharpest edges in view, and the variance of the Laplacian) and exposure
   (saturated pixels, mean level).

Every check is a row {device, check, result, figure, finding}: result "ok", "problem" (the finding names the
fix), "skipped" (not run, and why: e.g. the motion without a confirmation) or "info" (nothing to judge by). A
device that is not connected is a finding, never a traceback. The figures are measured on the devices: on a
simulated cell the world's fault knobs (drivers/sim/base.py SimFaults) and the protocol simulators' options
produce each finding.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import asdict, dataclass, replace

import numpy as np

from drivers.interfaces import ChecksTargets, DeviceError, DeviceState, MotionRejected, Pose
from drivers.limits import WorkspaceBox

from cellctl.core.manual_path import PathError, check_in_box

MOVE_MM = 5.0  # the arm's commissioning move, and back
MOVE_SPEED_M_S = 0.005  # slow: 5 mm/s
ARM_TOLERANCE_MM = 0.05  # the reported move may differ from the asked one by this
SCALE_TOLERANCE = 0.03  # a camera's measured move may differ from the arm's by this fraction
RETURN_TOLERANCE_PX = 1.5  # what a camera sees after the move back may lie this far from where it started
SLOW_REPLY_S = 0.1  # a reading that takes longer: the link is slow
SATURATED_FRACTION = 0.01  # more pixels than this at full scale: over-exposed
DARK_MEAN = 0.02  # a mean level below this fraction of full scale: under-exposed (or no light)
BLURRED_PX = 4.0  # edges blurred wider than this (Gaussian sigma, px): out of focus
EDGE_CONTRAST_NOISE = 8.0  # an edge counts when its contrast is this many noise sigmas
PROBE_IDS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 16, 65, 247)  # Modbus ids tried when the configured one is silent
# a Modbus gripper's backend -> the read that asks it for its state (address, count, function code)
MODBUS_PROBES = {"epick": (0x07D0, 3, 4), "vgc10": (0x0000, 2, 3)}

# the options of a backend that say where the device is (what to check when it does not answer)
ADDRESS_OPTIONS = {
    "abb": ("host", "motion_port", "logger_port"),
    "ur": ("host",),
    "epick": ("transport", "serial_port", "baudrate", "host", "port", "device_id"),
    "vgc10": ("host", "port", "device_id"),
}
ADDRESS_WORDS = ("host", "port", "address", "serial", "device", "ip", "url", "id")


@dataclass
class Check:
    device: str
    check: str
    result: str  # ok, problem, skipped, info
    figure: str = ""
    finding: str = ""


class Commissioning:
    """One self-test of `cell` (cellctl.core.cell.Cell, connected as far as it goes) against its cell file."""

    def __init__(self, cell, config, *, device: str | None = None, move: bool = False,
                 errors: dict[str, str] | None = None, calibrations: dict | None = None):
        self.cell, self.config, self.move = cell, config, move
        self.errors = dict(errors or {})  # why a device did not connect before (the daemon's start)
        self.calibrations = calibrations or {}  # the active calibration models, by target
        self.devices = devices_of(cell)
        check_device(cell, config, device)
        self.only = device
        self.checks: list[Check] = []
        self.frames: dict[str, object] = {}  # camera -> the readings' frame

    # -- the run --------------------------------------------------------------------------------------

    def run(self) -> dict:
        started = time.monotonic()
        chosen = [name for name in self.devices if self.only in (None, name)]
        for name in chosen:
            self._guarded(name, "link", self.link)
        for name in chosen:
            self._guarded(name, "readings", self.readings)
        if self.only is None or self.devices[self.only][0] in ("arm", "camera"):
            self._guarded("arm", "motion", lambda _name: self.motion())
        for name in chosen:
            if self.devices[name][0] == "gripper":
                self._guarded(name, "grip with nothing held", self.grip)
        for name in chosen:
            if self.devices[name][0] == "camera":
                self._guarded(name, "focus", self.focus)
                self._guarded(name, "exposure", self.exposure)
        order = {name: i for i, name in enumerate(self.devices)}  # each device's checks together, in their order
        rows = [asdict(c) for c in sorted(self.checks, key=lambda c: order.get(c.device, len(order)))]
        problems = sum(1 for c in self.checks if c.result == "problem")
        return {"cell": self.config.cell.name, "simulated": self.config.sim is not None, "device": self.only,
                "moved": self.move, "checks": rows, "problems": problems,
                "findings": [f"{c['device']}: {c['finding']}" for c in rows if c["result"] == "problem"],
                "seconds": round(time.monotonic() - started, 3)}

    def add(self, device: str, check: str, result: str, figure: str = "", finding: str = "") -> Check:
        row = Check(device, check, result, figure, finding)
        self.checks.append(row)
        return row

    def _guarded(self, name: str, check: str, step) -> None:
        """A check that fails in a way it did not foresee is a finding on that device, never a traceback."""
        try:
            step(name)
        except DeviceError as exc:
            self.add(name, check, "problem", "", f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001 - the self-test reports, whatever the device did
            self.add(name, check, "problem", "", f"the check failed: {type(exc).__name__}: {exc}")

    def device(self, name: str):
        return self.devices[name][1]

    def ready(self, name: str) -> bool:
        return self.device(name).state is DeviceState.READY

    def not_ready(self, name: str, check: str) -> None:
        self.add(name, check, "skipped", "", f"not checked: {name} is not connected (see its link)")

    # -- 1. link ----------------------------------------------------------------------------------------

    def link(self, name: str) -> None:
        kind, dev = self.devices[name]
        backend = self.backend(name)
        connect_s = None
        if dev.state is not DeviceState.READY:
            before = self.errors.get(name)
            t0 = time.monotonic()
            try:
                try:
                    dev.close()  # a faulted link is dropped before it is made again
                except Exception:  # noqa: BLE001, S110 - closing is best effort
                    pass
                dev.connect()
                connect_s = time.monotonic() - t0
            except Exception as exc:  # noqa: BLE001 - any failure is the finding
                self.add(name, "link", "problem", f"no connection ({time.monotonic() - t0:.2f} s)",
                         self.no_link(name, exc, before))
                return
        figure = [f"connected in {connect_s * 1e3:.0f} ms" if connect_s is not None else "connected"]
        version = self.version(name)
        if version:
            figure.append(version)
        latency, what = self.latency(name)
        if latency is not None:
            figure.append(f"{what} {latency * 1e3:.1f} ms")
        if latency is not None and latency > SLOW_REPLY_S and kind != "camera":
            self.add(name, "link", "problem", ", ".join(figure),
                     f"a {what.split(' (')[0]} takes {latency * 1e3:.0f} ms (median of 3; expected under "
                     f"{SLOW_REPLY_S * 1e3:.0f} ms): the link is slow; check the network or serial line and the "
                     f"device's reply settings ({self.address(name) or backend})")
            return
        self.add(name, "link", "ok", ", ".join(figure))

    def backend(self, name: str) -> str:
        kind = self.devices[name][0]
        return (self.config.cameras[name] if kind == "camera" else getattr(self.config, kind)).backend

    def options(self, name: str) -> dict:
        kind = self.devices[name][0]
        return (self.config.cameras[name] if kind == "camera" else getattr(self.config, kind)).options

    def address(self, name: str) -> str:
        """The options that say where the device is, as the cell file has them (with the driver's defaults)."""
        backend = self.backend(name)
        settings = getattr(self.device(name), "settings", None)
        keys = ADDRESS_OPTIONS.get(backend) or tuple(k for k in self.options(name)
                                                     if any(w in k for w in ADDRESS_WORDS))
        values = []
        for key in keys:
            value = getattr(settings, key, self.options(name).get(key))
            if value is not None:
                values.append(f"{key} {value}")
        return ", ".join(values)

    def no_link(self, name: str, exc: Exception, before: str | None) -> str:
        """Why `name` did not connect, and what to check (on a simulated cell whose protocol simulators did not
        start, that first)."""
        servers = self.errors.get("sim.servers")
        if servers and self.backend(name) in ADDRESS_OPTIONS:
            return (f"cannot connect: {type(exc).__name__}: {exc}; the cell's protocol simulators did not start "
                    f"({servers}): free their ports, or give sim.servers other ports (and the devices the same)")
        backend = self.backend(name)
        where = self.address(name)
        said = f"{type(exc).__name__}: {exc}"
        if backend in MODBUS_PROBES:
            probed = self.probe_modbus_ids(name)
            if probed is not None:
                return probed
        if backend in ("abb", "ur"):
            return (f"no answer from the {backend.upper()} controller ({where}): check {_keys(where)} and that the "
                    f"controller runs its server; {said}")
        section = f"cameras.{name}" if self.devices[name][0] == "camera" else name
        fix = f"check {_keys(where)} in the cell file ({section})" if where else \
            "check the cable, the power and the device's options in the cell file"
        seen = f" (at start: {before})" if before and before not in said else ""
        return f"cannot connect: {said}{seen}; {fix}"

    def probe_modbus_ids(self, name: str) -> str | None:
        """A Modbus gripper that does not answer its device id (silence on an RTU line, an exception from a Modbus
        TCP gateway): which ids do answer there (a short read of its state each), and the frames from other ids its
        link set aside. None when its own id answers now, or the link itself does not open (not an id problem)."""
        from drivers.grippers.modbus_link import ModbusLink

        dev = self.device(name)
        link = getattr(dev, "link", None)
        if link is None:
            return None
        address, count, function = MODBUS_PROBES[self.backend(name)]
        config = link.config
        strays = sorted({frame[0] for kind, frame in link.wire_log if kind == "stray" and frame})

        def answers(device_id: int, timeout_s: float) -> bool:
            probe = ModbusLink(f"{name} probe", replace(config, device_id=device_id, timeout_s=timeout_s, retries=0))
            try:
                probe.open()
                probe.read(address, count, function=function)
                return True
            except DeviceError as exc:
                if not probe.is_open and "could not" in str(exc):  # the port or host itself: not an id problem
                    raise
                return False
            finally:
                probe.close()

        try:
            if answers(config.device_id, config.timeout_s):
                return None  # its own id answers now: not an addressing problem
        except DeviceError:
            return None  # the link does not open: said as it is
        answered = []
        for device_id in PROBE_IDS:
            if device_id != config.device_id and answers(device_id, 0.05):
                answered.append(device_id)
                break
        where = (f"{config.serial_port} at {config.baudrate}" if config.kind == "serial"
                 else f"{config.host}:{config.port} ({'Modbus TCP' if config.kind == 'tcp' else 'RTU over TCP'})")
        seen = [f"frames from device {i} seen" for i in strays] + [f"device {i} answered" for i in answered
                                                                   if i not in strays]
        hint = "; ".join(seen) if seen else f"no other device id answered ({', '.join(map(str, PROBE_IDS))} tried)"
        fix = (f"check device_id (the gripper answers as {answered[0]}: set device_id: {answered[0]})" if answered
               else "check device_id, the cable, the power and the line's speed (baudrate)")
        return f"no answer from device {config.device_id} on {where}: {fix}; {hint}"

    def version(self, name: str) -> str:
        """What the device says it is, where its backend can say."""
        dev = self.device(name)
        world = getattr(dev, "world", None)
        if world is not None and hasattr(world, "seed"):
            from drivers.sim.kinds import world_kind

            return f"simulated ({world_kind(world.config)} world, simulation seed {world.seed})"
        try:
            if hasattr(dev, "robot_info"):  # ABB: serial*software*type
                info = dev.robot_info()
                return f"{info.robot_type}, software {info.software}, serial {info.serial}"
            if hasattr(dev, "robot_mode"):  # UR: its mode (the PolyScope version is not on RTDE)
                return f"robot mode {dev.robot_mode()}"
            applied = getattr(dev, "applied", None)  # GenICam: what the camera reports it applied
            if applied:
                return ", ".join(f"{k} {v:g}" for k, v in applied.items())
        except DeviceError as exc:
            return f"version not read ({exc})"
        return ""

    def latency(self, name: str) -> tuple[float | None, str]:
        kind, dev = self.devices[name]
        if kind == "arm":
            read, what = dev.pose, "pose read"
        elif kind == "gripper":
            read, what = dev.status, "status read"
        elif kind == "camera":
            t0 = time.monotonic()
            self.frames[name] = dev.capture()
            return time.monotonic() - t0, "frame"
        else:
            return None, ""
        times = []
        for _ in range(3):
            t0 = time.monotonic()
            read()
            times.append(time.monotonic() - t0)
        return statistics.median(times), f"{what} (median of 3)"

    # -- 2. readings ------------------------------------------------------------------------------------

    def readings(self, name: str) -> None:
        kind, dev = self.devices[name]
        if not self.ready(name):
            return self.not_ready(name, "readings")
        if kind == "arm":
            return self.arm_readings(name, dev)
        if kind == "gripper":
            s = dev.status()
            figure = f"vacuum {s.vacuum_kpa:.1f} kPa, object {'yes' if s.object_detected else 'no'}, " \
                     f"generator {'on' if s.gripping else 'off'}"
            if s.object_detected:
                return self.add(name, "readings", "problem", figure,
                                "the gripper reports an object: take it off the nozzle before commissioning (if "
                                "nothing is there, the nozzle is blocked or the detection level is too low)")
            return self.add(name, "readings", "ok", figure)
        if kind == "camera":
            frame = self.frames[name] = dev.capture()  # a second frame: the camera goes on delivering
            image = np.asarray(frame.image)
            h, w = image.shape[:2]
            figure = f"frame {frame.frame_id}: {w} x {h} px, {image.dtype}"
            if frame.exposure_s:
                figure += f", exposure {frame.exposure_s:g} s"
            if tuple(dev.resolution) != (w, h):
                return self.add(name, "readings", "problem", figure,
                                f"the frame is {w} x {h} px, the camera says {dev.resolution[0]} x "
                                f"{dev.resolution[1]}: check the camera's width/height settings (or binning)")
            return self.add(name, "readings", "ok", figure)
        return None

    def arm_readings(self, name: str, arm) -> None:
        p = arm.pose()
        j = arm.joints()
        joints = ", ".join(f"{v:.4f}" for v in j.positions)
        figure = (f"x {p.x * 1e3:.3f}, y {p.y * 1e3:.3f}, z {p.z * 1e3:.3f} mm, alpha "
                  f"{math.degrees(p.alpha):.2f} deg; joints [{joints}]")
        outside = self.outside_box(p)
        if outside:
            return self.add(name, "readings", "problem", figure,
                            f"the arm's pose: {outside}: check arm.limits, or the arm's "
                            "units and frame (tool, work object) on the controller")
        self.add(name, "readings", "ok", figure)

    def outside_box(self, p: Pose) -> str | None:
        """Why `p` is outside the cell file's workspace box (arm.limits), or None."""
        limits = self.config.arm.options.get("limits")
        try:
            check_in_box(p, WorkspaceBox.model_validate(limits) if limits else None)
        except PathError as exc:
            return str(exc).removeprefix("target ")  # "z_mm=45.000 is outside the workspace box [-5, 40] ..."
        return None

    # -- 3. motion ------------------------------------------------------------------------------------------

    def watching(self) -> list[str]:
        return [n for n, (kind, _) in self.devices.items() if kind == "camera" and self.only in (None, "arm", n)
                and self.ready(n)]

    def motion(self) -> None:
        if "arm" not in self.devices:
            return
        if not self.move:
            self.add("arm", "motion", "skipped", "",
                     f"the arm moves {MOVE_MM:g} mm and back only when you confirm it: give --move (or --yes), or "
                     "answer y at the prompt")
            return
        if not self.ready("arm"):
            return self.not_ready("arm", "motion")
        arm = self.device("arm")
        start = arm.pose()
        target = None
        refused = []
        for axis, sign in (("x", 1), ("x", -1), ("y", 1), ("y", -1)):
            d = sign * MOVE_MM * 1e-3
            candidate = replace(start, x=start.x + d) if axis == "x" else replace(start, y=start.y + d)
            why = self.outside_box(candidate)
            if why is None and isinstance(arm, ChecksTargets):  # the arm's own check: reach, joint limits
                try:
                    arm.check_target(candidate)
                except MotionRejected as exc:
                    why = str(exc)
            if why is None:
                target, direction = candidate, f"{'+' if sign > 0 else '-'}{axis}"
                break
            refused.append(why)
        if target is None:
            self.add("arm", "motion", "problem", "",
                     f"no {MOVE_MM:g} mm move along x or y from here stays in the workspace box and the arm's limits "
                     f"({refused[0]}): jog the arm inwards and run the self-test again")
            return
        cameras = self.watching()
        failed: dict[str, str] = {}

        def frames() -> dict:
            taken = {}
            for n in cameras:
                if n in failed:
                    continue
                try:
                    taken[n] = self.device(n).capture()
                except DeviceError as exc:  # that camera drops out of the check; the arm still comes back
                    failed[n] = f"{type(exc).__name__}: {exc}"
            return taken

        before = frames()
        try:
            arm.move_linear(target, MOVE_SPEED_M_S)
            there = arm.pose()
            moved = frames()
        except BaseException:
            try:  # back where it was if it can (what stopped it is the finding, not this)
                if arm.state is DeviceState.READY and float(np.linalg.norm(arm.pose().xyz - start.xyz)) > 1e-6:
                    arm.move_linear(start, MOVE_SPEED_M_S)
            except DeviceError:
                pass
            raise
        arm.move_linear(start, MOVE_SPEED_M_S)
        back = arm.pose()
        after = frames()
        cameras = [n for n in cameras if n not in failed]
        for n, why in failed.items():
            self.add(n, "motion seen", "problem", "", f"no frame during the arm's move: {why}")
        reported = float(np.linalg.norm(there.xyz - start.xyz) * 1e3)
        returned = float(np.linalg.norm(back.xyz - start.xyz) * 1e3)
        figure = (f"asked {MOVE_MM:.2f} mm ({direction}) at {MOVE_SPEED_M_S * 1e3:g} mm/s, reported "
                  f"{reported:.3f} mm, back within {returned:.3f} mm")
        arm_row = self.add("arm", "motion", "ok", figure)
        if abs(reported - MOVE_MM) > ARM_TOLERANCE_MM or returned > ARM_TOLERANCE_MM:
            arm_row.result = "problem"
            arm_row.finding = (f"asked {MOVE_MM:.2f} mm, the arm reports {reported:.3f} mm (and {returned:.3f} mm "
                               "off its start after the move back): check the arm's units and its speed/zone "
                               "settings, and that nothing stops it")
        seen = {}
        for n in cameras:
            seen[n] = self.motion_seen(n, before[n], moved[n], after[n], reported)
        self.judge_motion(arm_row, reported, seen)

    def motion_seen(self, camera: str, before, moved, after, reported_mm: float) -> dict:
        """How far `camera` saw things move: {"px", "mm" (None: no scale), "scale" (how), "back_px", "how"}."""
        shift = image_shift(before.image, moved.image)
        if shift is None:
            return {"px": None}
        px, how, uv0, uv1 = shift
        back = image_shift(before.image, after.image)
        out = {"px": px, "how": how, "back_px": back[0] if back else None, "mm": None, "scale": None}
        mm = self.located_mm(camera, uv0, uv1)
        if mm is not None:
            out["mm"], out["scale"] = mm, "its active calibration"
        else:
            scale = self.nominal_scale(camera)
            if scale is not None:
                um_per_px, source = scale
                out["mm"], out["scale"] = px * um_per_px * 1e-3, f"{um_per_px:.2f} um/px from {source}"
        return out

    def located_mm(self, camera: str, uv0, uv1) -> float | None:
        """The move between two pixels in mm by the camera's active planar calibration (a fixed camera only)."""
        if uv0 is None or camera not in self.calibrations:
            return None
        try:
            from calibration.usage import CellCalibration

            cal = CellCalibration(self.calibrations)
            if cal.rides_arm(camera):
                return None
            xy = cal.locate(camera, [tuple(uv0), tuple(uv1)], None)
        except Exception:  # noqa: BLE001 - no usable calibration: the nominal scale then
            return None
        xy = np.asarray(xy, dtype=float)
        return float(np.linalg.norm(xy[1] - xy[0]) * 1e3)

    def nominal_scale(self, camera: str) -> tuple[float, str] | None:
        """um per pixel from the area the camera serves: its size_mm (the field of view) over the resolution."""
        w, h = self.device(camera).resolution
        for name, area in self.config.areas.items():
            if area.camera == camera:
                um = (area.size_mm[0] / w + area.size_mm[1] / h) / 2 * 1e3
                return um, f"areas.{name}.size_mm"
        return None

    def judge_motion(self, arm_row: Check, reported: float, seen: dict) -> None:
        measured = {n: s for n, s in seen.items() if s.get("px") is not None and s["px"] >= 2.0}
        in_mm = {n: s for n, s in measured.items() if s["mm"] is not None}
        ratios = {n: s["mm"] / reported for n, s in in_mm.items()} if reported > 0 else {}
        off = {n: r for n, r in ratios.items() if abs(r - 1) > SCALE_TOLERANCE}
        all_agree = len(ratios) >= 2 and len(off) == len(ratios) and max(ratios.values()) - min(ratios.values()) < \
            SCALE_TOLERANCE
        for n, s in seen.items():
            if s.get("px") is None or s["px"] < 2.0:
                self.add(n, "motion seen", "info", "nothing moved in view" if s.get("px") is not None else
                         "nothing to track in view",
                         f"{n} saw nothing move with the arm: bring the arm (or a target it carries) into its view to "
                         "check it against the arm's move")
                continue
            figure = f"{s['px']:.1f} px ({s['how']})"
            if s["mm"] is not None:
                figure = f"{s['mm']:.2f} mm = {figure}, scale: {s['scale']}"
            row = self.add(n, "motion seen", "ok" if s["mm"] is not None else "info", figure)
            if s["mm"] is None:
                row.finding = (f"no scale known for {n} (no planar calibration, no area): its {s['px']:.1f} px "
                               "cannot be compared with the arm's mm; calibrate it to compare")
            elif n in off:
                row.result = "problem"
                if all_agree:
                    row.finding = (f"arm: moved {reported:.2f} mm, {n} saw {s['mm']:.2f} mm, as every camera did "
                                   f"(x{ratios[n]:.3f}): check the arm's units (or its scale)")
                else:
                    row.finding = (f"arm: moved {reported:.2f} mm, {n} saw {s['mm']:.2f} mm: check {n}'s um_per_px "
                                   f"({s['scale']}) or the arm's units")
            if s.get("back_px") is not None and s["back_px"] > RETURN_TOLERANCE_PX:
                row.result = "problem"
                row.finding = "; ".join(f for f in (row.finding, (
                    f"after the move back {n} sees the view {s['back_px']:.1f} px from where it started: a loose camera "
                    "mount, or the arm does not come back (backlash)")) if f)
        if all_agree and arm_row.result == "ok":
            arm_row.result = "problem"
            saw = ", ".join(f"{n} {in_mm[n]['mm']:.2f} mm" for n in ratios)
            arm_row.finding = f"moved {reported:.2f} mm, every camera saw {saw}: check the arm's units (or its scale)"

    # -- 4. grip with nothing held ----------------------------------------------------------------------

    def grip(self, name: str) -> None:
        if not self.ready(name):
            return self.not_ready(name, "grip with nothing held")
        gripper = self.device(name)
        rest = gripper.status()
        if rest.object_detected:
            return self.add(name, "grip with nothing held", "skipped", "",
                            "the gripper holds something: take it off the nozzle, then run the self-test again")
        try:
            detected = gripper.grip()
            on = gripper.status()
        finally:
            gripper.release()
        off = gripper.status()
        figure = (f"vacuum {rest.vacuum_kpa:.1f} kPa at rest, {on.vacuum_kpa:.1f} kPa on, {off.vacuum_kpa:.1f} kPa "
                  f"released; object {'detected' if detected or on.object_detected else 'none'}")
        if detected or on.object_detected:
            return self.add(name, "grip with nothing held", "problem", figure,
                            f"it detects an object with nothing held ({on.vacuum_kpa:.1f} kPa): the nozzle is "
                            "blocked or taped over, or the detection level is below what an open nozzle pulls; clean "
                            "the nozzle and check the detection vacuum (e.g. detect_vacuum_kpa)")
        if on.vacuum_kpa - rest.vacuum_kpa < 0.5:
            return self.add(name, "grip with nothing held", "problem", figure,
                            f"the vacuum stayed at {on.vacuum_kpa:.1f} kPa with the generator on: no vacuum supply; "
                            "check the air supply, the valve and the hose")
        if off.vacuum_kpa > rest.vacuum_kpa + 2.0:
            return self.add(name, "grip with nothing held", "problem", figure,
                            f"the vacuum did not go after the release ({off.vacuum_kpa:.1f} kPa): check the release "
                            "valve (or use an active release)")
        self.add(name, "grip with nothing held", "ok", figure)

    # -- 5. focus and exposure ------------------------------------------------------------------------------

    def frame(self, name: str):
        frame = self.frames.get(name)
        if frame is None:
            frame = self.frames[name] = self.device(name).capture()
        return frame

    def focus(self, name: str) -> None:
        if not self.ready(name):
            return self.not_ready(name, "focus")
        image = np.asarray(self.frame(name).image)
        sharp = sharpness(image)
        figure = f"Laplacian variance {sharp['laplacian_var']:.3g}"
        if sharp["blur_px"] is None:
            return self.add(name, "focus", "info", figure + ", no edge in view",
                            "no edge in view to judge the focus by: put a target (the calibration grid, a part) in "
                            "its view and run the self-test again")
        figure = f"edge blur {sharp['blur_px']:.1f} px (sigma), {figure}"
        if sharp["blur_px"] > BLURRED_PX:
            return self.add(name, "focus", "problem", figure,
                            f"edges blurred over {sharp['blur_px']:.1f} px (sigma; in focus: under {BLURRED_PX:g} px): "
                            f"focus {name}'s lens on the working plane (or check the working distance)")
        self.add(name, "focus", "ok", figure)

    def exposure(self, name: str) -> None:
        if not self.ready(name):
            return self.not_ready(name, "exposure")
        frame = self.frame(name)
        image = np.asarray(frame.image)
        full = float(np.iinfo(image.dtype).max) if image.dtype.kind in "ui" else float(image.max() or 1.0)
        saturated = float(np.mean(image >= full))
        mean = float(image.mean()) / full
        figure = f"saturated {saturated * 100:.2f} %, mean level {mean * 100:.1f} % of full scale"
        key, value, unit = self.exposure_setting(name, frame)
        if saturated > SATURATED_FRACTION:
            factor = 0.5 if saturated > 0.05 else 0.7
            return self.add(name, "exposure", "problem", figure,
                            f"{saturated * 100:.0f} % of pixels saturated: lower {key}"
                            + (f" from {value:g} to about {value * factor:.3g} {unit}" if value else "")
                            + " (or the light, or the gain)")
        if mean < DARK_MEAN:
            factor = min(0.08 / max(mean, 1e-4), 50.0)
            return self.add(name, "exposure", "problem", figure,
                            f"the image is dark (mean {mean * 100:.1f} % of full scale): raise {key}"
                            + (f" from {value:g} to about {value * factor:.3g} {unit}" if value else "")
                            + " (or the light, or the gain); check the lens cap and the aperture")
        self.add(name, "exposure", "ok", figure)

    def exposure_setting(self, name: str, frame) -> tuple[str, float | None, str]:
        """The cell file key that sets the camera's exposure, its value now (as the frame says) and its unit."""
        exposure = float(frame.exposure_s) if frame.exposure_s else None
        settings = getattr(self.device(name), "settings", None)
        if settings is not None and "exposure_s" in type(settings).model_fields:
            return f"cameras.{name}.exposure_s", exposure, "s"
        sim_name = getattr(self.device(name), "sim_name", None)
        if sim_name is not None:  # a simulated camera without its own setting: its world's
            return f"sim.cameras.{sim_name}.exposure_ms", exposure * 1e3 if exposure else None, "ms"
        return f"the exposure of {name}", exposure, "s"


# -- measurements on images -----------------------------------------------------------------------------------


def image_shift(a, b) -> tuple[float, str, tuple | None, tuple | None] | None:
    """How far the content of image `b` lies from `a`'s, px: the move of the bright features (nozzle, spheres, a
    board's white squares) found in both, as the one translation that carries the most of `a`'s features onto
    `b`'s (within SHIFT_TOLERANCE_PX), then the median of the matched moves. Returns (px, how, a feature's pixel in
    a, its pixel in b), or None when nothing can be tracked. Nearest neighbours are not enough: a camera on the arm
    sees every feature move by the whole move (800 px for 5 mm on the micro cell's), further than the spheres lie
    apart, and would pair each with its neighbour. (A whole-view shift by phase correlation was tried: on a
    simulated camera it locks onto the sensor noise, which is drawn at a new offset each frame, so it is not
    used.)"""
    (pa, what), (pb, _) = tracked_points(a), tracked_points(b)
    pairs = matched_by_translation(pa, pb)
    if not pairs:
        return None
    moves = [float(np.hypot(*(pb[j] - pa[i]))) for i, j in pairs]
    k = int(np.argsort(moves)[len(moves) // 2])
    i, j = pairs[k]
    return (statistics.median(moves), f"{len(pairs)} {what}{'s' if len(pairs) > 1 else ''} tracked", tuple(pa[i]),
            tuple(pb[j]))


SHIFT_TOLERANCE_PX = 4.0  # a feature carried by the view's translation lands this near its new place
SHIFT_CANDIDATES = 30  # features of `a` whose pairings with every feature of `b` are tried as the translation


def matched_by_translation(pa: np.ndarray, pb: np.ndarray) -> list[tuple[int, int]]:
    """The pairs (i, j) of the translation pa[i] -> pb[j] that most features share; among equally supported ones,
    the shortest (a regular pattern leaves its period unknown: the nearest is assumed, as before)."""
    from scipy.spatial import cKDTree

    if not len(pa) or not len(pb):
        return []
    tree = cKDTree(pb)
    central = np.argsort(np.hypot(*(pa - pa.mean(axis=0)).T))[:SHIFT_CANDIDATES]
    best: tuple[int, float] | None = None
    best_pairs: list[tuple[int, int]] = []
    for v in (pb[None, :, :] - pa[central, None, :]).reshape(-1, 2):
        d, j = tree.query(pa + v, distance_upper_bound=SHIFT_TOLERANCE_PX)
        hit = np.isfinite(d)
        score = (int(hit.sum()), -float(np.hypot(*v)))
        if best is None or score > best:
            best, best_pairs = score, [(int(i), int(j[i])) for i in np.flatnonzero(hit)]
    return best_pairs


def tracked_points(image) -> tuple[np.ndarray, str]:
    """The pixels a camera can follow between two frames: its bright features (nozzle, spheres, a board's white
    squares, a CSM fixture's white mark)."""
    from calibration.vision.features import find_features

    return np.array([[f.blob.u, f.blob.v] for f in find_features(image)]).reshape(-1, 2), "feature"


def _grey(image) -> np.ndarray:
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    img = img.astype(np.float32)
    full = float(np.iinfo(image.dtype).max) if np.asarray(image).dtype.kind in "ui" else 1.0
    return img / full


def sharpness(image) -> dict:
    """The focus figures of a frame: the variance of the Laplacian (of the grey levels as fractions of full scale;
    it grows with sharp content and with noise), and the blur of the sharpest edges in view as a Gaussian sigma in
    px (a blurred step of contrast C has a steepest gradient of C / (sqrt(2 pi) sigma); measured after a 1 px
    smoothing that takes the noise out, which is then taken back out of the sigma). No edge stands out from the
    noise: blur_px None."""
    import cv2

    grey = _grey(image)
    laplacian = float(cv2.Laplacian(grey, cv2.CV_32F).var())
    smooth = cv2.GaussianBlur(grey, (0, 0), 1.0)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3) / 8
    magnitude = np.hypot(gx, gy)
    step = 1.0 / float(np.iinfo(np.asarray(image).dtype).max) if np.asarray(image).dtype.kind in "ui" else 1e-6
    noise = max(float(np.median(np.abs(grey - cv2.medianBlur(grey, 3)))) * 1.4826, step)  # at least one grey level
    steepest = float(magnitude.max())
    at = np.unravel_index(int(np.argmax(magnitude)), magnitude.shape)
    # the edge's contrast: the spread of levels around the steepest point
    r = 12
    patch = smooth[max(at[0] - r, 0):at[0] + r + 1, max(at[1] - r, 0):at[1] + r + 1]
    contrast = float(np.percentile(patch, 98) - np.percentile(patch, 2)) if patch.size else 0.0
    if steepest <= 0 or contrast < EDGE_CONTRAST_NOISE * noise:
        return {"laplacian_var": laplacian, "blur_px": None}
    sigma = contrast / (math.sqrt(2 * math.pi) * steepest)
    if sigma * 4 > r:  # a wide edge: the patch did not hold its whole contrast; measure over a wider one
        r = int(min(sigma * 6, 200))
        patch = smooth[max(at[0] - r, 0):at[0] + r + 1, max(at[1] - r, 0):at[1] + r + 1]
        contrast = float(np.percentile(patch, 98) - np.percentile(patch, 2))
        sigma = contrast / (math.sqrt(2 * math.pi) * steepest)
    return {"laplacian_var": laplacian, "blur_px": float(math.sqrt(max(sigma ** 2 - 1.0, 0.0)))}


# -- the cell's devices and its workspace box ----------------------------------------------------------------


def check_device(cell, config, device: str | None) -> None:
    """NotFound naming the cell's devices when `device` is not one of them (None: all of them)."""
    names = list(devices_of(cell))
    if device is not None and device not in names:
        from cellctl.errors import NotFound

        raise NotFound(f"device: {device!r} is not a device of cell {config.cell.name!r}; devices: "
                       f"{', '.join(names)}")


def motion_detail() -> dict:
    """What the self-test's motion is, for the audit."""
    return {"move_mm": MOVE_MM, "speed_mm_s": MOVE_SPEED_M_S * 1e3, "checked": "against arm.limits before it is sent"}


def devices_of(cell) -> dict[str, tuple[str, object]]:
    """name -> (kind, device) of what a self-test checks: the arm, the gripper and the cameras (the operator is a
    person), in the cell file's order."""
    return {name: (kind, dev) for kind, name, dev in cell.named_devices() if kind != "operator"}


def _keys(where: str) -> str:
    """"host 1.2.3.4, port 5" -> "host and port" (the options to check)."""
    keys = [part.split(" ")[0] for part in where.split(", ") if part]
    if not keys:
        return "the device's address options"
    return keys[0] if len(keys) == 1 else ", ".join(keys[:-1]) + " and " + keys[-1]


def commission(cell, config, *, device: str | None = None, move: bool = False, errors: dict | None = None,
               calibrations: dict | None = None) -> dict:
    """The self-test of `cell` (see the module docstring): {"cell", "simulated", "device", "moved", "checks":
    [{"device", "check", "result", "figure", "finding"}], "problems", "findings", "seconds"}."""
    return Commissioning(cell, config, device=device, move=move, errors=errors, calibrations=calibrations).run()
