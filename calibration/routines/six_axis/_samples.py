"""The samples of a hand-eye calibration, and pose pairs from elsewhere, read into what the fit needs.

A run records one row per board corner seen (`corner_id`, `u_px`, `v_px`) with the flange pose the arm reported
at that pose; a frame refused by the detector is one row with its status and the reason. A touch (set `touch`) is
one row: the corner a held-out view located (`touch_*_mm`, base frame) and the joints the tool tip reached it at. A file of pose pairs
(easy_handeye, MoveIt, a teach pendant) has one row per pose: the flange pose and the camera->board pose measured
there (`target_*`). Poses are `x_mm, y_mm, z_mm, qw, qx, qy, qz` (unit quaternion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.errors import CalibrationInputError
from calibration.models.hand_eye import View, pose_from_dict

POSE_FIELDS = ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")
FLANGE_COLUMNS = tuple(f"flange_{f}" for f in POSE_FIELDS)
TARGET_COLUMNS = tuple(f"target_{f}" for f in POSE_FIELDS)
JOINT_COLUMNS = tuple(f"j{i}_deg" for i in range(1, 7))
INTRINSIC_COLUMNS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3")
TOUCH_COLUMNS = ("touch_x_mm", "touch_y_mm", "touch_z_mm")
SAMPLE_COLUMNS = ("step", "pose", "set", "status", "camera", "frame_id", "width_px", "height_px", *JOINT_COLUMNS,
                  *FLANGE_COLUMNS, "corner_id", "u_px", "v_px", *INTRINSIC_COLUMNS, *TOUCH_COLUMNS, "message")
FIT_COLUMNS = ("pose", *FLANGE_COLUMNS)
MIN_POSES = 3


def _number(row: dict, column: str, where: str) -> float:
    value = row.get(column)
    if value is None or value == "":
        raise CalibrationInputError(f"{where}: column {column} is empty")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise CalibrationInputError(f"{where}: {column}={value!r} is not a number") from None
    if not math.isfinite(number):
        raise CalibrationInputError(f"{where}: {column}={value} is not a finite number")
    return number


def pose_of(row: dict, prefix: str, where: str) -> np.ndarray:
    """The 4x4 (m) of a row's `prefix_x_mm .. prefix_qz`; CalibrationInputError naming the column otherwise."""
    values = {f: _number(row, f"{prefix}_{f}", where) for f in POSE_FIELDS}
    try:
        return pose_from_dict(values)
    except CalibrationInputError as exc:
        raise CalibrationInputError(f"{where}: {prefix}_*: {exc}") from None


def _set_of(row: dict, where: str) -> str:
    value = row.get("set") or "cal"
    if value not in ("cal", "ver"):
        raise CalibrationInputError(f"{where}: set={value!r}; allowed: cal, ver (empty: cal)")
    return value


def has_corners(rows: list[dict]) -> bool:
    return any(r.get("corner_id") not in (None, "") for r in rows)


@dataclass
class ImageSamples:
    views: dict[str, list[View]]  # "cal" / "ver" -> views
    size: tuple[int, int]
    stored: dict | None  # the intrinsics the run used as stored (columns fx_px ..), None when fitted
    refused: list[dict]  # frames the detector refused: pose, reason
    touches: list[dict]  # the touch test's rows: pose, corner_id, touch_*_mm (floats), message


def is_touch(row: dict) -> bool:
    return row.get("set") == "touch"


def image_samples(rows: list[dict]) -> ImageSamples:
    by_pose: dict[str, list[dict]] = {}
    refused, touches = [], []
    for r in rows:
        if is_touch(r) and r.get("status", "ok") == "ok":
            where = f"touch {r.get('pose')}"
            touches.append({"pose": r.get("pose"), "corner_id": int(_number(r, "corner_id", where)),
                            **{c: _number(r, c, where) for c in TOUCH_COLUMNS}, "message": r.get("message") or ""})
            continue
        if r.get("status", "ok") != "ok":
            refused.append({"pose": r.get("pose"), "step": r.get("step"), "reason": r.get("message") or r.get("status")})
            continue
        by_pose.setdefault(str(r["pose"]), []).append(r)
    views: dict[str, list[View]] = {"cal": [], "ver": []}
    size, stored = None, None
    for pose, group in by_pose.items():
        where = f"pose {pose}"
        first = group[0]
        T = pose_of(first, "flange", where)
        ids = np.array([int(_number(r, "corner_id", where)) for r in group])
        uv = np.array([[_number(r, "u_px", where), _number(r, "v_px", where)] for r in group])
        if len(set(ids.tolist())) != len(ids):
            raise CalibrationInputError(f"{where}: a corner id appears twice")
        views[_set_of(first, where)].append(View(pose, T, ids, uv))
        if first.get("width_px") not in (None, ""):
            size = (int(_number(first, "width_px", where)), int(_number(first, "height_px", where)))
        if first.get("fx_px") not in (None, "") and stored is None:
            stored = {c: _number(first, c, where) for c in INTRINSIC_COLUMNS}
    if size is None:
        raise CalibrationInputError("the samples do not say the image size (columns width_px, height_px)")
    _enough(len(views["cal"]), "poses with board corners")
    return ImageSamples(views, size, stored, refused, touches)


@dataclass
class PosePairs:
    names: dict[str, list[str]]  # "cal" / "ver" -> pose names
    flange: dict[str, list[np.ndarray]]  # T_base_flange
    target: dict[str, list[np.ndarray]]  # T_camera_board


def pose_pairs(rows: list[dict]) -> PosePairs:
    if not rows:
        raise CalibrationInputError("no rows")
    missing = [c for c in ("pose", *FLANGE_COLUMNS, *TARGET_COLUMNS) if c not in rows[0]]
    if missing:
        raise CalibrationInputError(f"missing columns: {', '.join(missing)} (a pose-pair file has pose, "
                                    f"{', '.join(FLANGE_COLUMNS)}, {', '.join(TARGET_COLUMNS)}; optional: set, "
                                    f"{', '.join(JOINT_COLUMNS)})")
    out = PosePairs({"cal": [], "ver": []}, {"cal": [], "ver": []}, {"cal": [], "ver": []})
    seen: dict[str, int] = {}
    for i, r in enumerate(rows):
        where = f"row {i + 2}"  # the header is row 1
        name = str(r.get("pose") or "").strip()
        if not name:
            raise CalibrationInputError(f"{where}: column pose is empty")
        if name in seen:
            raise CalibrationInputError(f"{where}: pose {name!r} again (first on row {seen[name]}); each pose once")
        seen[name] = i + 2
        which = _set_of(r, where)
        out.names[which].append(name)
        out.flange[which].append(pose_of(r, "flange", where))
        out.target[which].append(pose_of(r, "target", where))
    _duplicates(out.flange["cal"], out.names["cal"])
    _enough(len(out.flange["cal"]), "calibration pose pairs")
    return out


def _duplicates(transforms: list[np.ndarray], names: list[str]) -> None:
    for i in range(len(transforms)):
        for j in range(i):
            if np.allclose(transforms[i], transforms[j], atol=1e-7):
                raise CalibrationInputError(f"poses {names[j]} and {names[i]} have the same flange pose: a duplicate "
                                            "adds nothing; remove it or record another pose")


def _enough(n: int, what: str) -> None:
    if n < MIN_POSES:
        raise CalibrationInputError(f"{n} {what}, fewer than the {MIN_POSES} a hand-eye fit needs (15 or more "
                                    "well-spread poses give a trustworthy result)")
