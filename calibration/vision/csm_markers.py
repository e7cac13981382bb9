"""The fixture's circle marks in a camera image (seed 002 section II.B, Fig. 5), two ways.

Each mark is a ring with a centre of the other colour, 1/3 of its diameter: a black circle with a white
centre, or a white circle with a black centre. Any string of pixels through the centre then reads
d:1:d (dark:light:dark, or the reverse), and under the near-orthographic view the ratio survives.

- `method="dld"`, the seed's detector: sweep the rows of the thresholded image for runs in the ratio
  d:1:d (within a tolerance); through each candidate, verify by vertical and both diagonal strings; the
  centre is the average of the four passes' chord midpoints (every chord through an ellipse's centre is
  bisected by it), with threshold crossings interpolated to sub-pixel. The sweep covers only the window
  where the mask changes along rows (found by cv2, widened by the longest run a triple may have: the
  same candidates as sweeping every row), the strings are sampled from a float copy of that window, and
  the four strings of a pass are sampled and read together.
- `method="contour"`, a modern alternative and the default: rings found as contours with exactly one
  hole of about 1/9 their area; from the ring's grey-level centroid, 48 rays find the inner and outer
  edges at sub-pixel (threshold crossings interpolated), an ellipse is fitted to each edge, and the centre
  is the mean of the two ellipse centres. On the simulated cell it is the more accurate (about 0.026 px
  RMS against the true projections, the d:1:d strings 0.036 px); both take a few milliseconds per
  1600 x 1200 frame (tools/bench_csm.py).

`find_marks` returns the centres of the black and of the white marks; `label_fixture` names them after the
fixture drawing (which black is which) by the best affine match of the drawing to the image.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.errors import VisionError

METHODS = ("contour", "dld")


@dataclass(frozen=True)
class MarkOptions:
    dark_threshold: int = 80  # 8-bit level: below it a pixel is "black print"
    light_threshold: int = 190  # above it a pixel is "white print"
    ratio_tolerance: float = 0.5  # |d - l| <= tol * l for the d:1:d test
    min_run_px: int = 2
    max_run_px: int = 60


@dataclass(frozen=True)
class Marks:
    black: np.ndarray  # (n, 2) u, v
    white: np.ndarray  # (m, 2)


def find_marks(image: np.ndarray, method: str = "contour", options: MarkOptions = MarkOptions()) -> Marks:
    if method not in METHODS:
        raise VisionError(f"unknown mark detector {method!r}; allowed: {', '.join(METHODS)}")
    image = np.asarray(image)
    if image.ndim != 2:
        raise VisionError(f"expected a grey image (h, w), got shape {image.shape}")
    if image.dtype != np.uint8:  # 16-bit cameras: the thresholds are 8-bit levels
        image = (image.astype(np.float32) / np.iinfo(image.dtype).max * 255).astype(np.uint8)
    find = _contour_marks if method == "contour" else _dld_marks
    return Marks(find(image, dark=True, o=options), find(image, dark=False, o=options))


# --- modern: contours + grey moments -------------------------------------------------------

def _contour_marks(image: np.ndarray, dark: bool, o: MarkOptions) -> np.ndarray:
    mask = (image < o.dark_threshold) if dark else (image > o.light_threshold)
    contours, hierarchy = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    centres = []
    if hierarchy is None:
        return np.zeros((0, 2))
    for i, (_next, _previous, child, parent) in enumerate(hierarchy[0]):
        if parent != -1 or child == -1 or hierarchy[0][child][0] != -1:
            continue  # an outer contour with exactly one hole
        outer, hole = cv2.contourArea(contours[i]), cv2.contourArea(contours[child])
        if outer < 20 or not 0.04 < hole / outer < 0.3:  # the hole is (1/3)^2 = 0.11 of the mark, blurred
            continue
        centre = _grey_centroid(image, contours[i], dark)
        if centre is not None:
            _, _, w, h = cv2.boundingRect(contours[i])
            refined = _ellipse_centre(image, centre, 0.75 * max(w, h), dark,
                                      float(o.dark_threshold if dark else o.light_threshold))
            centres.append(centre if refined is None else refined)
    return np.array(centres).reshape(-1, 2)


def _ellipse_centre(image, start, reach: float, dark: bool, level: float, rays: int = 48, step: float = 0.25):
    """Sub-pixel edges where rays from `start` cross the threshold (ring's inner and outer edge, linearly
    interpolated), an ellipse fitted to each edge; the centre is the mean of the two ellipse centres."""
    t = np.arange(0.0, reach, step)
    angles = np.linspace(0, 2 * np.pi, rays, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    pts = start + t[None, :, None] * dirs[:, None, :]  # (rays, samples, 2)
    h, w = image.shape
    if pts[..., 0].min() < 0 or pts[..., 1].min() < 0 or pts[..., 0].max() > w - 1 or pts[..., 1].max() > h - 1:
        return None
    values = cv2.remap(image, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR)
    values = values.astype(np.float64)
    on = (values < level) if dark else (values > level)
    edges = ([], [])
    for r in range(rays):
        flips = np.nonzero(on[r, 1:] != on[r, :-1])[0]
        if len(flips) < 2 or on[r, 0]:
            return None  # the centre must be the other colour, then the ring, then the plate
        for k, i in enumerate(flips[:2]):
            v0, v1 = values[r, i], values[r, i + 1]
            edges[k].append(start + (t[i] + step * (level - v0) / (v1 - v0)) * dirs[r])
    centres = [np.array(cv2.fitEllipse(np.array(e, dtype=np.float32))[0]) for e in edges]
    return np.mean(centres, axis=0)


def _grey_centroid(image: np.ndarray, contour: np.ndarray, dark: bool) -> np.ndarray | None:
    """Intensity-weighted centroid of the ring: weight = how much darker (lighter) than the plate around it.
    The centre of the other colour weighs nothing; the ring is symmetric about the centre."""
    x, y, w, h = cv2.boundingRect(contour)
    pad = max(3, int(0.25 * max(w, h)))
    x0, y0 = max(x - pad, 0), max(y - pad, 0)
    x1, y1 = min(x + w + pad, image.shape[1]), min(y + h + pad, image.shape[0])
    win = image[y0:y1, x0:x1].astype(np.float64)
    border = np.concatenate([win[0], win[-1], win[:, 0], win[:, -1]])
    plate = float(np.median(border))
    spread = 3.0 * float(np.median(np.abs(border - plate))) * 1.4826 + 2.0  # noise dead zone
    weight = (plate - win - spread) if dark else (win - plate - spread)
    # only the ring itself: inside the outer contour, grown by the blur
    inside = np.zeros(win.shape, np.uint8)
    cv2.drawContours(inside, [contour - [x0, y0]], -1, 1, thickness=cv2.FILLED)
    inside = cv2.dilate(inside, np.ones((5, 5), np.uint8))
    weight = np.where(inside > 0, np.clip(weight, 0, None), 0.0)
    total = weight.sum()
    if total <= 0:
        return None
    vv, uu = np.mgrid[y0:y1, x0:x1]
    return np.array([(weight * uu).sum() / total, (weight * vv).sum() / total])


# --- the seed's d:1:d strings ---------------------------------------------------------------

_DIRECTIONS = np.array([(1.0, 0.0), (0.0, 1.0), (0.7071067811865476, 0.7071067811865476),
                        (0.7071067811865476, -0.7071067811865476)])
_DIRECTIONS_NORMAL = _DIRECTIONS.T @ _DIRECTIONS  # the four chords' midpoints as least squares
_STRING_ROWS = np.arange(4)[:, None]
_INNER_OUTER = np.array([-1, -2, 0, 1])  # crossings about the centre: inner, outer left; inner, outer right


def _dld_marks(image: np.ndarray, dark: bool, o: MarkOptions) -> np.ndarray:
    level = float(o.dark_threshold if dark else o.light_threshold)
    window = _sweep_window(image, dark, o)
    if window is None:
        return np.zeros((0, 2))
    candidates = _window_candidates(image, window, dark, o)
    grey = _Strings(image, window, 2.5 * o.max_run_px + 2)
    centres, tried = [], []
    for u, v in candidates:
        if any(math.hypot(u - c[0], v - c[1]) < 3 for c in centres + tried):
            continue  # a row of a mark already found (or already refuted)
        tried.append((u, v))
        centre = _four_passes(grey, np.array([u, v]), dark, level, o)
        if centre is not None and not any(np.hypot(*(centre - c)) < 3 for c in centres):
            centres.append(centre)
    return np.array(centres).reshape(-1, 2)


def _sweep_window(image: np.ndarray, dark: bool, o: MarkOptions) -> tuple[int, int, int, int] | None:
    """The part of the image the row sweep needs, (x0, y0, x1, y1): the rows where the mask changes
    along a row, and the columns where it does, widened by more than any run of a d:1:d triple can be
    long. Outside it every row is one run, so no triple is lost; a run the window cuts is longer than the
    widening both in the image and in the window, so it fails the ratio test either way. The sweep then
    finds exactly the full image's candidates, for a fraction of the cost of sweeping every row."""
    # rows with pixels of both kinds (a row's extremes are cheap), then the changes within them
    lo, hi = image.min(axis=1), image.max(axis=1)
    both = np.nonzero((lo < o.dark_threshold) & (hi >= o.dark_threshold) if dark
                      else (hi > o.light_threshold) & (lo <= o.light_threshold))[0]
    if both.size == 0:
        return None
    r0, r1 = int(both[0]), int(both[-1]) + 1
    band = image[r0:r1]
    m = ((band < o.dark_threshold) if dark else (band > o.light_threshold)).view(np.uint8)
    x, y, w, h = cv2.boundingRect(cv2.compare(m[:, 1:], m[:, :-1], cv2.CMP_NE))  # mask[:, j] != mask[:, j+1]
    if w == 0:
        return None
    margin = int(math.ceil((1 + o.ratio_tolerance) * o.max_run_px)) + 2
    return max(x + 1 - margin, 0), r0 + y, min(x + w + margin, image.shape[1]), r0 + y + h


