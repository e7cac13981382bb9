"""The local line detector of seed 000 section III (Gennery's weighted-average detector).

For a projected model line the detector looks for the image line next to it:

1. visibility: the estimated models are rasterised into a z-buffer; a model line is
   cut into segments of about 20 px and a segment is kept when the z-buffer shows
   nothing in front of it (`visible_segments`);
2. along the segment, intervals of about 2 px; in each, a search along the nearest
   multiple of 45 deg to the line's normal (so the search walks whole pixels),
   Sobel edge elements whose gradient points along the normal, and their weighted
   average: one edge point per interval, with its variance;
3. a weighted least-squares line through those points in the model line's frame
   (x across, y along, endpoints at (0, 0) and (0, L)): the distances h1, h2 of the
   image line from the two endpoints and their 2x2 weight matrix (eqs. 2-4);
4. the systematic-error term (eqs. 10-11, sigma_sys = 0.5 px) and, where one side
   of the edge is saturated, the blooming term (eq. 12, sigma_bloom = 2 px).

The result gives the image line's endpoints (eqs. 8-9), which the line-based
matching (calibration.models.model_matching) uses.

How it is computed: the Sobel gradients, the noise and the saturation level of an
image are computed once (`edge_image`) and reused by every detection on that image
(a line-based update detects on the same two frames in every round). The search
reads only the gradients on its search lines (a gather of whole pixels), never the
rest of the frame, and all segments are processed together: every interval of every
segment is one row of the same arrays, and the per-segment sums of the least-squares
fits (eqs. 2-4) are bincounts over those rows, so the cost grows linearly with the
number of segments with no Python loop per segment. Likewise the visibility test
cuts all edges into segments at once and reads the z-buffer only around the test
points; the z-buffer fills each face's pixel box from the face's plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geometry.projection import face_footprint, pinhole

SOBEL_NOISE_GAIN = np.sqrt(12.0)  # std of a 3x3 Sobel response per unit of pixel noise


@dataclass
class LineMeasurement:
    ok: np.ndarray  # (n,) bool: an image line was found
    Q1: np.ndarray  # (n, 2) image-line endpoints beside the model endpoints (eqs. 8-9)
    Q2: np.ndarray
    h: np.ndarray  # (n, 2) h1, h2 (px, along the normal (-s, c) of the model line)
    W_img: np.ndarray  # (n, 2, 2) eq. 2
    W: np.ndarray  # (n, 2, 2) eq. 11 (or 12 with blooming)
    n_points: np.ndarray  # (n,) edge points used
    bloomed: np.ndarray  # (n,) bool


# ------------------------------------------------------------------ z-buffer and visibility

def depth_buffer(width: int, height: int, faces_cam: list[np.ndarray], f: float, cu: float, cv: float,
                 near: float = 1e-3) -> np.ndarray:
    """Depth (camera z) of the nearest face at every pixel; inf where no face is.

    faces_cam: convex polygons in camera coordinates (k, 3). 1/z is affine on the image of a plane, so the depth
    of a pixel is exact for planar faces."""
    zbuf = np.full((height, width), np.inf)
    if not len(faces_cam):
        return zbuf
    # the faces' planes, all at once; the faces turned away from the camera or reaching behind it are dropped
    # here (about half of a closed model), so only the others go through face_footprint's per-face checks
    P = np.array([poly[:3] for poly in faces_cam])  # (faces, 3, 3): the first three corners
    normals = _cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    offsets = (normals * P[:, 0]).sum(axis=1)
    zmin = np.array([poly[:, 2].min() for poly in faces_cam])
    for k in np.flatnonzero((offsets < 0) & (zmin > near)):
        footprint = face_footprint(faces_cam[k], f, cu, cv, width, height, near)
        if footprint is None:
            continue  # outside the image
        uv, (u0, v0, u1, v1) = footprint
        mask = np.zeros((v1 - v0, u1 - u0), np.uint8)
        cv2.fillConvexPoly(mask, np.round((uv - [u0, v0]) * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
        normal, d = normals[k], offsets[k]
        # the face's plane over its pixel box: a ray (x, y, 1) meets it at z = d / (ray . normal), rows and
        # columns broadcast; d < 0 (the face looks at the camera), so the face is in front where ray . normal < 0.
        # In place where it can be: fresh temporaries of a face's size cost as much as the arithmetic
        z = np.add.outer((np.arange(v0, v1) - cv) / f * normal[1] + normal[2], (np.arange(u0, u1) - cu) / f * normal[0])
        write = z < -1e-12
        write &= mask.view(bool)
        with np.errstate(divide="ignore"):
            np.divide(d, z, out=z)
        box = zbuf[v0:v1, u0:u1]  # a view: written in place
        write &= z > near
        write &= z < box
        np.copyto(box, z, where=write)
    return zbuf


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (n, 3) arrays (np.cross's axis handling costs more than the arithmetic here)."""
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


