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
    for poly in faces_cam:
        footprint = face_footprint(poly, f, cu, cv, width, height, near)
        if footprint is None:
            continue  # behind the camera (none in our scenes), facing away or outside the image
        uv, (u0, v0, u1, v1) = footprint
        mask = np.zeros((v1 - v0, u1 - u0), np.uint8)
        cv2.fillConvexPoly(mask, np.round((uv - [u0, v0]) * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
        vv, uu = np.nonzero(mask)
        if not vv.size:
            continue
        normal = np.cross(poly[1] - poly[0], poly[2] - poly[0])
        d = normal @ poly[0]
        rays = np.column_stack([(uu + u0 - cu) / f, (vv + v0 - cv) / f, np.ones(vv.size)])
        denom = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(np.abs(denom) > 1e-12, d / denom, np.inf)
        z = np.where(z > near, z, np.inf)
        cur = zbuf[vv + v0, uu + u0]
        closer = z < cur
        zbuf[vv[closer] + v0, uu[closer] + u0] = z[closer]
    return zbuf


def visible_segments(zbuf: np.ndarray, E1: np.ndarray, E2: np.ndarray, f: float, cu: float, cv: float,
                     segment_px: float = 20.0, rel_tol: float = 0.005, margin_px: int = 25):
    """Cut 3D edges (camera coordinates, endpoints E1, E2 (n, 3)) into segments of about `segment_px` in the
    image and keep the visible ones.

    Returns (edge index, t0, t1) per visible segment, t the fraction along the edge."""
    height, width = zbuf.shape
    # the largest depth around each pixel: a point on a face's border counts as visible
    zmax = cv2.dilate(np.where(np.isfinite(zbuf), zbuf, 1e30).astype(np.float32), np.ones((3, 3), np.uint8))
    out = []
    for k, (a, b) in enumerate(zip(E1, E2)):
        if a[2] <= 0 or b[2] <= 0:
            continue
        pa, pb = pinhole(np.array([a, b]), f, cu, cv)
        length = np.linalg.norm(pb - pa)
        n_seg = max(1, int(round(length / segment_px)))
        for s in range(n_seg):
            t0, t1 = s / n_seg, (s + 1) / n_seg
            ts = t0 + (t1 - t0) * np.array([0.1, 0.3, 0.5, 0.7, 0.9])
            P = a + ts[:, None] * (b - a)
            uv = pinhole(P, f, cu, cv)
            ui, vi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            inside = (ui >= margin_px) & (ui < width - margin_px) & (vi >= margin_px) & (vi < height - margin_px)
            if inside.sum() < 4:
                continue
            zi = zmax[vi[inside], ui[inside]]
            seen = P[inside, 2] <= zi * (1 + rel_tol)
            if seen.sum() >= 4:
                out.append((k, t0, t1))
    return out


# ------------------------------------------------------------------ detector

def estimate_noise(image: np.ndarray) -> float:
    """Pixel noise sigma from the Sobel response of the (mostly flat) image: robust median estimate."""
    g = cv2.Sobel(image.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    return float(max(1.4826 * np.median(np.abs(g)) / SOBEL_NOISE_GAIN, 0.3))


def detect_lines(image: np.ndarray, A: np.ndarray, B: np.ndarray, *, search_px: int = 20, interval_px: float = 2.0,
                 sigma_sys: float = 0.5, blooming: bool = True, sigma_bloom: float = 2.0, min_points: int = 4,
                 max_angle_deg: float = 30.0, saturation: float | None = None, noise: float | None = None
                 ) -> LineMeasurement:
    """Image lines beside the projected model segments A -> B (n, 2 each, px)."""
    img = image.astype(np.float32)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    height, width = img.shape
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    sigma_n = noise if noise is not None else estimate_noise(img)
    sigma_g = sigma_n * SOBEL_NOISE_GAIN
    threshold = 5.0 * sigma_g
    full = saturation if saturation is not None else (255.0 if image.dtype == np.uint8 else float(img.max()))
    cos_max = np.cos(np.radians(max_angle_deg))
    any_saturated = bool(img.max() >= 0.98 * full)

    n = len(A)
    ok = np.zeros(n, bool)
    h = np.zeros((n, 2))
    W_img = np.zeros((n, 2, 2))
    W = np.zeros((n, 2, 2))
    n_pts = np.zeros(n, int)
    bloomed = np.zeros(n, bool)
    ks = np.arange(-search_px, search_px + 1)
    for i in range(n):
        a, b = np.asarray(A[i], float), np.asarray(B[i], float)
        L = float(np.linalg.norm(b - a))
        if L < 4:
            continue
        t = (b - a) / L
        normal = np.array([-t[1], t[0]])  # (-s, c): the direction of h in eq. 8
        angle = np.arctan2(normal[1], normal[0])
        q = np.round(angle / (np.pi / 4)) * (np.pi / 4)  # nearest multiple of 45 deg
        step = np.array([np.round(np.cos(q)), np.round(np.sin(q))])  # whole-pixel step along the search
        along_normal = float(step @ normal)  # > 0: distance across the line per step
        n_int = max(3, int(L // interval_px))
        centres = a + np.outer((np.arange(n_int) + 0.5) / n_int, b - a)
        base = np.round(centres)
        pts = base[:, None, :] + ks[None, :, None] * step  # (n_int, K, 2)
        ui = pts[..., 0].astype(int)
        vi = pts[..., 1].astype(int)
        inside = (ui >= 1) & (ui < width - 1) & (vi >= 1) & (vi < height - 1)
        ui_c, vi_c = np.clip(ui, 0, width - 1), np.clip(vi, 0, height - 1)
        g = np.stack([gx[vi_c, ui_c], gy[vi_c, ui_c]], axis=-1)
        across = np.abs(g @ normal)
        mag = np.linalg.norm(g, axis=-1)
        strength = np.where(inside & (across >= cos_max * mag), across, 0.0)
        # edge elements: local maxima of the response above the threshold; in each interval the one nearest
        # the predicted line wins (parallel edges of the same object lie a few pixels away)
        peak = np.zeros_like(strength, bool)
        peak[:, 1:-1] = (strength[:, 1:-1] > threshold) & (strength[:, 1:-1] >= strength[:, :-2]) & \
                        (strength[:, 1:-1] >= strength[:, 2:])
        found = peak.any(axis=1)
        if found.sum() < min_points:
            continue
        k0 = np.argmin(np.where(peak, np.abs(ks)[None, :], np.inf), axis=1)[found]
        e = strength[found]
        # weighted average of the responses around the peak: one edge point per interval, with its variance
        idx = k0[:, None] + np.arange(-2, 3)[None, :]
        valid = (idx >= 0) & (idx < len(ks))
        idx = np.clip(idx, 0, len(ks) - 1)
        win = np.where(valid, np.clip(np.take_along_axis(e, idx, axis=1) - 0.5 * threshold, 0.0, None), 0.0)
        total = win.sum(axis=1)
        pos = ks[idx]
        s_hat = (win * pos).sum(axis=1) / total
        var_s = (((pos - s_hat[:, None]) ** 2) * (win > 0)).sum(axis=1) * sigma_g**2 / total**2
        p = base[found] + s_hat[:, None] * step
        d = p - a
        xs, ys = d @ normal, d @ t
        ws = 1.0 / np.maximum(var_s * along_normal**2, 0.01**2)
        keep = np.ones(len(xs), bool)
        for _ in range(2):  # one refit without the edge points far off the first line
            aj = np.column_stack([1 - ys / L, ys / L])
            Wi = (aj[keep] * ws[keep, None]).T @ aj[keep]
            if np.linalg.cond(Wi) > 1e8:
                break
            hh = np.linalg.solve(Wi, (aj[keep] * ws[keep, None]).T @ xs[keep])
            res = xs - aj @ hh
            new_keep = np.abs(res) <= 3 * np.maximum(1 / np.sqrt(ws), 0.7)
            if new_keep.sum() < min_points or np.array_equal(new_keep, keep):
                break
            keep = new_keep
        aj = np.column_stack([1 - ys / L, ys / L])
        Wi = (aj[keep] * ws[keep, None]).T @ aj[keep]
        if keep.sum() < min_points or np.linalg.cond(Wi) > 1e8:
            continue
        hh = np.linalg.solve(Wi, (aj[keep] * ws[keep, None]).T @ xs[keep])  # eqs. 2-4
        var_extra = sigma_sys**2
        if blooming and any_saturated and _saturated_side(img, a, b, normal, hh, full):
            var_extra += sigma_bloom**2
            bloomed[i] = True
        ok[i] = True
        h[i] = hh
        W_img[i] = Wi
        W[i] = np.linalg.solve(np.eye(2) + var_extra * Wi, Wi)  # eq. 11 (12)
        n_pts[i] = int(keep.sum())
    Q1 = np.asarray(A, float) + h[:, :1] * _normals(A, B)
    Q2 = np.asarray(B, float) + h[:, 1:] * _normals(A, B)
    return LineMeasurement(ok, Q1, Q2, h, W_img, W, n_pts, bloomed)


def _normals(A, B) -> np.ndarray:
    d = np.asarray(B, float) - np.asarray(A, float)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.column_stack([-d[:, 1], d[:, 0]])


def _saturated_side(img, a, b, normal, hh, full, offset: float = 3.0) -> bool:
    """True when the image is saturated just beside the found line on either side (blooming is likely)."""
    height, width = img.shape
    mids = [a + (b - a) * s + normal * (hh[0] * (1 - s) + hh[1] * s) for s in (0.25, 0.5, 0.75)]
    for sign in (-1, 1):
        vals = []
        for m in mids:
            u, v = np.round(m + sign * offset * normal).astype(int)
            if 0 <= u < width and 0 <= v < height:
                vals.append(img[v, u])
        if vals and np.median(vals) >= 0.98 * full:
            return True
    return False
