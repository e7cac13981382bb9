"""The OpenCV way, on the same samples, for the comparison every report shows.

cv2.calibrateCamera on the planar target (one view; the focal length cannot be told
from the distance in a near-frontal view, so it is fixed at a long-lens guess and the
principal point at the centre, as an engineer would), then cv2.findHomography from
undistorted points to the plane. For the hybrid strategy the registration is
cv2.estimateAffinePartial2D (rotation, translation and one scale).
"""

from __future__ import annotations

import cv2
import numpy as np

from calibration.stats import error_stats


class OpenCVPlanarMap:
    def __init__(self, uv: np.ndarray, xy: np.ndarray, image_size: tuple[int, int]):
        w, h = image_size
        self.origin = xy.mean(axis=0)
        scale = 1e3  # to millimetres: OpenCV's solvers like numbers of order one to thousands
        obj = np.column_stack([(xy - self.origin) * scale, np.zeros(len(xy))]).astype(np.float32)
        f = 10.0 * max(w, h)
        K0 = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
        flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_FOCAL_LENGTH | cv2.CALIB_FIX_PRINCIPAL_POINT
                 | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3)
        _, self.K, self.dist, _, _ = cv2.calibrateCamera([obj], [uv.astype(np.float32)], (w, h), K0, None, flags=flags)
        self.H, _ = cv2.findHomography(self._undistort(uv), (xy - self.origin) * scale)
        self.scale = scale

    def _undistort(self, uv: np.ndarray) -> np.ndarray:
        return cv2.undistortPoints(np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2), self.K, self.dist).reshape(-1, 2)

    def pixel_to_plane(self, uv) -> np.ndarray:
        und = self._undistort(np.atleast_2d(uv)).reshape(-1, 1, 2)
        return cv2.perspectiveTransform(und, self.H).reshape(-1, 2) / self.scale + self.origin


def opencv_similarity(src: np.ndarray, dst: np.ndarray):
    """dst ~ s R src + t by cv2.estimateAffinePartial2D (LMedS, robust): a function of points."""
    M, _ = cv2.estimateAffinePartial2D(src.astype(np.float64), dst.astype(np.float64), method=cv2.LMEDS)
    if M is None:
        raise ValueError("OpenCV could not estimate the registration")
    return lambda p: np.atleast_2d(p) @ M[:, :2].T + M[:, 2]


def baseline_stats(fit_and_map, uv_ver: np.ndarray, xy_ver: np.ndarray) -> dict:
    """Verification errors of an OpenCV fit, or why it failed (OpenCV raises on degenerate input)."""
    try:
        mapped = fit_and_map()(uv_ver)
    except (cv2.error, ValueError) as exc:
        return {"error": str(exc).strip().splitlines()[-1]}
    return {"verification": error_stats(np.linalg.norm(mapped - xy_ver, axis=1))}