def visible_segments(zbuf: np.ndarray, E1: np.ndarray, E2: np.ndarray, f: float, cu: float, cv: float,
                     segment_px: float = 20.0, rel_tol: float = 0.005, margin_px: int = 25):
    """Cut 3D edges (camera coordinates, endpoints E1, E2 (n, 3)) into segments of about `segment_px` in the
    image and keep the visible ones.

    Returns (edge index, t0, t1) per visible segment, t the fraction along the edge."""
    k, t0, t1 = visible_segment_arrays(zbuf, E1, E2, f, cu, cv, segment_px, rel_tol, margin_px)
    return list(zip(k.tolist(), t0.tolist(), t1.tolist()))


def visible_segment_arrays(zbuf: np.ndarray, E1: np.ndarray, E2: np.ndarray, f: float, cu: float, cv: float,
                           segment_px: float = 20.0, rel_tol: float = 0.005, margin_px: int = 25):
    """`visible_segments` as arrays (edge index, t0, t1), all segments of all edges tested at once."""
    height, width = zbuf.shape
    E1, E2 = np.asarray(E1, float).reshape(-1, 3), np.asarray(E2, float).reshape(-1, 3)
    edges = np.flatnonzero((E1[:, 2] > 0) & (E2[:, 2] > 0))
    if not edges.size:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    length = np.linalg.norm(pinhole(E2[edges], f, cu, cv) - pinhole(E1[edges], f, cu, cv), axis=1)
    n_seg = np.maximum(1, np.round(length / segment_px).astype(int))
    k = np.repeat(edges, n_seg)
    s = np.arange(len(k)) - np.repeat(np.cumsum(n_seg) - n_seg, n_seg)  # segment number along its edge
    n = np.repeat(n_seg, n_seg)
    t0, t1 = s / n, (s + 1) / n
    ts = t0[:, None] + (t1 - t0)[:, None] * np.array([0.1, 0.3, 0.5, 0.7, 0.9])  # 5 test points per segment
    a, b = E1[k][:, None, :], E2[k][:, None, :]
    P = a + ts[..., None] * (b - a)  # (segments, 5, 3)
    uv = pinhole(P.reshape(-1, 3), f, cu, cv).reshape(len(k), 5, 2)
    ui, vi = np.round(uv[..., 0]).astype(int), np.round(uv[..., 1]).astype(int)
    inside = (ui >= margin_px) & (ui < width - margin_px) & (vi >= margin_px) & (vi < height - margin_px)
    # the largest depth in the test pixel's 3x3 neighbourhood (1e30 for no face): a point on a face's border
    # counts as visible; read at the test points only (indices clipped to the image: a repeated edge pixel
    # leaves the maximum as it is)
    du, dv = np.meshgrid([-1, 0, 1], [-1, 0, 1])
    around = zbuf[np.clip(vi[..., None] + dv.ravel(), 0, height - 1), np.clip(ui[..., None] + du.ravel(), 0, width - 1)]
    zi = np.where(np.isfinite(around), around, 1e30).astype(np.float32).max(axis=-1)
    seen = inside & (P[..., 2] <= zi * (1 + rel_tol))
    keep = (inside.sum(axis=1) >= 4) & (seen.sum(axis=1) >= 4)
    return k[keep], t0[keep], t1[keep]


# ------------------------------------------------------------------ detector