def _window_candidates(image: np.ndarray, window, dark: bool, o: MarkOptions) -> list[tuple[float, float]]:
    """`_row_candidates` of the whole image's mask, swept in `window` alone."""
    x0, y0, x1, y1 = window
    part = image[y0:y1, x0:x1]
    mask = (part < o.dark_threshold) if dark else (part > o.light_threshold)
    return [(u + x0, v + y0) for u, v in _row_candidates(mask, o)]


class _Strings:
    """The grey image as float32 for bilinear sampling along strings (cv2.remap), converted only around
    the sweep window, grown to the whole image if a string ever leaves that."""

    def __init__(self, image: np.ndarray, window, reach: float):
        self.image, self.shape = image, image.shape
        x0, y0, x1, y1 = window
        pad = int(math.ceil(reach)) + 2
        self.x0, self.y0 = max(x0 - pad, 0), max(y0 - pad, 0)
        self.x1, self.y1 = min(x1 + pad, image.shape[1]), min(y1 + pad, image.shape[0])
        self.grey = image[self.y0:self.y1, self.x0:self.x1].astype(np.float32)

    def sample(self, centre: np.ndarray, du: np.ndarray, dv: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        """Bilinear values at centre + (du, dv), whose extremes are centre + lo, + hi; None if any lies
        outside the image."""
        h, w = self.shape
        lo_u, lo_v = centre + lo
        hi_u, hi_v = centre + hi
        if lo_u < 0 or lo_v < 0 or hi_u > w - 1 or hi_v > h - 1:
            return None
        if lo_u < self.x0 or lo_v < self.y0 or hi_u > self.x1 - 2 or hi_v > self.y1 - 2:
            self.x0 = self.y0 = 0
            self.x1, self.y1 = w, h
            self.grey = self.image.astype(np.float32)
        # the window's offset is subtracted in float32, where it is exact: the same samples as from the image
        u = (centre[0] + du).astype(np.float32) - np.float32(self.x0)
        v = (centre[1] + dv).astype(np.float32) - np.float32(self.y0)
        return cv2.remap(self.grey, u, v, cv2.INTER_LINEAR)


def _row_candidates(mask: np.ndarray, o: MarkOptions) -> list[tuple[float, float]]:
    """Horizontal sweep: in every row, consecutive runs on:off:on of about equal lengths (the centre run
    `off`). Per mark (cluster of rows), the row whose ratio is closest to 1:1:1 comes first."""
    m = mask.astype(np.int8)
    padded = np.pad(m, ((0, 0), (1, 1)))
    rows, cols = np.nonzero(np.diff(padded, axis=1))  # run boundaries, sorted by row then column
    if rows.size < 4:
        return []
    # runs between consecutive boundaries of one row; value of the run = mask right after its start
    same = rows[1:] == rows[:-1]
    start, end, r = cols[:-1][same], cols[1:][same], rows[:-1][same]
    value = m[r, np.minimum(start, m.shape[1] - 1)]
    length = end - start
    if length.size < 3:
        return []
    a, b, c = length[:-2], length[1:-1], length[2:]
    ok = ((r[:-2] == r[2:]) & (value[:-2] == 1) & (value[1:-1] == 0) & (value[2:] == 1)
          & (b >= o.min_run_px) & (b <= o.max_run_px)
          & (np.abs(a - b) <= o.ratio_tolerance * b) & (np.abs(c - b) <= o.ratio_tolerance * b))
    idx = np.nonzero(ok)[0]
    score = (np.abs(a - b) + np.abs(c - b))[idx] / b[idx]
    order = idx[np.argsort(score, kind="stable")]
    return [(float(start[i + 1] + length[i + 1] / 2 - 0.5), float(r[i])) for i in order]


@functools.lru_cache(maxsize=8)
def _strings(reach: float, step: float):
    """Parameters t along a string; the four strings' offsets from their centre, u and v (4, n) each,
    and their extremes (lo, hi) per coordinate."""
    t = np.arange(-reach, reach + step, step)
    du, dv = t[None, :] * _DIRECTIONS[:, :1], t[None, :] * _DIRECTIONS[:, 1:]
    return t, du, dv, np.array([du.min(), dv.min()]), np.array([du.max(), dv.max()])


def _four_passes(grey: _Strings, guess, dark: bool, level: float, o: MarkOptions) -> np.ndarray | None:
    """Chord midpoints along the horizontal, vertical and both diagonal strings through the current centre;
    each string must read d:1:d. A chord's midpoint fixes the centre along its own direction, so the four
    passes are averaged as four such constraints (least squares), and repeated from the new centre until it
    stays put (a chord through an ellipse's centre is bisected by it; one beside it is not).

    Along a string the centre run and the two ring runs around it are read from the threshold crossings
    (interpolated between samples); the chord's midpoint is the mean of the outer and inner chords'. The
    four strings are sampled and read together."""
    step = 0.25
    t, du, dv, lo, hi = _strings(2.5 * o.max_run_px, step)
    n = len(t)
    k0 = n // 2
    first = np.arange(4) * (n - 1)  # where each string's crossings start, the strings laid end to end
    centre = np.asarray(guess, dtype=float)
    for _ in range(8):
        values = grey.sample(centre, du, dv, lo, hi)  # (4, n)
        if values is None:
            return None
        on = (values < level) if dark else (values > level)
        if on[:, k0].any():
            return None  # the centre of a mark is the other colour
        # crossings between samples i and i+1 of a string, the strings laid end to end
        crossings = np.flatnonzero(on[:, 1:] != on[:, :-1])
        start, split, end = (np.searchsorted(crossings, first + k) for k in (0, k0, n - 1))
        if ((split - start) < 2).any() or ((end - split) < 2).any():
            return None
        # per string: inner left, outer left, inner right, outer right crossing
        i = crossings[split[:, None] + _INNER_OUTER] - first[:, None]
        v0, v1 = values[_STRING_ROWS, i], values[_STRING_ROWS, i + 1]
        same = v1 == v0
        f = np.where(same, 0.5, (level - v0) / np.where(same, 1, v1 - v0))
        inner_l, outer_l, inner_r, outer_r = (t[i] + f * step).T
        light = inner_r - inner_l
        d1, d2 = inner_l - outer_l, outer_r - inner_r
        tol = o.ratio_tolerance * light
        if ((light < o.min_run_px * 0.5) | (np.abs(d1 - light) > tol) | (np.abs(d2 - light) > tol)).any():
            return None
        mid = 0.5 * ((inner_l + inner_r) / 2 + (outer_l + outer_r) / 2)
        along = [d @ (centre + m * d) for d, m in zip(_DIRECTIONS, mid)]  # each chord's midpoint, along it
        new = np.linalg.solve(_DIRECTIONS_NORMAL, _DIRECTIONS.T @ np.array(along))
        moved = np.hypot(*(new - centre))
        centre = new
        if moved < 1e-3:
            break
    return centre


# --- naming the marks after the fixture drawing ------------------------------------------------

def label_fixture(marks: Marks, white_xy, black_xy, max_residual_px: float = 3.0) -> dict[str, np.ndarray]:
    """{'white': uv, 'black1': uv, ...}: the assignment of image marks to drawing points (plate x, y) whose
    best 2D affine fit has the smallest residual and keeps the drawing's handedness (the plate is seen
    from its front). Raises VisionError if the marks do not make up the fixture."""
    if len(marks.white) != 1 or len(marks.black) != len(black_xy):
        raise VisionError(f"expected 1 white and {len(black_xy)} black marks, found {len(marks.white)} white "
                          f"and {len(marks.black)} black")
    drawing = np.vstack([np.asarray(white_xy, float).reshape(1, 2), np.asarray(black_xy, float)])
    best = None
    for perm in itertools.permutations(range(len(marks.black))):
        image_pts = np.vstack([marks.white, marks.black[list(perm)]])
        A = np.column_stack([drawing, np.ones(len(drawing))])
        coef, *_ = np.linalg.lstsq(A, image_pts, rcond=None)
        if np.linalg.det(coef[:2].T) <= 0:  # mirrored: this order would mean seeing the plate from behind
            continue
        residual = float(np.abs(A @ coef - image_pts).max())
        if best is None or residual < best[0]:
            best = (residual, perm)
    if best is None or best[0] > max_residual_px:
        raise VisionError(f"the marks do not match the fixture drawing (best residual "
                          f"{'-' if best is None else f'{best[0]:.1f}'} px > {max_residual_px} px)")
    named = {"white": marks.white[0]}
    for i, j in enumerate(best[1], start=1):
        named[f"black{i}"] = marks.black[j]
    return named
