"""The live camera view's work, behind the service's camera verbs (LocalService delegates here).

- A live frame: a new capture of a camera while no job uses the cell (`Worker.idle_cell` around each
  capture: beside a job it is refused, naming the job), with its figures (`stats`: the histogram of the raw
  levels, the saturated share, the mean level) and drawn for a person: the saturated pixels highlighted, the
  features `find_features` sees in this frame, and the camera's active calibration's grid (cellctl/http/overlay.py).
- Exposure and gain: read and changed on the connected camera (drivers/cameras/live.py), any backend.
- Written back to the cell file: the changed keys' lines only (comments and the rest of the text kept), a
  unified diff shown first, the file replaced atomically; a key the file takes from another (`extends:`) is
  refused, naming that file.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from drivers.cameras._common import CameraSettingError
from drivers.cameras.live import supports_live
from drivers.interfaces import DeviceError

from cellctl.errors import Conflict, InvalidRequest, NotFound, ServiceError, Unavailable
from cellctl.stores.run_folder import write_atomic

LIVE_LAYERS = ("features", "grid", "saturation")
HIST_BINS = 64
SATURATED_BGR = (255, 0, 255)  # magenta: not the overlay's green, cyan or red
FULL_SCALE = {"Mono10": 1023, "Mono12": 4095, "Mono14": 16383}  # 16-bit words holding fewer bits


@dataclass
class LiveFrame:
    """One live frame: the raw frame, its figures, and what the routines it serves found in it."""

    camera: str
    frame: object  # drivers.interfaces.Frame
    captured: float  # epoch s
    stats: dict = field(default_factory=dict)


def frame_stats(image: np.ndarray, meta: dict | None = None) -> dict:
    """The figures an exposure is judged by, on the raw levels: full scale, mean level (% of full scale),
    saturated pixels (count and %), and a histogram of HIST_BINS bins over 0..full scale (fractions)."""
    gray = image if image.ndim == 2 else image.max(axis=2)  # a colour pixel saturates when any channel does
    full = FULL_SCALE.get((meta or {}).get("pixel_format"), 255 if gray.dtype == np.uint8 else 65535)
    saturated = int(np.count_nonzero(gray >= full))
    hist, _ = np.histogram(gray, bins=HIST_BINS, range=(0, full + 1))
    n = gray.size
    return {"width": int(gray.shape[1]), "height": int(gray.shape[0]), "full_scale": full,
            "mean_pct": round(float(gray.mean()) / full * 100, 3), "min": int(gray.min()), "max": int(gray.max()),
            "saturated": saturated, "saturated_pct": round(saturated / n * 100, 4),
            "histogram": [round(float(h) / n, 6) for h in hist]}


def saturated_mask(image: np.ndarray, full: int) -> np.ndarray:
    gray = image if image.ndim == 2 else image.max(axis=2)
    return gray >= full


def to_bgr8(image: np.ndarray, full: int) -> np.ndarray:
    import cv2

    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / full)
    if image.ndim == 2 or image.shape[2] == 1:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(image)


class LiveCameras:
    """The live view of one daemon's cameras: over its worker, its cell file and its calibration store."""

    def __init__(self, config, worker, calstore, config_path: Path | None):
        self.config, self.worker, self.calstore = config, worker, calstore
        self.config_path = Path(config_path) if config_path is not None else None
        # per camera device: its values before anything here changed them, which is what the cell file implies
        # for a setting it leaves out (the camera's own, or the simulated camera's nominal one)
        self._connected: dict[int, dict] = {}

    # -- frames ------------------------------------------------------------------------------------

    def capture(self, camera: str) -> LiveFrame:
        """A new frame of `camera`, refused (Conflict naming the job) while a job uses the cell."""
        with self.worker.idle_cell(f"the live view of {camera} waits until it is done (the job owns the "
                                   "cameras)", beside_manual=True) as cell:  # watching the arm being jogged
            device = self._device(cell, camera)
            try:
                frame = device.capture()
            except DeviceError as exc:
                raise Unavailable(f"camera {camera}: {type(exc).__name__}: {exc}") from None
        return LiveFrame(camera, frame, time.time(), frame_stats(frame.image, frame.meta))

    def render(self, live: LiveFrame, layers: set[str], width: int | None) -> np.ndarray:
        """The frame in colour, scaled to `width` (never up), the saturated pixels highlighted and the overlay
        layers drawn; the legend says what each is."""
        from cellctl.http import overlay

        image = live.frame.image
        full = live.stats["full_scale"]
        out = to_bgr8(image, full)
        data = overlay.OverlayData()
        if "saturation" in layers:
            mask = saturated_mask(image, full)
            if mask.any():
                out[mask] = SATURATED_BGR
            data.notes.append(f"saturated: {live.stats['saturated_pct']:.3g} % of pixels (magenta)")
        if "features" in layers:
            self._features(live, data)
        if "grid" in layers:
            cal = self.calstore.active(live.camera)
            planar = overlay._planar(cal)
            if planar is None:
                data.notes.append(f"no active planar calibration of {live.camera}: no grid")
            else:
                overlay._grid(SimpleNamespace(config=self.config), live.camera, cal, planar, data)
        return overlay.render(out, data, width)

    def _features(self, live: LiveFrame, data) -> None:
        from calibration.vision.features import find_features

        found = find_features(live.frame.image)
        data.features = [(f.blob.u, f.blob.v, f.blob.diameter_px) for f in found]
        kinds = {}
        for f in found:
            kinds[f.kind] = kinds.get(f.kind, 0) + 1
        served = self.routines_of(live.camera)
        what = ", ".join(f"{n} {k}{'s' if n > 1 else ''}" for k, n in sorted(kinds.items())) or "no feature"
        data.feature_label = f"found now: {what}" + (f" (as {', '.join(served)} find them)" if served else "")
        live.stats["features"] = [{"kind": f.kind, "u_px": round(f.blob.u, 2), "v_px": round(f.blob.v, 2),
                                   "diameter_px": round(f.blob.diameter_px, 2)} for f in found]

    def routines_of(self, camera: str) -> list[str]:
        """The routines of the cell file whose area (or other areas they name) this camera sees."""
        areas = {name for name, a in self.config.areas.items() if a.camera == camera}
        out = []
        for routine, params in (self.config.routines or {}).items():
            named = {v for k, v in (params or {}).items() if isinstance(v, str) and (k == "area" or k.endswith("_area"))}
            if named & areas or any(v == camera for v in (params or {}).values() if isinstance(v, str)):
                out.append(routine)
        return out

    def picture(self, camera: str, layers: set[str], width: int | None, fmt: str) -> tuple[bytes, LiveFrame]:
        """A live frame drawn, encoded as JPEG (the stream) or PNG (a snapshot)."""
        import cv2

        live = self.capture(camera)
        drawn = self.render(live, layers, width)
        ok, data = cv2.imencode(".png", drawn) if fmt == "png" else cv2.imencode(
            ".jpg", drawn, [cv2.IMWRITE_JPEG_QUALITY, 80])
        if not ok:
            raise ServiceError(f"camera {camera}: could not encode the frame as {fmt}")
        return data.tobytes(), live

    # -- exposure and gain -----------------------------------------------------------------------------

    def _device(self, cell, camera: str):
        try:
            return cell.cameras[camera]
        except KeyError:
            raise NotFound(f"no camera {camera!r}; cameras: {', '.join(sorted(cell.cameras))}") from None

    def settings(self, camera: str) -> dict:
        """What the camera uses now and what the cell file says, per live setting, with the ranges allowed."""
        with self.worker.idle_cell("its cameras' settings are read when it is done", beside_manual=True) as cell:
            device = self._device(cell, camera)
            if not supports_live(device):
                return self._answer(camera, [], {}, {})
            try:
                specs, values = device.live_specs(), device.live_values()
            except CameraSettingError as exc:
                raise InvalidRequest(str(exc)) from None
            except DeviceError as exc:
                raise Unavailable(f"camera {camera}: {type(exc).__name__}: {exc}") from None
            connected = self._connected.setdefault(id(device), dict(values))
        return self._answer(camera, specs, values, connected)

    def set_settings(self, camera: str, values: dict) -> dict:
        if not isinstance(values, dict) or not values:
            raise InvalidRequest("settings: give at least one, e.g. {\"exposure_s\": 0.01}")
        with self.worker.idle_cell(f"change {camera}'s settings when it is done", beside_manual=True) as cell:
            device = self._device(cell, camera)
            if not supports_live(device):
                raise InvalidRequest(f"camera {camera}: its backend changes no setting live")
            try:
                connected = self._connected.setdefault(id(device), dict(device.live_values()))
                device.set_live(values)
                specs, now = device.live_specs(), device.live_values()
            except CameraSettingError as exc:
                raise InvalidRequest(str(exc)) from None
            except DeviceError as exc:
                raise Unavailable(f"camera {camera}: {type(exc).__name__}: {exc}") from None
        return self._answer(camera, specs, now, connected)

    def _answer(self, camera: str, specs, values: dict, connected: dict | None = None) -> dict:
        in_file = self._file_options(camera)
        backend = self.config.cameras[camera].backend
        out = {}
        for spec in specs:
            value, written = values.get(spec.key), in_file.get(spec.key)
            implied = written if written is not None else (connected or {}).get(spec.key)
            out[spec.key] = dict(spec.public(), value=value, in_file=written,
                                 changed=value is not None and not _same(value, implied))
        return {"camera": camera, "backend": backend, "settings": out,
                "note": None if specs else f"the {backend} camera {camera} has no setting to change live here"}

    def _file_options(self, camera: str) -> dict:
        """The camera's options as the cell file on disk has them now (extends merged)."""
        if self.config_path is None:
            return dict(self.config.cameras[camera].options)
        from cellctl.config import CellFileError, load_cell_file

        try:
            config, _ = load_cell_file(self.config_path, routines=False)
            return dict(config.cameras[camera].options) if camera in config.cameras else {}
        except CellFileError:
            return dict(self.config.cameras[camera].options)

    # -- written back to the cell file -------------------------------------------------------------------

    def save(self, camera: str, confirm: bool) -> dict:
        """The cell file with the camera's changed settings, as a unified diff; with `confirm`, written."""
        if self.config_path is None:
            raise Unavailable("writing settings back needs the daemon's cell file")
        now = self.settings(camera)
        changes = {k: s["value"] for k, s in now["settings"].items() if s["changed"]}
        path = self.config_path
        answer = {"camera": camera, "file": str(path), "changes": {k: [now["settings"][k]["in_file"], v]
                                                                    for k, v in changes.items()},
                  "diff": "", "written": False}
        if not changes:
            answer["message"] = f"{path.name}: {camera}'s settings already say what it uses now; nothing to write"
            return answer
        old = path.read_text()
        new = edit_camera_options(old, camera, changes, str(path), defined_in(path, camera))
        answer["diff"] = "".join(difflib.unified_diff(old.splitlines(keepends=True), new.splitlines(keepends=True),
                                                      f"a/{path.name}", f"b/{path.name}"))
        if not confirm:
            answer["message"] = "not written: confirm to write it"
            return answer
        write_atomically(path, new)
        answer["written"] = True
        answer["message"] = (f"written to {path}; the daemon reads it at its next start (the camera keeps the "
                             "live settings meanwhile)")
        return answer


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    except (TypeError, ValueError):
        return a == b