@dataclass(frozen=True)
class EdgeImage:
    """What the detector needs of one image, computed once and shared by every detection on it."""

    img: np.ndarray  # (h, w) float32 grey levels
    gx: np.ndarray  # (h * w,) float32 Sobel gradients, row-major pixels (flat: the search gathers from them)
    gy: np.ndarray
    sigma_n: float  # pixel noise
    full: float  # the saturation level
    any_saturated: bool

    @property
    def shape(self) -> tuple[int, int]:
        return self.img.shape


def edge_image(image: np.ndarray, saturation: float | None = None, noise: float | None = None) -> EdgeImage:
    """Grey levels, Sobel gradients, noise and saturation level of an image (grey or BGR)."""
    img = image.astype(np.float32)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    sigma_n = noise if noise is not None else _noise_of_sobel(image, gx)
    full = saturation if saturation is not None else (255.0 if image.dtype == np.uint8 else float(img.max()))
    return EdgeImage(img, gx.ravel(), gy.ravel(), float(sigma_n), float(full), bool(img.max() >= 0.98 * full))


def estimate_noise(image: np.ndarray) -> float:
    """Pixel noise sigma from the Sobel response of the (mostly flat) image: robust median estimate."""
    return _noise_of_sobel(image, cv2.Sobel(image.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3))


