"""A calibration as a file for another program: JSON, or OpenCV FileStorage YAML.

    doc = export_document(calibration)        # id, target, routine, version, created, cell, model
    text = opencv_yaml(doc)                   # cv2.FileStorage can read it back
"""

from __future__ import annotations

import json
import math
import re

from cellctl.service.interface import Export, ExportFormat
from cellctl.stores.calibrations import Calibration


def export_calibration(c: Calibration, format: ExportFormat) -> Export:
    """The calibration with its model, as `format` ("json" or "opencv")."""
    doc = {"id": c.id, "target": c.target, "routine": c.routine, "version": c.version, "created": c.created,
           "cell": c.cell, "model": c.model}
    if format == "json":
        return Export(json.dumps(doc, indent=2, allow_nan=False, default=str), "application/json",
                      f"calibration-{c.id}.json")
    return Export(opencv_yaml(doc), "application/x-yaml", f"calibration-{c.id}.yaml")


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