# -- editing the cell file's text --------------------------------------------------------------------------


def yaml_number(value) -> str:
    """A number as YAML 1.1 (PyYAML) reads back as that number: 1e-05 would be a string, 1.0e-05 is a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"not a number: {value!r}")
    if isinstance(value, int):
        return str(value)
    text = repr(float(value))
    if "e" in text:
        mantissa, exponent = text.split("e")
        if "." not in mantissa:
            mantissa += ".0"
        text = f"{mantissa}e{exponent}"
    return text


_KEY = re.compile(r"^(?P<indent>[ ]*)(?P<key>[A-Za-z0-9_.\-]+|\"[^\"]*\"|'[^']*'):(?P<rest>.*)$")


def _split_comment(rest: str) -> tuple[str, str]:
    """(value text, trailing comment with its spacing) of what follows a key's colon (no quotes with # kept)."""
    m = re.search(r"\s+#", rest)
    if m and "'" not in rest[:m.start()] and '"' not in rest[:m.start()]:
        return rest[:m.start()], rest[m.start():]
    return rest, ""


def defined_in(path: Path, camera: str) -> str | None:
    """The file along `path`'s `extends:` chain whose cameras: section has `camera`, None if none (or unreadable)."""
    import yaml

    seen = set()
    while path not in seen:
        seen.add(path)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError):
            return None
        if isinstance(data, dict) and camera in (data.get("cameras") or {}):
            return str(path)
        base = data.get("extends") if isinstance(data, dict) else None
        if not isinstance(base, str):
            return None
        path = (path.parent / base).resolve()
    return None


