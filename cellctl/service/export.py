"""A calibration as a file for another program: JSON, OpenCV FileStorage YAML, or (an arm's) URDF.

    export_calibration(calibration, "json")   # id, target, routine, version, created, cell, model
    opencv_yaml(doc)                          # cv2.FileStorage can read it back
    export_calibration(arm, "urdf")           # the calibrated arm (geometry/urdf.py), its tool if it has one

Every calibration exports as json and opencv; an `arm` calibration (routine arm-kinematics: its model holds the
calibrated kinematic table) also as urdf.
"""

from __future__ import annotations

import json
import math
import re
from typing import get_args

from geometry.kinematic_table import KinematicTable
from geometry.urdf import urdf_of

from cellctl.errors import InvalidRequest
from cellctl.service.interface import Export, ExportFormat
from cellctl.stores.calibrations import Calibration

EXPORT_FORMATS: tuple[str, ...] = get_args(ExportFormat)
ANY_CALIBRATION = ("json", "opencv")  # what every calibration exports as
ARM_TARGET = "arm"  # the target of an arm's own geometry (arm-kinematics): it also exports as urdf


def formats_of(c: Calibration) -> tuple[str, ...]:
    """The formats calibration `c` exports as."""
    return (*ANY_CALIBRATION, "urdf") if c.target == ARM_TARGET else ANY_CALIBRATION


def check_format(format: str) -> None:
    """InvalidRequest unless `format` is an export format at all."""
    if format not in EXPORT_FORMATS:
        raise InvalidRequest(f"format: {format!r}; allowed: {', '.join(EXPORT_FORMATS)}")


def export_calibration(c: Calibration, format: ExportFormat) -> Export:
    """The calibration with its model, as `format` ("json", "opencv", or "urdf" for an `arm` calibration).
    InvalidRequest naming the formats this calibration allows when it does not export as `format`."""
    check_format(format)
    allowed = formats_of(c)
    if format not in allowed:
        raise InvalidRequest(f"format: {format!r} exports an arm's calibrated geometry (target {ARM_TARGET!r}); "
                             f"calibration {c.id} is of target {c.target!r} (routine {c.routine}); allowed for it: "
                             f"{', '.join(allowed)}")
    doc = {"id": c.id, "target": c.target, "routine": c.routine, "version": c.version, "created": c.created,
           "cell": c.cell, "model": c.model}
    if format == "json":
        return Export(json.dumps(doc, indent=2, allow_nan=False, default=str), "application/json",
                      f"calibration-{c.id}.json")
    if format == "urdf":
        return Export(arm_urdf(c), "application/xml", f"calibration-{c.id}.urdf")
    return Export(opencv_yaml(doc), "application/x-yaml", f"calibration-{c.id}.yaml")


def arm_urdf(c: Calibration) -> str:
    """The URDF of an `arm` calibration: its calibrated table, and its tool (T_flange_tool) if it measured one."""
    model = c.model
    problem = None
    try:
        table = KinematicTable.from_dict(model["table"])
    except (KeyError, TypeError):
        problem = "its model has no kinematic table (model.table, as the arm-kinematics routine stores it)"
    except ValueError as exc:
        problem = str(exc)
    if problem is None:
        try:
            text = urdf_of(table, _robot_name(c), model.get("tool"), comment=_provenance(c))
        except ValueError as exc:
            problem = str(exc)
    if problem is not None:
        raise InvalidRequest(f"format: 'urdf': calibration {c.id} (target {c.target!r}, routine {c.routine}) cannot "
                             f"be written as a URDF: {problem}; allowed for it: json, opencv") from None
    return text


def _robot_name(c: Calibration) -> str:
    """<arm model>_<cell>_v<version>, in letters, digits and underscores."""
    return re.sub(r"\W", "_", f"{c.model.get('arm_model') or 'arm'}_{c.cell or 'cell'}_v{c.version}")


def _provenance(c: Calibration) -> str:
    tool = c.model.get("tool")
    frame = c.model.get("tool_frame")
    tool_note = ("no tool" if tool is None else
                 f"link 'tool' on the flange: T_flange_tool{f' of the {frame}' if frame else ''}")
    return (f"cellctl calibration {c.id}: version {c.version} of target {c.target!r}, routine {c.routine}, cell "
            f"{c.cell!r}, created {c.created}. The calibrated kinematic table of {c.model.get('arm_model')!r} "
            f"(base_link: the cell frame; joint positions are the controller's joint angles); {tool_note}.")


def _fs_key(key: str) -> str:
    """FileStorage keys: a letter first, then letters, digits, underscores."""
    key = re.sub(r"\W", "_", str(key))
    return key if key[:1].isalpha() else f"k_{key}"


def opencv_yaml(doc: dict) -> str:
    """The document as an OpenCV FileStorage YAML: numeric arrays as matrices, maps as maps."""
    import cv2
    import numpy as np

    fs = cv2.FileStorage("calibration.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)

    def write(name: str | None, value) -> None:
        if isinstance(value, dict):
            fs.startWriteStruct(name or "", cv2.FileNode_MAP)
            for k, v in value.items():
                write(_fs_key(k), v)
            fs.endWriteStruct()
        elif isinstance(value, (list, tuple)):
            arr = None
            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                pass
            if arr is not None and arr.ndim in (1, 2) and arr.size and np.all(np.isfinite(arr)):
                fs.write(name, arr.reshape(len(arr), -1) if arr.ndim == 2 else arr.reshape(1, -1))
            else:
                fs.startWriteStruct(name or "", cv2.FileNode_SEQ)
                for v in value:
                    write(None, v)
                fs.endWriteStruct()
        elif value is None:
            _write_scalar(fs, name, "")
        elif isinstance(value, bool) or isinstance(value, int) and abs(value) < 2**31:
            _write_scalar(fs, name, int(value))
        elif isinstance(value, (int, float)):  # FileStorage ints are 32-bit: larger ones go as reals
            _write_scalar(fs, name, float(value))
        else:
            _write_scalar(fs, name, str(value))

    for key, value in doc.items():
        write(_fs_key(key), value)
    return fs.releaseAndGetString()


def _write_scalar(fs, name: str | None, value) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        value = str(value)
    fs.write(name if name is not None else "", value)
