"""What the web console draws over a camera's frame, drawn here with OpenCV (the browser gets one PNG).

Three layers, all from data the daemon already keeps:
- features: what the latest step of a job measured in this camera (its sample rows' u_px, v_px);
- grid: the active calibration of this camera (its B1+B2 map) carried back into the image: lines of
  constant robot x and y over the camera's areas, so a wrong calibration shows as a grid off the scene;
- residuals: that calibration's verification points, arrows from where the robot's position projects
  to where the camera saw it, scaled up (the legend says how much) as in the report's residual plot.

Only models and plain samples are read here; nothing about the simulated world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from calibration.models.planar import PlanarMap
from calibration.routines.base import image_residuals

from cellctl.stores.run_folder import read_samples_text

LAYERS = ("features", "grid", "residuals")
FEATURE, GRID, RESIDUAL, TEXT = (60, 220, 60), (230, 200, 0), (40, 60, 255), (255, 255, 255)  # BGR


@dataclass
class OverlayData:
    """Everything a frame's overlay shows, in full-resolution pixels and metres."""

    features: list[tuple[float, float, float | None]] = field(default_factory=list)  # u, v, diameter (px)
    feature_label: str = ""
    grid_map: PlanarMap | None = None
    grid_extents: list[tuple[float, float, float, float]] = field(default_factory=list)  # x0, y0, x1, y1 (m)
    grid_label: str = ""
    residual_uv: np.ndarray | None = None
    residual_vec: np.ndarray | None = None  # metres, in image directions (calibration.routines.base)
    residual_label: str = ""
    notes: list[str] = field(default_factory=list)  # why a requested layer is empty


# -- gathering -------------------------------------------------------------------------------


def gather(daemon, camera: str, layers: set[str]) -> OverlayData:
    data = OverlayData()
    if "features" in layers:
        _features(daemon, camera, data)
    if layers & {"grid", "residuals"}:
        cal = daemon.calstore.active(camera)
        planar = _planar(cal)
        if planar is None:
            data.notes.append(f"no active planar calibration of {camera}")
        else:
            if "grid" in layers:
                _grid(daemon, camera, cal, planar, data)
            if "residuals" in layers:
                _residuals(daemon, camera, cal, planar, data)
    return data


def _planar(cal) -> PlanarMap | None:
    if cal is None:
        return None
    doc = (cal.model or {}).get("map")
    try:
        return PlanarMap.from_dict(doc) if isinstance(doc, dict) else None
    except Exception:  # noqa: BLE001 - not a planar map: nothing to draw
        return None


def _rows(path: Path) -> list[dict]:
    try:
        text = path.read_text()
    except OSError:
        return []
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines.pop()  # the worker may be writing the last line right now
    return read_samples_text("".join(lines))


def _is_xy(*values) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


def _features(daemon, camera: str, data: OverlayData) -> None:
    seen = daemon.worker.steps.get(camera)
    if seen is None:
        data.notes.append(f"no step has measured in {camera} since the daemon started")
        return
    job_id, folder, row = seen
    rows = [r for r in _rows(Path(folder) / "samples.csv")
            if r.get("step") == row.get("step") and r.get("camera", camera) == camera] or [row]
    for r in rows:
        if _is_xy(r.get("u_px"), r.get("v_px")):
            d = r.get("diameter_px")
            data.features.append((float(r["u_px"]), float(r["v_px"]), float(d) if _is_xy(d) else None))
    data.feature_label = f"job {job_id} step {row.get('step')}: {len(data.features)} feature(s)"


def _grid(daemon, camera: str, cal, planar: PlanarMap, data: OverlayData) -> None:
    for area in daemon.config.areas.values():
        if area.camera == camera:
            (cx, cy), (w, h) = area.centre_mm, area.size_mm
            data.grid_extents.append(((cx - w / 2) * 1e-3, (cy - h / 2) * 1e-3, (cx + w / 2) * 1e-3,
                                      (cy + h / 2) * 1e-3))
    if not data.grid_extents:
        data.notes.append(f"no area of the cell file is seen by {camera}")
        return
    data.grid_map = planar
    data.grid_label = f"calibration {cal.id} ({cal.routine} v{cal.version})"


def _residuals(daemon, camera: str, cal, planar: PlanarMap, data: OverlayData) -> None:
    path = daemon.calstore.samples_path(cal.id) or (Path(cal.run_dir) / "samples.csv" if cal.run_dir else None)
    rows = _rows(path) if path else []
    ver = [r for r in rows if r.get("set") == "ver" and r.get("status", "ok") == "ok"
           and r.get("camera", camera) == camera and _is_xy(r.get("u_px"), r.get("v_px"), r.get("x_mm"), r.get("y_mm"))]
    if not ver:
        data.notes.append(f"calibration {cal.id} has no verification points in {camera}")
        return
    uv = np.array([[r["u_px"], r["v_px"]] for r in ver], dtype=float)
    xy = np.array([[r["x_mm"], r["y_mm"]] for r in ver], dtype=float) * 1e-3
    data.residual_uv, data.residual_vec = uv, image_residuals(planar, uv, xy)
    data.residual_label = f"verification of calibration {cal.id}: {len(ver)} point(s)"


