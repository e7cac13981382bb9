"""Where what a hand-eye-calibrated camera sees at a pixel lies, in the base frame, and how sure that is.

The pixel's ray leaves the lens (the fitted intrinsics undo the distortion) from where the camera is: the flange's
pose times X on the wrist, Y over the table. It meets a plane: the board's (eye-in-hand, Y's z = 0: the table the
board lies on) or the horizontal plane at height z. The 1-sigma comes from the calibration's covariance of X, Y and
the intrinsics (the arm's stated accuracy included, as in the fit's reported sigmas), propagated through that
construction; the feature's own pixel noise is not in it.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.errors import CalibrationInputError
from calibration.models.hand_eye import Intrinsics, pose_from_dict

PARAMETERS = ([f"X_{a}" for a in ("rx", "ry", "rz", "x", "y", "z")] + [f"Y_{a}" for a in ("rx", "ry", "rz", "x", "y", "z")]
              + ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"])  # as the fit names them
STEP = 1e-6  # central differences: rad, m and the intrinsics' own units scaled below
UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def _perturbed(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """As the fit perturbs X and Y: turned by rotation vector p[:3] in its own frame, moved by p[3:] in its parent's."""
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(p[:3]).as_matrix()
    out[:3, 3] = T[:3, 3] + p[3:6]
    return out


def flange_from_values(values) -> np.ndarray:
    """The 4x4 (m) of a flange pose given as (x_mm, y_mm, z_mm, qw, qx, qy, qz)."""
    values = [float(v) for v in values]
    if len(values) != 7 or not all(math.isfinite(v) for v in values):
        raise CalibrationInputError(f"flange: {values}; allowed: seven finite numbers x_mm, y_mm, z_mm, qw, qx, qy, qz")
    try:
        return pose_from_dict(dict(zip(("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz"), values)))
    except CalibrationInputError as exc:
        raise CalibrationInputError(f"flange: {exc}") from None


class HandEyeCamera:
    """A camera as its active hand-eye calibration (a `hand-eye` model) describes it."""

    def __init__(self, model: dict):
        try:
            self.mount = model["mount"]
            self.X, self.Y = pose_from_dict(model["hand_eye"]), pose_from_dict(model["world"])
            self.lens = Intrinsics.from_dict(model["intrinsics"])
        except KeyError as exc:
            raise CalibrationInputError(f"the hand-eye calibration lacks {exc.args[0]!r}: fit it again") from None
        cov = model.get("covariance")
        self.covariance = None if cov is None else _ordered(cov["names"], np.asarray(cov["matrix"], dtype=float))
        floor = model.get("arm_accuracy") or {"mm": 0.0, "deg": 0.0}
        self.floor = (floor["mm"] * 1e-3, math.radians(floor["deg"]))

    @property
    def rides_arm(self) -> bool:
        return self.mount == "eye-in-hand"

    def check_on_image(self, uv: np.ndarray) -> None:
        w, h = self.lens.width, self.lens.height
        off = np.nonzero(~((uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)))[0]
        if off.size:
            u, v = uv[off[0]]
            raise CalibrationInputError(f"pixel ({u:g}, {v:g}) is off the camera's {w} x {h} image; allowed: u in "
                                        f"[0, {w - 1}], v in [0, {h - 1}]")

    def locate(self, uv, T_base_flange: np.ndarray | None = None, z_m: float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) base-frame points (m) of pixels uv on the plane, and each one's 1-sigma per axis in the plane
        (sqrt(trace(C) / 2), m; NaN when the calibration keeps no covariance)."""
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        if self.rides_arm and T_base_flange is None:
            raise CalibrationInputError("the camera rides the arm (eye-in-hand): locating with it needs the flange "
                                        "pose the arm reports")
        if not self.rides_arm and z_m is None:
            raise CalibrationInputError("eye-to-hand: give the height z_mm of the plane to locate on (the board this "
                                        "camera was calibrated with rides the flange, not the table)")
        self.check_on_image(uv)
        points = self._points(np.zeros(self._n_params()), uv, T_base_flange, z_m)
        if self.covariance is None:
            return points, np.full(len(uv), np.nan)
        C = self._parameter_covariance()
        J = np.stack([(self._points(d, uv, T_base_flange, z_m) - self._points(-d, uv, T_base_flange, z_m)) / (2 * s)
                      for d, s in self._steps()], axis=-1)  # (n, 3, p)
        cov = np.einsum("nip,pq,njq->nij", J, C, J)
        return points, np.sqrt(np.clip(np.trace(cov, axis1=1, axis2=2), 0, None) / 2)

    # -- the construction, as a function of a perturbation of the parameters ----------------------------------
    def _n_params(self) -> int:
        return len(PARAMETERS)

    def _steps(self):
        scales = np.r_[[1.0] * 12, [self.lens.fx, self.lens.fy, self.lens.fx, self.lens.fy], [1.0] * 5]
        for i in range(self._n_params()):
            d = np.zeros(self._n_params())
            d[i] = STEP * scales[i]
            yield d, d[i]

    def _points(self, d: np.ndarray, uv: np.ndarray, T_base_flange, z_m) -> np.ndarray:
        X, Y = _perturbed(self.X, d[0:6]), _perturbed(self.Y, d[6:12])
        lens = self.lens.with_vector(self.lens.vector() + d[12:21])
        T_base_camera = T_base_flange @ X if self.rides_arm else Y
        xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), lens.K(), np.asarray(lens.dist), None, None, None,
                                 UNDISTORT).reshape(-1, 2)
        rays = T_base_camera[:3, :3] @ np.column_stack([xy, np.ones(len(xy))]).T  # (3, n)
        origin = T_base_camera[:3, 3]
        if z_m is None:  # the board's plane
            normal, on_plane = Y[:3, 2], Y[:3, 3]
        else:
            normal, on_plane = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, z_m])
        facing = normal @ rays
        if np.any(np.abs(facing) < 1e-9):
            raise CalibrationInputError("the pixel's ray runs along the plane: it meets it nowhere")
        t = (normal @ (on_plane - origin)) / facing
        if np.any(t <= 0):
            raise CalibrationInputError("the plane is behind the camera at this pixel: check z_mm")
        return (origin[:, None] + rays * t).T

    def _parameter_covariance(self) -> np.ndarray:
        """X's, Y's and the intrinsics' block of the fit's covariance, the arm's accuracy added to X and Y."""
        C = self.covariance.copy()
        t, r = self.floor
        C[np.diag_indices(12)] += np.tile(np.r_[[r ** 2] * 3, [t ** 2] * 3], 2)
        return C


def _ordered(names: list[str], matrix: np.ndarray) -> np.ndarray:
    """The fit's covariance over PARAMETERS, zero for those it held (the intrinsics, when stored ones were used)."""
    index = {n: i for i, n in enumerate(names)}
    if matrix.shape != (len(names), len(names)) or not all(p in index for p in PARAMETERS[:12]):
        raise CalibrationInputError("the hand-eye calibration's covariance does not cover X and Y: fit it again")
    have = [(k, index[p]) for k, p in enumerate(PARAMETERS) if p in index]
    C = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    for a, i in have:
        for b, j in have:
            C[a, b] = matrix[i, j]
    return C