def _noise_of_sobel(image: np.ndarray, gx: np.ndarray) -> float:
    """1.4826 median|gx| / SOBEL_NOISE_GAIN (at least 0.3), gx the horizontal Sobel response of `image`."""
    med = None
    if image.dtype == np.uint8 and image.ndim == 2:
        # an 8-bit image's Sobel response is a whole number: the median from a 256-bin histogram of |gx|
        # (saturated at 255, exact below), the value np.median gives (the mean of the two middle ones) without
        # sorting the frame
        mag = cv2.convertScaleAbs(cv2.Sobel(image, cv2.CV_16S, 1, 0, ksize=3))
        cum = np.cumsum(cv2.calcHist([mag], [0], None, [256], [0, 256]).ravel().astype(np.int64))
        ranks = np.array([(mag.size - 1) // 2, mag.size // 2])  # the middle ranks, 0-based
        values = np.searchsorted(cum, ranks + 1)  # the first value with more than `rank` values at or below it
        if values.max() < 255:
            med = 0.5 * float(values.sum())
    if med is None:
        med = float(np.median(np.abs(gx)))
    return float(max(1.4826 * med / SOBEL_NOISE_GAIN, 0.3))


def detect_lines(image: np.ndarray | EdgeImage, A: np.ndarray, B: np.ndarray, *, search_px: int = 20,
                 interval_px: float = 2.0, sigma_sys: float = 0.5, blooming: bool = True, sigma_bloom: float = 2.0,
                 min_points: int = 4, max_angle_deg: float = 30.0, saturation: float | None = None,
                 noise: float | None = None) -> LineMeasurement:
    """Image lines beside the projected model segments A -> B (n, 2 each, px).

    `image`: the image, or its `edge_image` when several detections run on it (saturation and noise are then
    those it was made with)."""
    E = image if isinstance(image, EdgeImage) else edge_image(image, saturation, noise)
    height, width = E.shape
    sigma_g = E.sigma_n * SOBEL_NOISE_GAIN
    threshold = 5.0 * sigma_g
    cos_max = np.cos(np.radians(max_angle_deg))

    A = np.asarray(A, float).reshape(-1, 2)
    B = np.asarray(B, float).reshape(-1, 2)
    n = len(A)
    ok = np.zeros(n, bool)
    h = np.zeros((n, 2))
    W_img = np.zeros((n, 2, 2))
    W = np.zeros((n, 2, 2))
    n_pts = np.zeros(n, int)
    bloomed = np.zeros(n, bool)
    normals = _normals(A, B)

    # per segment (the ones long enough): direction t, normal (-s, c) (the direction of h in eq. 8) and the
    # whole-pixel search step along the nearest multiple of 45 deg to the normal
    diff = B - A
    L_all = np.linalg.norm(diff, axis=1)
    seg_idx = np.flatnonzero(L_all >= 4)
    a, L = A[seg_idx], L_all[seg_idx]
    t = diff[seg_idx] / L[:, None]
    normal = np.column_stack([-t[:, 1], t[:, 0]])
    q = np.round(np.arctan2(normal[:, 1], normal[:, 0]) / (np.pi / 4)) * (np.pi / 4)
    step = np.column_stack([np.round(np.cos(q)), np.round(np.sin(q))])
    su, sv = step.astype(int).T
    along_normal = (step * normal).sum(axis=1)  # > 0: distance across the line per step
    n_int = np.maximum(3, (L // interval_px).astype(int))

    # every interval of every segment is a row: `seg` says whose
    m = len(seg_idx)
    seg = np.repeat(np.arange(m), n_int)
    j = np.arange(len(seg)) - np.repeat(np.cumsum(n_int) - n_int, n_int)
    base = np.round(a[seg] + ((j + 0.5) / n_int[seg])[:, None] * diff[seg_idx][seg])
    ks = np.arange(-search_px, search_px + 1)
    # the search pixels (rows, K), whole numbers (base and step are); the passes over all of them below work in
    # place: fresh temporaries of this size cost as much as the arithmetic
    ui = ks * su[seg][:, None]
    ui += base[:, 0].astype(int)[:, None]
    vi = ks * sv[seg][:, None]
    vi += base[:, 1].astype(int)[:, None]
    inside = ui >= 1  # where the Sobel response is defined
    inside &= ui < width - 1
    inside &= vi >= 1
    inside &= vi < height - 1
    flat = vi * width
    flat += ui
    gx, gy = E.gx.take(flat, mode="clip"), E.gy.take(flat, mode="clip")  # only the search lines' gradients
    # the response across the line, in float32 like the gradients (the weighted average below is in float64)
    n32 = normal.astype(np.float32)
    strength = gx * n32[seg, 0][:, None]
    strength += gy * n32[seg, 1][:, None]
    np.abs(strength, out=strength)
    mag = gx * gx
    mag += gy * gy
    np.sqrt(mag, out=mag)
    mag *= np.float32(cos_max)
    along = strength >= mag  # the gradient within max_angle_deg of the normal
    along &= inside
    strength *= along
    # edge elements: local maxima of the response above the threshold; in each interval the one nearest
    # the predicted line wins (parallel edges of the same object lie a few pixels away)
    peak = np.zeros_like(strength, bool)
    mid = peak[:, 1:-1]  # a view
    np.greater(strength[:, 1:-1], threshold, out=mid)
    mid &= strength[:, 1:-1] >= strength[:, :-2]
    mid &= strength[:, 1:-1] >= strength[:, 2:]
    found = peak.any(axis=1)
    enough = np.bincount(seg, weights=found, minlength=m) >= min_points
    rows = np.flatnonzero(found & enough[seg])
    seg_r = seg[rows]
    k0 = np.argmin(np.where(peak[rows], np.abs(ks)[None, :], np.inf), axis=1)
    e = strength[rows].astype(float)
    # weighted average of the responses around the peak: one edge point per interval, with its variance
    idx = k0[:, None] + np.arange(-2, 3)[None, :]
    valid = (idx >= 0) & (idx < len(ks))
    idx = np.clip(idx, 0, len(ks) - 1)
    win = np.where(valid, np.clip(np.take_along_axis(e, idx, axis=1) - 0.5 * threshold, 0.0, None), 0.0)
    total = win.sum(axis=1)
    pos = ks[idx]
    s_hat = (win * pos).sum(axis=1) / total
    var_s = (((pos - s_hat[:, None]) ** 2) * (win > 0)).sum(axis=1) * sigma_g**2 / total**2
    d = base[rows] + s_hat[:, None] * step[seg_r] - a[seg_r]
    xs = (d * normal[seg_r]).sum(axis=1)
    y = (d * t[seg_r]).sum(axis=1) / L[seg_r]  # along the segment, 0 at A and 1 at B
    ws = 1.0 / np.maximum(var_s * along_normal[seg_r] ** 2, 0.01**2)
    aj = np.column_stack([1 - y, y])  # x = h1 (1 - y) + h2 y

    def fit(keep):
        """Per segment: the normal matrix (eq. 2), the solution (eqs. 3-4, where well conditioned) and the
        kept count."""
        wk = ws * keep
        Wi = np.zeros((m, 2, 2))
        rhs = np.zeros((m, 2))
        for p in range(2):
            rhs[:, p] = np.bincount(seg_r, wk * aj[:, p] * xs, minlength=m)
            for r in range(p, 2):
                Wi[:, p, r] = Wi[:, r, p] = np.bincount(seg_r, wk * aj[:, p] * aj[:, r], minlength=m)
        well = enough & (_cond2(Wi) <= 1e8)
        hh = np.zeros((m, 2))
        if well.any():
            hh[well] = np.linalg.solve(Wi[well], rhs[well][..., None])[..., 0]
        return Wi, hh, well, np.bincount(seg_r, keep, minlength=m)

    # one refit per segment without the edge points far off its first line, the segments together
    keep = np.ones(len(rows), bool)
    active = enough.copy()
    for _ in range(2):
        _, hh, well, _ = fit(keep)
        active &= well
        res = xs - (aj * hh[seg_r]).sum(axis=1)
        new_keep = np.abs(res) <= 3 * np.maximum(1 / np.sqrt(ws), 0.7)
        changed = np.bincount(seg_r, new_keep != keep, minlength=m) > 0
        active &= changed & (np.bincount(seg_r, new_keep, minlength=m) >= min_points)
        if not active.any():
            break
        keep = np.where(active[seg_r], new_keep, keep)
    Wi, hh, well, n_kept = fit(keep)
    good = well & (n_kept >= min_points)
    out = seg_idx[good]
    ok[out] = True
    h[out] = hh[good]
    W_img[out] = Wi[good]
    n_pts[out] = n_kept[good].astype(int)
    var_extra = np.full(len(out), sigma_sys**2)
    if blooming and E.any_saturated and len(out):
        bloomed[out] = _saturated_side(E.img, A[out], B[out], normals[out], h[out], E.full)
        var_extra += np.where(bloomed[out], sigma_bloom**2, 0.0)
    W[out] = np.linalg.solve(np.eye(2) + var_extra[:, None, None] * W_img[out], W_img[out])  # eq. 11 (12)
    Q1 = A + h[:, :1] * normals
    Q2 = B + h[:, 1:] * normals
    return LineMeasurement(ok, Q1, Q2, h, W_img, W, n_pts, bloomed)


def _cond2(S: np.ndarray) -> np.ndarray:
    """2-norm condition numbers of symmetric positive semi-definite 2x2 matrices (inf when singular)."""
    tr, det = S[:, 0, 0] + S[:, 1, 1], S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    lmax = 0.5 * tr + np.hypot(0.5 * (S[:, 0, 0] - S[:, 1, 1]), S[:, 0, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(det > 0, lmax * lmax / np.where(det > 0, det, 1.0), np.inf)  # lmin = det / lmax


def _normals(A, B) -> np.ndarray:
    d = np.asarray(B, float) - np.asarray(A, float)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.column_stack([-d[:, 1], d[:, 0]])


def _saturated_side(img, a, b, normal, hh, full, offset: float = 3.0) -> np.ndarray:
    """Per found line (rows of a, b, normal, hh): True when the image is saturated just beside it on either side
    (blooming is likely), judged by the median of three samples `offset` px off the line."""
    height, width = img.shape
    s = np.array([0.25, 0.5, 0.75])[None, :, None]
    mids = a[:, None] + (b - a)[:, None] * s + normal[:, None] * (hh[:, None, :1] * (1 - s) + hh[:, None, 1:] * s)
    out = np.zeros(len(a), bool)
    for sign in (-1, 1):
        uv = np.round(mids + sign * offset * normal[:, None]).astype(int)  # (n, 3, 2)
        u, v = uv[..., 0], uv[..., 1]
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        vals = np.sort(np.where(inside, img[np.where(inside, v, 0), np.where(inside, u, 0)], np.nan), axis=1)
        count = inside.sum(axis=1)  # the samples inside the image come first after the sort (nan last)
        med = np.select([count == 3, count == 2, count == 1], [vals[:, 1], 0.5 * (vals[:, 0] + vals[:, 1]), vals[:, 0]],
                        -np.inf)
        out |= med >= 0.98 * full
    return out