# -- drawing ---------------------------------------------------------------------------------


def render(image: np.ndarray, data: OverlayData, width: int | None = None) -> np.ndarray:
    """The frame (scaled to `width`, never up) in colour with the overlay drawn at that scale."""
    h0, w0 = image.shape[:2]
    s = min(1.0, width / w0) if width else 1.0
    out = cv2.resize(image, (max(1, round(w0 * s)), max(1, round(h0 * s))), interpolation=cv2.INTER_AREA) \
        if s < 1.0 else image.copy()
    if out.dtype != np.uint8:  # e.g. 16-bit sensors: to 8 bits for the screen
        out = cv2.convertScaleAbs(out, alpha=255.0 / max(float(out.max()), 1.0))
    if out.ndim == 2 or out.shape[2] == 1:
        out = cv2.cvtColor(out, cv2.COLOR_GRAY2BGR)
    lw = max(1, round(out.shape[1] / 500))
    legend: list[tuple[str, tuple]] = []
    if data.grid_map is not None:
        pitches = _draw_grid(out, data, s, lw)
        legend.append((f"{data.grid_label}: lines every {' / '.join(f'{p * 1e3:g}' for p in pitches)} mm", GRID))
    if data.residual_uv is not None:
        legend.append((_draw_residuals(out, data, s, lw), RESIDUAL))
    for u, v, d in data.features:
        c = (round(u * s), round(v * s))
        r = max(4, round((d or 20) * s / 2))
        cv2.circle(out, c, r, FEATURE, lw, cv2.LINE_AA)
        cv2.drawMarker(out, c, FEATURE, cv2.MARKER_CROSS, max(6, r // 2), lw, cv2.LINE_AA)
    if data.feature_label:
        legend.append((data.feature_label, FEATURE))
    legend += [(n, TEXT) for n in data.notes]
    _legend(out, legend)
    return out


def _nice_pitch(span_m: float, lines: int = 12) -> float:
    raw = span_m / lines
    step = 10 ** math.floor(math.log10(raw))
    return next(k * step for k in (1, 2, 5, 10) if k * step >= raw)


def _draw_grid(out: np.ndarray, data: OverlayData, s: float, lw: int) -> list[float]:
    """Lines of constant robot x and y over each area; returns their pitch per area (m)."""
    planar, pitches = data.grid_map, []
    for x0, y0, x1, y1 in data.grid_extents:
        pitch = _nice_pitch(max(x1 - x0, y1 - y0))
        pitches.append(pitch)
        xs = np.arange(math.ceil(x0 / pitch), math.floor(x1 / pitch) + 1) * pitch
        ys = np.arange(math.ceil(y0 / pitch), math.floor(y1 / pitch) + 1) * pitch
        along_x, along_y = np.linspace(x0, x1, 60), np.linspace(y0, y1, 60)
        # sampled densely, so the lens distortion shows as curved lines
        lines = [np.column_stack([np.full_like(along_y, x), along_y]) for x in xs]
        lines += [np.column_stack([along_x, np.full_like(along_x, y)]) for y in ys]
        for line in lines:
            uv = planar.plane_to_pixel(line) * s
            if np.all(np.isfinite(uv)):
                cv2.polylines(out, [np.round(uv).astype(np.int32)], False, GRID, lw, cv2.LINE_AA)
    return pitches


def _draw_residuals(out: np.ndarray, data: OverlayData, s: float, lw: int) -> str:
    lengths = np.linalg.norm(data.residual_vec, axis=1)
    longest = float(lengths.max()) if lengths.size else 0.0
    # the longest arrow a tenth of the picture's width: px on screen per metre of error
    gain = 0.1 * out.shape[1] / longest if longest > 0 else 0.0
    for (u, v), vec in zip(data.residual_uv * s, data.residual_vec):
        tip = (round(u + vec[0] * gain), round(v + vec[1] * gain))
        cv2.circle(out, (round(u), round(v)), lw + 1, RESIDUAL, -1, cv2.LINE_AA)
        cv2.arrowedLine(out, (round(u), round(v)), tip, RESIDUAL, lw, cv2.LINE_AA, tipLength=0.25)
    return f"{data.residual_label}; longest {longest * 1e6:.1f} um drawn {0.1 * out.shape[1]:.0f} px"


def _legend(out: np.ndarray, entries: list[tuple[str, tuple]]) -> None:
    scale = max(0.4, out.shape[1] / 1600)
    thick = max(1, round(scale * 1.5))
    line_h = round(28 * scale)
    y = line_h + 4
    for text, colour in entries:
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
        cv2.rectangle(out, (4, y - th - 4), (12 + tw, y + 5), (0, 0, 0), -1)
        cv2.putText(out, text, (8, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thick, cv2.LINE_AA)
        y += line_h + 4


def encode_png(image: np.ndarray) -> bytes:
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("could not encode the overlay")
    return png.tobytes()
