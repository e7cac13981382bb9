"""Step actions shared by routines: go somewhere, look, measure the feature."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from drivers.interfaces import Frame, Pose, move_via

from calibration.errors import CalibrationInputError, VisionError
from calibration.models.tool_offset import rot
from calibration.routines.base import Devices, Step
from calibration.usage import CellCalibration, ToolCompensatedArm
from calibration.vision.centroid import find_blob


@dataclass(frozen=True)
class Look:
    """What a visit captured (`look`): processed by `measure_look`, in a worker thread if need be."""

    target: Pose
    camera: str
    reported: Pose
    frame: Frame


def visit_pose(step: Step) -> Pose:
    """Where a visit step measures (its args x, y, z, alpha)."""
    a = step.args
    return Pose(a["x"], a["y"], a["z"], a["alpha"])


def look(devices: Devices, target: Pose, camera: str) -> Look:
    """At `target` (the arm already there): the reported pose and a frame."""
    reported = devices.arm.pose()
    return Look(target, camera, reported, devices.camera(camera).capture())


def measure_look(seen: Look, polarity: str = "bright") -> tuple[dict, Frame]:
    """Find the one feature in a frame `look` took. A frame without a usable feature is a sample too (status
    'no-feature', the reason in 'message'): the report lists it, fits skip it. No device access."""
    target, reported, frame = seen.target, seen.reported, seen.frame
    row = {"camera": seen.camera, "frame_id": frame.frame_id,
           "cmd_x_mm": target.x * 1e3, "cmd_y_mm": target.y * 1e3, "z_mm": reported.z * 1e3,
           "x_mm": reported.x * 1e3, "y_mm": reported.y * 1e3, "alpha_abs_deg": math.degrees(reported.alpha)}
    try:
        blob = find_blob(frame.image, polarity=polarity)
    except VisionError as exc:
        row.update(status="no-feature", u_px=math.nan, v_px=math.nan, diameter_px=math.nan, snr=math.nan,
                   message=str(exc))
    else:
        row.update(status="ok", u_px=blob.u, v_px=blob.v, diameter_px=blob.diameter_px, snr=blob.snr, message="")
    return row, frame


def visit_and_measure(devices: Devices, target: Pose, camera: str, polarity: str = "bright") -> tuple[dict, Frame]:
    """Move to `target`, capture, find the one feature: the move, `look` and `measure_look` in a row."""
    devices.arm.move_linear(target)
    return measure_look(look(devices, target, camera), polarity)


CLEARANCE = 3e-3  # m above a part or a surface for moves over it


def pick_sphere(devices: Devices, supply_xy: tuple[float, float], contact_z: float, alpha: float) -> None:
    """Over the feeder, down onto the sphere (the nozzle's spring takes up the diameter tolerance),
    vacuum on, up. `contact_z`: the tip height touching the smallest sphere the tolerance allows."""
    x, y = supply_xy
    move_via(devices.arm, Pose(x, y, contact_z + CLEARANCE, alpha))  # passed on the way down: no settling there
    devices.arm.move_linear(Pose(x, y, contact_z, alpha))
    held = devices.gripper.grip()
    move_via(devices.arm, Pose(x, y, contact_z + CLEARANCE, alpha))
    if not held:
        raise CalibrationInputError(f"no sphere picked at the supply ({x * 1e3:.3f}, {y * 1e3:.3f}) mm: "
                                    "is the feeder loaded and its position right?")


def measure_centring(devices: Devices, area_name: str | None, sphere_diameter: float,
                     alpha: float) -> tuple[np.ndarray, list[Frame]]:
    """How far the held sphere sits off the nozzle (seed 001 6.2.2: the calibrated camera 1 supports area2),
    and the frame it was measured in; no area: no measurement, zero offset.

    The nozzle holds the sphere's centre in the area's plane over its centre, at the alpha its camera was
    calibrated at; that camera's active map gives the robot position that would put the bare nozzle
    where the sphere is seen, so the difference to the reported position is the sphere's offset on the
    nozzle. Returned turned to `alpha` (the offset turns with the nozzle). A sphere not seen is a fault
    for the operator: it is still held (dropping it would litter the area)."""
    if area_name is None:
        return np.zeros(2), []
    area = devices.area(area_name)
    z = area.z + sphere_diameter / 2
    row, frame = visit_and_measure(devices, Pose(*area.centre, z, area.alpha_cal), area.camera)
    if row["status"] != "ok":
        raise VisionError(f"the held sphere is not seen by {area.camera} over {area.name}: {row['message']}")
    cal = CellCalibration(devices.calibrations)
    seen = cal.locate(area.camera, [row["u_px"], row["v_px"]])[0]
    # off the nozzle, not off the axis: a nozzle touched up since the maps sits tool_shift(0) from where they expect it
    offset = seen - np.array([row["x_mm"], row["y_mm"]]) * 1e-3 - cal.tool_shift(0.0)
    return rot(alpha - area.alpha_cal) @ offset, [frame]


def place_held_sphere(devices: Devices, target: Pose, offset, alpha_cal: float) -> tuple[np.ndarray, Pose]:
    """Place the held sphere, `offset` off the nozzle (measure_centring), so that it lands on `target`: the nozzle
    goes off the target by the offset, the axis off the nozzle by the tool compensation. Returns where the sphere
    lands by the controller's reported pose at the release (m, x y), and that pose."""
    cal = CellCalibration(devices.calibrations)
    arm = ToolCompensatedArm(devices.arm, cal, alpha_cal)
    reported = place_sphere(replace(devices, arm=arm), Pose(target.x - offset[0], target.y - offset[1], target.z,
                                                            target.alpha))
    return np.array([reported.x, reported.y]) + offset + cal.tool_shift(target.alpha - alpha_cal), reported


@dataclass
class Delivered:
    """A sphere picked, centred, placed and looked at (deliver_sphere)."""

    offset: np.ndarray  # its offset on the nozzle as measured (m; zero without a centring area)
    landed: np.ndarray  # where it lands by the controller's reported pose (m)
    reported: Pose  # the pose at the release
    frames: list  # the centring frame (if measured), then the camera's view from the park position


def deliver_sphere(devices: Devices, pick_xy, pick_contact: float, target: Pose, alpha_cal: float,
                   centring_area: str | None, sphere_diameter: float, park_xyz, camera: str,
                   carry_alpha: float) -> Delivered:
    """Pick a sphere at `pick_xy`, measure its offset on the nozzle with `centring_area`'s camera, place it on
    `target` compensated (place_held_sphere), park out of view at `carry_alpha` and capture with `camera`."""
    pick_sphere(devices, pick_xy, pick_contact, carry_alpha)
    offset, frames = measure_centring(devices, centring_area, sphere_diameter, target.alpha)
    landed, reported = place_held_sphere(devices, target, offset, alpha_cal)
    devices.arm.move_linear(Pose(*park_xyz, carry_alpha))
    return Delivered(offset, landed, reported, [*frames, devices.camera(camera).capture()])


def deliver_from_supply(devices: Devices, params, target: Pose, centring_area: str | None, camera: str) -> Delivered:
    """deliver_sphere from the feeder a routine's parameters name (supply_mm, supply_z_mm, park_mm and the
    spheres' size), carried at the target's rotation (its alpha_cal)."""
    contact = (params.supply_z_mm + params.sphere_diameter_mm - params.sphere_tolerance_mm) * 1e-3
    return deliver_sphere(devices, tuple(v * 1e-3 for v in params.supply_mm), contact, target, target.alpha,
                          centring_area, params.sphere_diameter_mm * 1e-3, tuple(v * 1e-3 for v in params.park_mm),
                          camera, target.alpha)


def new_spheres(blobs, seen: list[tuple[float, float]], apart_px: float = 20.0) -> list:
    """The blobs farther than `apart_px` from every sphere seen before: the ones just placed."""
    return [b for b in blobs if all(math.hypot(b.u - u, b.v - v) > apart_px for u, v in seen)]


def place_sphere(devices: Devices, target: Pose) -> Pose:
    """Down onto the surface at `target` (its z: tip height touching the smallest sphere), vacuum off, up.
    Returns the pose the controller reported at the release."""
    above = Pose(target.x, target.y, target.z + CLEARANCE, target.alpha)
    move_via(devices.arm, above)  # passed on the way down: no settling there
    devices.arm.move_linear(target)
    reported = devices.arm.pose()
    devices.gripper.release()
    move_via(devices.arm, above)
    return reported
