"""ChArUco corners in an image (cv2.aruco), with the checks that keep a bad frame out of a hand-eye fit.

cv2.aruco finds the markers, interpolates the chessboard corners between them and refines each to sub-pixel
(its saddle point). A frame is refused, with the reason, when it shows too few corners, when they lie on one
line (no pose from them), or when its pose is ambiguous: a small or distant board seen nearly head-on has two
poses (mirror images about the line of sight) that explain the corners almost equally well, and a fit fed the
wrong one is pulled far off.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geometry.charuco import BoardDrawing

from calibration.errors import VisionError

AMBIGUITY_RATIO = 1.5  # the second-best planar pose must explain the corners this much worse (RMS) to trust the best


@dataclass(frozen=True)
class Corners:
    ids: np.ndarray  # (n,) corner ids of the board drawing
    uv: np.ndarray  # (n, 2) px
    markers: int  # markers found

    def __len__(self) -> int:
        return len(self.ids)


def find_corners(image: np.ndarray, drawing: BoardDrawing, min_corners: int = 12) -> Corners:
    """The board's corners in `image` (grey, uint8 or uint16); VisionError saying why when there are too few or
    they are collinear."""
    if image.ndim != 2:
        raise VisionError(f"expected a grey image, got shape {image.shape}")
    if image.dtype != np.uint8:
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    board = drawing.board()
    corners, ids, markers, _ = cv2.aruco.CharucoDetector(board).detectBoard(image)
    n_markers = 0 if markers is None else len(markers)
    if ids is None or len(ids) < min_corners:
        found = 0 if ids is None else len(ids)
        raise VisionError(f"{found} board corners found ({n_markers} markers), fewer than min_corners={min_corners}: "
                          "is the board in view, lit and in focus?")
    ids = ids.ravel().astype(int)
    if board.checkCharucoCornersCollinear(ids.reshape(-1, 1).astype(np.int32)):
        raise VisionError(f"the {len(ids)} corners found lie on one line: no pose from them")
    return Corners(ids, corners.reshape(-1, 2).astype(float), n_markers)


def board_pose(corners: Corners, drawing: BoardDrawing, K: np.ndarray, dist) -> tuple[np.ndarray, float]:
    """T_camera_board by planar PnP (IPPE, both solutions compared) and its RMS reprojection error (px);
    VisionError when the two planar solutions explain the corners about equally well."""
    object_points = drawing.corners()[corners.ids]
    n, rvecs, tvecs, errors = cv2.solvePnPGeneric(object_points, corners.uv, K, np.asarray(dist, float),
                                                  flags=cv2.SOLVEPNP_IPPE)
    if n == 0:
        raise VisionError("no board pose fits the corners found")
    errors = np.asarray(errors, dtype=float).ravel()
    order = np.argsort(errors)
    best = order[0]
    if n > 1 and errors[order[1]] < AMBIGUITY_RATIO * max(errors[best], 1e-3):
        raise VisionError(f"ambiguous board pose: two poses explain the corners with RMS {errors[best]:.2f} and "
                          f"{errors[order[1]]:.2f} px (a small or distant board seen head-on); tilt the view")
    rvec, tvec = cv2.solvePnPRefineLM(object_points, corners.uv, K, np.asarray(dist, float), rvecs[best], tvecs[best])
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    projected = cv2.projectPoints(object_points, rvec, tvec, K, np.asarray(dist, float))[0].reshape(-1, 2)
    return T, float(np.sqrt(np.mean(np.sum((projected - corners.uv) ** 2, axis=1))))
