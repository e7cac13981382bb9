"""A run folder: the manifest, every sample as it arrives, images, the result.

Nothing is half-written: JSON and images go to a temporary file renamed into
place; samples are appended one line at a time and fsynced, and a line cut by a
crash (no newline yet) is dropped when the folder is opened again.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

MANIFEST = "run.json"
SAMPLES = "samples.csv"
RESULT = "result.json"


class RunFolderError(RuntimeError):
    pass


def write_atomic(path: Path, data: bytes | str, mode: int | None = None) -> None:
    """Written whole under a temporary name, then renamed: a reader sees the old file or the new one. `mode`: the
    file is created with it (a key's 0600: never wider, not even for a moment); None: as open() makes it."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666 if mode is None else mode)
    try:
        if mode is not None:
            os.fchmod(fd, mode)  # whatever the umask left
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def to_jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return None if not math.isfinite(float(obj)) else float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def write_json(path: Path, obj: Any) -> None:
    write_atomic(path, json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n")


class RunFolder:
    def __init__(self, path: str | Path):
        self.path = Path(path)

    @property
    def samples_path(self) -> Path:
        return self.path / SAMPLES

    @property
    def images_path(self) -> Path:
        return self.path / "images"

    def exists(self) -> bool:
        return (self.path / MANIFEST).exists()

    def create(self, manifest: dict, columns: tuple[str, ...]) -> None:
        if self.exists():
            raise RunFolderError(f"{self.path} already holds a run; resume it (--resume) or choose another --out")
        self.path.mkdir(parents=True, exist_ok=True)
        write_json(self.path / MANIFEST, dict(manifest, columns=list(columns)))
        write_atomic(self.samples_path, ",".join(columns) + "\n")

    def manifest(self) -> dict:
        try:
            return json.loads((self.path / MANIFEST).read_text())
        except FileNotFoundError:
            raise RunFolderError(f"{self.path} holds no run to resume (no {MANIFEST})") from None

    def check(self, row: dict, columns: tuple[str, ...]) -> None:
        unknown = set(row) - set(columns)
        if unknown:
            raise RunFolderError(f"sample has columns {sorted(unknown)} not in the run's columns")

    def append_many(self, rows: list[dict], columns: tuple[str, ...]) -> None:
        """Append rows in one write, fsynced: a crash leaves them all or (after the cut line is dropped) none. A write
        that fails (the disk full) is cut back to where it began: the rows before stay as they were."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        for row in rows:
            self.check(row, columns)
            writer.writerow([csv_cell(row.get(c)) for c in columns])
        data = memoryview(buf.getvalue().encode())
        fd = os.open(self.samples_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)  # unbuffered: nothing is left to flush later
        try:
            start = os.lseek(fd, 0, os.SEEK_END)
            try:
                while data:
                    data = data[os.write(fd, data):]
                os.fsync(fd)
            except OSError:
                os.ftruncate(fd, start)  # truncating needs no new space
                raise
        finally:
            os.close(fd)

    def samples(self) -> list[dict]:
        """Every complete sample; what a crash cut (a partial line, a step with rows missing) is removed."""
        text = self.samples_path.read_text()
        lines = text.splitlines(keepends=True)
        if lines and not lines[-1].endswith("\n"):
            lines.pop()
        rows = read_samples_text("".join(lines))
        if rows and rows[-1].get("step_rows"):
            last = [r for r in rows if r["step"] == rows[-1]["step"]]
            if len(last) < int(rows[-1]["step_rows"]):
                rows, lines = rows[: -len(last)], lines[: -len(last)]
        if "".join(lines) != text:
            write_atomic(self.samples_path, "".join(lines))
        return rows

    def save_image(self, name: str, image: np.ndarray) -> str:
        import cv2

        self.images_path.mkdir(exist_ok=True)
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise RunFolderError(f"could not encode image {name}")
        write_atomic(self.images_path / name, png.tobytes())
        return f"images/{name}"


def csv_cell(value: Any) -> str:
    """A value as samples.csv holds it (floats by repr: the shortest exact round trip)."""
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        return "nan" if math.isnan(value) else repr(float(value))  # repr: shortest exact round trip
    if isinstance(value, np.integer):
        return str(int(value))
    return str(value)


def read_samples_text(text: str) -> list[dict]:
    reader = csv.DictReader(io.StringIO(text))
    return [{k: _parse(v) for k, v in row.items()} for row in reader]


def _parse(value: str | None) -> Any:
    if value is None or value == "":
        return None
    try:
        return int(value)
    except ValueError:
        pass
    try:
        return float(value)
    except ValueError:
        return value