def edit_camera_options(text: str, camera: str, changes: dict, source: str = "the cell file",
                        defined: str | None = None) -> str:
    """The cell file's text with `cameras.<camera>.<key>: value` set for each change, every other line as it
    was. The camera's entry may be a flow mapping on one line ({backend: sim}) or a block. Refused
    (InvalidRequest) when the file has no such entry of its own (it `extends:` another that has it) or a layout
    this edit does not follow; the result is parsed back and checked to change exactly those keys."""
    import yaml

    lines = text.splitlines(keepends=True)
    before = yaml.safe_load(text) or {}
    base = before.get("extends") if isinstance(before, dict) else None
    own = (before.get("cameras") or {}).get(camera) if isinstance(before, dict) else None
    if own is None:
        where = (f"it extends {base}, and cameras.{camera} is in {defined or base}: edit {camera}'s settings "
                 f"there, or give {camera} an entry in {source}" if base else f"it has no cameras.{camera} entry")
        raise InvalidRequest(f"{source}: cannot write {camera}'s settings: {where}")
    if not isinstance(own, dict):
        raise InvalidRequest(f"{source}: cameras.{camera} is not a mapping; edit it by hand")
    start = next((i for i, line in enumerate(lines) if re.match(r"^cameras:\s*(#.*)?$", line.rstrip("\n"))), None)
    if start is None:
        raise InvalidRequest(f"{source}: cameras: is not a block of its own at the start of a line; edit it by hand")
    cam_line, cam_indent = None, None
    i = start + 1
    while i < len(lines):
        line = lines[i]
        if line.strip() and not line.startswith((" ", "\t", "#")):
            break  # the next top-level key
        m = _KEY.match(line.rstrip("\n"))
        if m and m["key"].strip("'\"") == camera and (cam_indent is None or len(m["indent"]) <= cam_indent):
            cam_line, cam_indent = i, len(m["indent"])
            break
        i += 1
    if cam_line is None:
        raise InvalidRequest(f"{source}: cameras.{camera} is not on a line of its own; edit it by hand")
    m = _KEY.match(lines[cam_line].rstrip("\n"))
    value, comment = _split_comment(m["rest"])
    eol = "\n" if lines[cam_line].endswith("\n") else ""
    if value.strip().startswith("{"):
        if not value.strip().endswith("}"):
            raise InvalidRequest(f"{source}: cameras.{camera} is a flow mapping over several lines; edit it by hand")
        inner = value.strip()[1:-1]
        for key, new in changes.items():
            written = yaml_number(new)
            found = re.search(rf"(^|,)(\s*){re.escape(key)}\s*:\s*([^,]*?)(\s*)(?=,|$)", inner)
            if found:
                inner = f"{inner[:found.start()]}{found[1]}{found[2]}{key}: {written}{found[4]}{inner[found.end():]}"
            elif inner.strip():
                inner = f"{inner.rstrip()}, {key}: {written}{inner[len(inner.rstrip()):]}"
            else:
                inner = f"{key}: {written}"
        lead = value[:len(value) - len(value.lstrip())]
        lines[cam_line] = f"{m['indent']}{m['key']}:{lead}{{{inner}}}{comment}{eol}"
    elif value.strip():
        raise InvalidRequest(f"{source}: cameras.{camera} is written as {value.strip()!r}; edit it by hand")
    else:  # a block: its lines are those indented deeper
        end, child_indent, found = cam_line + 1, None, {}
        while end < len(lines):
            line = lines[end]
            if line.strip() and not line.lstrip().startswith("#"):
                indent = len(line) - len(line.lstrip(" "))
                if indent <= cam_indent:
                    break
                child_indent = child_indent if child_indent is not None else indent
                km = _KEY.match(line.rstrip("\n"))
                if km and len(km["indent"]) == child_indent:
                    found[km["key"].strip("'\"")] = end
            end += 1
        if child_indent is None:
            raise InvalidRequest(f"{source}: cameras.{camera} has no options on their own lines; edit it by hand")
        last = max(found.values()) if found else cam_line
        inserted = []
        for key, new in changes.items():
            if key in found:
                km = _KEY.match(lines[found[key]].rstrip("\n"))
                old_value, old_comment = _split_comment(km["rest"])
                if old_value.strip().startswith(("{", "[", "|", ">")) or not old_value.strip():
                    raise InvalidRequest(f"{source}: cameras.{camera}.{key} is not a plain value; edit it by hand")
                tail = "\n" if lines[found[key]].endswith("\n") else ""
                lines[found[key]] = f"{km['indent']}{km['key']}: {yaml_number(new)}{old_comment}{tail}"
            else:
                inserted.append(f"{' ' * child_indent}{key}: {yaml_number(new)}\n")
        if inserted:
            if not lines[last].endswith("\n"):
                lines[last] += "\n"
            lines[last + 1:last + 1] = inserted
    out = "".join(lines)
    after = yaml.safe_load(out)
    expected = json.loads(json.dumps(before))
    expected["cameras"][camera] = dict(own, **changes)
    if json.loads(json.dumps(after)) != expected:
        raise InvalidRequest(f"{source}: the edit of cameras.{camera} did not come out as meant; nothing written "
                             "(edit it by hand)")
    return out


def write_atomically(path: Path, text: str) -> None:
    """`text` replaces the file at once (written beside it, renamed over it), keeping its mode."""
    path = Path(path)
    try:
        mode = path.stat().st_mode & 0o7777
        write_atomic(path, text, mode)
    except OSError as exc:
        raise Conflict(f"{path}: cannot write it: {exc.strerror or exc}") from None
