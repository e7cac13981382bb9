"""Hand-eye calibration: where a camera sits on the flange (or the board on the flange), and where the board (or
the camera) sits in the base frame, with an uncertainty that can be trusted.

Two mounts, named by their frames (T_a_b is b's pose in a, so T_a_b @ T_b_c = T_a_c):
- eye-in-hand: X = T_flange_camera, Y = T_base_board; a board point p is in the camera at
  inv(X) @ inv(T_base_flange) @ Y @ p;
- eye-to-hand: X = T_flange_board, Y = T_base_camera; the camera sees inv(Y) @ T_base_flange @ X @ p.

`fit_views` is one simultaneous adjustment over the reprojection error of every corner in every image: X, Y, the
camera's intrinsics and the board's printed scale together. The usual chain (intrinsics, then a PnP pose per
image, then a closed-form AX = XB) only initialises it: each link of a chain passes its error on to the next,
which seed 000 measures for its model matching and which the closed-form methods show here (their X is two to
ten times further off on the same images).

The arm is not perfect: a factory-calibrated six-axis arm reaches a pose within about 0.1 mm and 0.01 deg, and that
error is the same for every corner of one image, so the corner residuals of an image are correlated. Each image
therefore gets a small flange-pose correction, a random effect with a zero-mean prior of the arm's accuracy; the
pixel noise and the arm's accuracy are re-estimated from the residuals by variance-component estimation
(Förstner), and the covariance of X and Y is the marginal of the whole adjustment. So the reported sigma grows
when the arm, not the camera, limits the result, instead of shrinking with the number of corners.

`fit_pose_pairs` does the same from pose pairs alone (the flange pose and the camera->board pose measured at it,
what easy_handeye, MoveIt or a teach pendant give): the best closed-form start, then a robust joint refinement of X
and Y with outlier pairs dropped and a covariance. `check_motion` refuses the classic source of garbage, rotations
about one axis or too small, naming what poses to add.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import sparse
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative, group_columns  # least_squares' own sparse differences
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from calibration.errors import CalibrationInputError

MOUNTS = ("eye-in-hand", "eye-to-hand")
MIN_VIEWS = 3
OUTLIER_Z = 5.0  # an image (or a pose pair) this many robust sigmas worse than the others is dropped
GROSS_PX = 0.5  # ... and only if its corners are off by more than this RMS: sub-pixel differences are lens and light
SCALE_PRIOR = 0.01  # pose pairs: the board printed within about 1 % of its drawing (a weak 1-sigma prior)
BOUND95_3D = math.sqrt(chi2.ppf(0.95, 3))
OPENCV_HAND_EYE = {"TSAI": cv2.CALIB_HAND_EYE_TSAI, "PARK": cv2.CALIB_HAND_EYE_PARK,
                   "HORAUD": cv2.CALIB_HAND_EYE_HORAUD, "ANDREFF": cv2.CALIB_HAND_EYE_ANDREFF,
                   "DANIILIDIS": cv2.CALIB_HAND_EYE_DANIILIDIS}
OPENCV_ROBOT_WORLD = {"SHAH": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH, "LI": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI}


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float]  # k1 k2 p1 p2 k3, OpenCV's order

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def vector(self) -> np.ndarray:
        return np.array([self.fx, self.fy, self.cx, self.cy, *self.dist])

    def with_vector(self, v) -> "Intrinsics":
        v = [float(x) for x in v]
        return Intrinsics(self.width, self.height, *v[:4], tuple(v[4:9]))

    def to_dict(self) -> dict:
        return {"width_px": self.width, "height_px": self.height, "fx_px": self.fx, "fy_px": self.fy,
                "cx_px": self.cx, "cy_px": self.cy, **dict(zip(("k1", "k2", "p1", "p2", "k3"), self.dist))}

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        try:
            return cls(int(d["width_px"]), int(d["height_px"]), float(d["fx_px"]), float(d["fy_px"]),
                       float(d["cx_px"]), float(d["cy_px"]), tuple(float(d[k]) for k in ("k1", "k2", "p1", "p2", "k3")))
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationInputError(f"intrinsics: {exc!r}; expected width_px, height_px, fx_px, fy_px, cx_px, "
                                        "cy_px, k1, k2, p1, p2, k3") from None


@dataclass
class View:
    """One image at one robot pose."""

    pose: str
    T_base_flange: np.ndarray  # as the arm reported it
    ids: np.ndarray  # (n,) corner ids
    uv: np.ndarray  # (n, 2) px


@dataclass(frozen=True)
class Board:
    corners: np.ndarray  # (N, 3) nominal corner positions in the board frame (m), by id


@dataclass
class HandEyeResult:
    """X and Y with their 1-sigma: translations in the parent frame's axes (the flange's for X, the base's for Y),
    rotations as small angles about the parent frame's axes."""

    mount: str
    X: np.ndarray
    Y: np.ndarray
    intrinsics: Intrinsics | None
    board_scale: float
    sigma_X_translation_m: np.ndarray
    sigma_X_rotation_rad: np.ndarray
    sigma_Y_translation_m: np.ndarray
    sigma_Y_rotation_rad: np.ndarray
    bound95_X_translation_m: float  # |translation error| below this with 95 % (3-D, along the worst direction)
    bound95_X_rotation_rad: float
    covariance: np.ndarray
    parameter_names: list[str]
    rms_px: float | None
    per_view: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    iterations: int = 0
    noise: dict = field(default_factory=dict)  # the variance components as estimated: px, arm mm and deg


# -- small SE(3) helpers ---------------------------------------------------------------------------------------------
def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4) if T.ndim == 2 else np.tile(np.eye(4), (T.shape[0], 1, 1))
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    return out


def _T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _perturbed(T0: np.ndarray, p: np.ndarray) -> np.ndarray:
    """T0 turned by rotation vector p[:3] in its own frame and moved by p[3:] in its parent's."""
    return _T(T0[:3, :3] @ Rotation.from_rotvec(p[:3]).as_matrix(), T0[:3, 3] + p[3:6])


def _rigid_batch(p: np.ndarray) -> np.ndarray:
    """(n, 4, 4) of (n, 6) rotation vectors and translations."""
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(p[:, :3]).as_matrix()
    T[:, :3, 3] = p[:, 3:]
    return T


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation distance m, rotation angle rad) between two transforms."""
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(Rotation.from_matrix(dR).magnitude())


def pose_to_dict(T: np.ndarray) -> dict:
    """{x_mm, y_mm, z_mm, qw, qx, qy, qz}, qw >= 0."""
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return {"x_mm": float(T[0, 3] * 1e3), "y_mm": float(T[1, 3] * 1e3), "z_mm": float(T[2, 3] * 1e3),
            "qw": float(w), "qx": float(x), "qy": float(y), "qz": float(z)}


def pose_from_dict(d: dict) -> np.ndarray:
    """The 4x4 (m) of {x_mm, ..., qz}; CalibrationInputError naming the field that is missing, not finite, or a
    quaternion not of unit length (within 1e-6)."""
    values = {}
    for k in ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz"):
        if k not in d:
            raise CalibrationInputError(f"{k} is missing (a pose is x_mm, y_mm, z_mm, qw, qx, qy, qz)")
        try:
            values[k] = float(d[k])
        except (TypeError, ValueError):
            raise CalibrationInputError(f"{k}={d[k]!r} is not a number") from None
        if not math.isfinite(values[k]):
            raise CalibrationInputError(f"{k}={d[k]} is not a finite number")
    q = np.array([values["qx"], values["qy"], values["qz"], values["qw"]])
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-6:
        raise CalibrationInputError(f"the quaternion (qw, qx, qy, qz) has length {norm:.9f}, not 1 (within 1e-6)")
    return _T(Rotation.from_quat(q).as_matrix(), [values["x_mm"] * 1e-3, values["y_mm"] * 1e-3, values["z_mm"] * 1e-3])


def _check_mount(mount: str) -> None:
    if mount not in MOUNTS:
        raise CalibrationInputError(f"mount={mount!r}; allowed: {', '.join(MOUNTS)}")


def _check_transforms(Ts, what: str) -> np.ndarray:
    arr = np.asarray(Ts, dtype=float)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise CalibrationInputError(f"{what}: expected 4x4 transforms, got an array of shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationInputError(f"{what}: a transform holds a value that is not finite")
    return arr


# -- motion ---------------------------------------------------------------------------------------------------------
def check_motion(T_base_flange_list, min_angle_deg: float = 5.0, min_spread: float = 0.1) -> dict:
    """Whether the flange's rotations can identify a hand-eye rotation; CalibrationInputError naming what to add.

    Each pair of poses rotates the flange by an angle about an axis (in the first pose's flange frame). The
    rotation-axis spread is sqrt(l2 / l1) of the angle-weighted scatter of those axes, sum of angle^2 a a^T: 0 when
    every rotation is about one axis (AX = XB then leaves X's translation along it and its rotation about it
    free), 1 when the axes spread as much in a second direction as in the first."""
    F = _check_transforms(T_base_flange_list, "flange poses")
    n = len(F)
    if n < 2:
        raise CalibrationInputError(f"{n} pose: a hand-eye fit needs rotations between poses, so at least "
                                    f"{MIN_VIEWS} poses")
    i, j = np.triu_indices(n, 1)
    rel = Rotation.from_matrix(np.swapaxes(F[i, :3, :3], 1, 2) @ F[j, :3, :3]).as_rotvec()
    angles = np.linalg.norm(rel, axis=1)
    k = int(np.argmax(angles))
    largest = math.degrees(angles[k])
    if largest < min_angle_deg:
        raise CalibrationInputError(
            f"rotations too small: the largest between two poses is {largest:.2f} deg (poses {i[k] + 1} and "
            f"{j[k] + 1}); tilt the tool by at least {min_angle_deg:g} deg between poses, about two different axes")
    scatter = rel.T @ rel
    values, vectors = np.linalg.eigh(scatter)  # ascending
    spread = float(math.sqrt(max(values[1], 0.0) / values[2]))
    if spread < min_spread:
        axis, others = vectors[:, 2], (vectors[:, 1], vectors[:, 0])
        axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
        said = ", ".join("(" + ", ".join(f"{v:.2f}" for v in o) + ")" for o in others)
        raise CalibrationInputError(
            "rotation axes span one direction: the poses rotate about ~(" + ", ".join(f"{v:.2f}" for v in axis)
            + f") in the flange frame (spread {spread:.2f}, at least {min_spread:g} needed); add poses tilted about "
            f"{said} of the flange")
    return {"max_angle_deg": largest, "spread": spread, "axis_singular_values": [float(math.sqrt(max(v, 0)))
                                                                                for v in values[::-1]],
            "n_pairs": int(len(i))}


# -- closed forms (OpenCV) -----------------------------------------------------------------------------------------
def _split(Ts: np.ndarray):
    return [T[:3, :3] for T in Ts], [T[:3, 3].reshape(3, 1) for T in Ts]


def _valid(T) -> bool:
    return T is not None and np.all(np.isfinite(T)) and abs(np.linalg.det(T[:3, :3]) - 1) < 1e-3


def _mean_transform(Ts: np.ndarray) -> np.ndarray:
    return _T(Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix(), Ts[:, :3, 3].mean(axis=0))


def opencv_baselines(T_base_flange_list, T_camera_board_list, mount: str) -> dict[str, dict]:
    """OpenCV's five calibrateHandEye methods and calibrateRobotWorldHandEye (SHAH, LI) on the same pose pairs:
    name -> {"X", "Y", "error"}; a method that fails or returns NaN has X = Y = None and the reason."""
    _check_mount(mount)
    F = _check_transforms(T_base_flange_list, "flange poses")
    B = _check_transforms(T_camera_board_list, "camera->board poses")
    out = {}
    # calibrateHandEye: eye-in-hand takes gripper->base (F) and gives cam->gripper (X); eye-to-hand takes the
    # inverse robot poses and gives cam->base (Y); the other transform is the average that closes the loop
    robot = F if mount == "eye-in-hand" else _inv(F)
    Rg, tg = _split(robot)
    Rb, tb = _split(B)
    for name, method in OPENCV_HAND_EYE.items():
        try:
            R, t = cv2.calibrateHandEye(Rg, tg, Rb, tb, method=method)
            solved = _T(R, np.asarray(t).ravel())
            if not _valid(solved):
                raise ValueError("returned a rotation that is not one (NaN or not orthonormal)")
            if mount == "eye-in-hand":
                X, Y = solved, _mean_transform(F @ solved @ B)
            else:
                Y, X = solved, _mean_transform(_inv(F) @ solved @ B)
            out[name] = {"X": X, "Y": Y, "error": None}
        except (cv2.error, ValueError, np.linalg.LinAlgError) as exc:
            out[name] = {"X": None, "Y": None, "error": f"{name}: {str(exc).strip().splitlines()[-1]}"}
    # calibrateRobotWorldHandEye solves T_cam_world @ T_world_base = T_cam_gripper @ T_gripper_base; eye-to-hand
    # reads "cam" as the flange's board and "world" as the fixed camera
    world2cam = B if mount == "eye-in-hand" else _inv(B)
    Rw, tw = _split(world2cam)
    Rr, tr = _split(_inv(F))
    for name, method in OPENCV_ROBOT_WORLD.items():
        try:
            R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(Rw, tw, Rr, tr, method=method)
            T_world_base, T_cam_gripper = _T(R_bw, np.ravel(t_bw)), _T(R_gc, np.ravel(t_gc))
            if not (_valid(T_world_base) and _valid(T_cam_gripper)):
                raise ValueError("returned a rotation that is not one (NaN or not orthonormal)")
            out[name] = {"X": _inv(T_cam_gripper), "Y": _inv(T_world_base), "error": None}
        except (cv2.error, ValueError, np.linalg.LinAlgError) as exc:
            out[name] = {"X": None, "Y": None, "error": f"{name}: {str(exc).strip().splitlines()[-1]}"}
    return out


def _predicted(X, Y, F, mount: str) -> np.ndarray:
    """T_camera_board predicted at flange poses F (n, 4, 4)."""
    if mount == "eye-in-hand":
        return _inv(F @ X) @ Y
    return _inv(Y) @ F @ X


def _pair_residuals(X, Y, F, B, mount) -> np.ndarray:
    """(n, 6): rotation (rad) and translation (m) of each measured camera->board pose off the prediction."""
    P = _predicted(X, Y, F, mount)
    rot = Rotation.from_matrix(np.swapaxes(B[:, :3, :3], 1, 2) @ P[:, :3, :3]).as_rotvec()
    return np.hstack([rot, P[:, :3, 3] - B[:, :3, 3]])


def _best_closed_form(F, B, mount) -> tuple[np.ndarray, np.ndarray, str]:
    best = None
    for name, b in opencv_baselines(F, B, mount).items():
        if b["X"] is None:
            continue
        r = _pair_residuals(b["X"], b["Y"], F, B, mount)
        score = float(np.median(np.linalg.norm(r[:, 3:], axis=1)) + 0.1 * np.median(np.linalg.norm(r[:, :3], axis=1)))
        if best is None or score < best[0]:
            best = (score, b["X"], b["Y"], name)
    if best is None:
        raise CalibrationInputError("no closed-form hand-eye method found a solution: check that the pose pairs "
                                    "belong together (flange pose and camera->board pose of the same moment)")
    return best[1], best[2], best[3]


# -- variance components ------------------------------------------------------------------------------------------
def _redundancy(J: sparse.spmatrix | np.ndarray, groups: list[np.ndarray]) -> tuple[list[float], np.ndarray]:
    """Each group's redundancy (its rows minus the trace of its part of the hat matrix, tr(inv(N) Jg^T Jg)), and
    inv(N), N = J^T J. J stays sparse: the normal matrices are small even when J has tens of thousands of rows."""
    J = sparse.csr_matrix(J)
    N = (J.T @ J).toarray()
    Ninv = np.linalg.pinv(N, rcond=1e-12, hermitian=True)
    reds = []
    for rows in groups:
        Jg = J[rows]
        reds.append(float(len(rows) - np.sum(Ninv * (Jg.T @ Jg).toarray())))
    return reds, Ninv


def _robust_sigma(values: np.ndarray) -> tuple[float, float]:
    median = float(np.median(values))
    return median, float(1.4826 * np.median(np.abs(values - median))) or max(median * 0.1, 1e-12)


# -- the simultaneous adjustment of images -------------------------------------------------------------------------
class ViewProblem:
    """Parameters: X (rotvec, t), Y (rotvec, t), [intrinsics], [log board scale], a 6-vector per view (the flange
    correction: rotation vector, translation in the flange frame). Residuals: each corner's (u, v) over the pixel
    sigma, then each view's correction over the arm's sigmas."""

    def __init__(self, views, board, mount, lens0, X0, Y0, fit_intrinsics, fit_scale):
        self.views, self.mount, self.lens0 = views, mount, lens0
        self.X0, self.Y0 = X0, Y0
        self.fit_intrinsics, self.fit_scale = fit_intrinsics, fit_scale
        self.view_of = np.concatenate([np.full(len(v.ids), k) for k, v in enumerate(views)])
        self.points = np.concatenate([board.corners[v.ids] for v in views])
        self.uv = np.concatenate([v.uv for v in views])
        self.F = np.array([v.T_base_flange for v in views])
        self.n_lens = 9 if fit_intrinsics else 0
        self.n_global = 12 + self.n_lens + (1 if fit_scale else 0)
        self.n = len(views)
        self.sigma_px, self.sigma_t, self.sigma_r = 0.2, 1e-4, math.radians(0.01)

    def unpack(self, x):
        X = _perturbed(self.X0, x[0:6])
        Y = _perturbed(self.Y0, x[6:12])
        k = 12
        lens = self.lens0.with_vector(x[k:k + 9]) if self.fit_intrinsics else self.lens0
        k += self.n_lens
        scale = math.exp(x[k]) if self.fit_scale else 1.0
        deltas = x[self.n_global:].reshape(self.n, 6)
        return X, Y, lens, scale, deltas

    def x0(self):
        x = np.zeros(self.n_global + 6 * self.n)
        if self.fit_intrinsics:
            x[12:21] = self.lens0.vector()
        return x

    def flanges(self, x) -> np.ndarray:
        """(n, 4, 4) flange poses of the views: as the arm reported them (an arm calibration computes them)."""
        return self.F

    def camera_board(self, x) -> np.ndarray:
        X, Y, _, _, deltas = self.unpack(x)
        D = _rigid_batch(deltas)  # flange corrections: true flange = reported @ D
        return _predicted(X, Y, self.flanges(x) @ D, self.mount)

    def project(self, x) -> np.ndarray:
        _, _, lens, scale, _ = self.unpack(x)
        T = self.camera_board(x)[self.view_of]
        p = np.einsum("nij,nj->ni", T[:, :3, :3], self.points * scale) + T[:, :3, 3]
        return distort(lens, p)

    def residuals(self, x) -> np.ndarray:
        _, _, _, _, deltas = self.unpack(x)
        r_img = ((self.project(x) - self.uv) / self.sigma_px).ravel()
        r_arm = (deltas / np.r_[[self.sigma_r] * 3, [self.sigma_t] * 3]).ravel()
        return np.concatenate([r_img, r_arm])

    def sparsity(self) -> sparse.lil_matrix:
        m = 2 * len(self.uv) + 6 * self.n
        S = sparse.lil_matrix((m, self.n_global + 6 * self.n), dtype=int)
        rows = np.arange(2 * len(self.uv))
        S[rows, :self.n_global] = 1
        for k in range(self.n):
            corner_rows = np.flatnonzero(np.repeat(self.view_of == k, 2))
            cols = self.n_global + 6 * k + np.arange(6)
            S[np.ix_(corner_rows, cols)] = 1
            S[2 * len(self.uv) + 6 * k + np.arange(6), cols] = 1
        return S

    def names(self) -> list[str]:
        names = [f"X_{a}" for a in ("rx", "ry", "rz", "x", "y", "z")] + [f"Y_{a}" for a in ("rx", "ry", "rz", "x", "y", "z")]
        if self.fit_intrinsics:
            names += ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
        if self.fit_scale:
            names.append("log_board_scale")
        return names + [f"{v.pose}_{a}" for v in self.views for a in ("rx", "ry", "rz", "x", "y", "z")]


def distort(lens: Intrinsics, p: np.ndarray) -> np.ndarray:
    """OpenCV's pinhole with (k1, k2, p1, p2, k3) of camera-frame points (n, 3): (n, 2) px."""
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    k1, k2, p1, p2, k3 = lens.dist
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([lens.fx * xd + lens.cx, lens.fy * yd + lens.cy])


def _pnp(view: View, board: Board, lens: Intrinsics) -> np.ndarray:
    ok, rvec, tvec = cv2.solvePnP(board.corners[view.ids], view.uv, lens.K(), np.asarray(lens.dist))
    if not ok:
        raise CalibrationInputError(f"pose {view.pose}: no board pose fits its corners")
    return _T(cv2.Rodrigues(rvec)[0], tvec.ravel())


def _check_views(views, board) -> None:
    for v in views:
        ids, uv = np.asarray(v.ids), np.asarray(v.uv, dtype=float)
        if uv.shape != (len(ids), 2):
            raise CalibrationInputError(f"pose {v.pose}: {len(ids)} corner ids but uv of shape {uv.shape}")
        if len(ids) and (ids.min() < 0 or ids.max() >= len(board.corners)):
            raise CalibrationInputError(f"pose {v.pose}: corner id {int(ids.max())} outside the board's "
                                        f"0..{len(board.corners) - 1}")
        if not np.all(np.isfinite(uv)):
            raise CalibrationInputError(f"pose {v.pose}: a corner's pixel is not a finite number")
        _check_transforms([v.T_base_flange], f"pose {v.pose}: flange pose")


def fit_views(views: list[View], board: Board, mount: str, intrinsics0: Intrinsics, fit_intrinsics: bool = True,
              fit_scale: bool = True, loss: str = "soft_l1", arm_sigma_m: float = 1e-4,
              arm_sigma_rad: float = math.radians(0.01), X0=None, Y0=None,
              arm_accuracy: tuple[float, float] = (1e-4, math.radians(0.01)), estimate_noise: bool = True) -> HandEyeResult:
    """The simultaneous adjustment (module docstring). `arm_sigma_*`: the first guess of the arm's pose error per
    image (re-estimated); `arm_accuracy`: the arm's stated accuracy (m, rad, 1-sigma per axis), the floor of X's and
    Y's uncertainty."""
    _check_mount(mount)
    _check_views(views, board)
    views = [v for v in views if len(v.ids) >= 4]
    if len(views) < MIN_VIEWS:
        raise CalibrationInputError(f"{len(views)} images with board corners, fewer than the {MIN_VIEWS} a hand-eye "
                                    "fit needs (15 or more well-spread poses give a trustworthy result)")
    check_motion([v.T_base_flange for v in views])
    if X0 is None or Y0 is None:
        F = np.array([v.T_base_flange for v in views])
        B = np.array([_pnp(v, board, intrinsics0) for v in views])
        X0, Y0, _ = _best_closed_form(F, B, mount)
    rejected: list[dict] = []
    while True:
        problem, solution, noise = _adjust(views, board, mount, intrinsics0, X0, Y0, fit_intrinsics, fit_scale,
                                           loss, arm_sigma_m, arm_sigma_rad, estimate_noise)
        worst = _worst_view(problem, solution.x)
        if worst is None or len(views) - 1 < MIN_VIEWS:
            break
        k, reason = worst
        rejected.append({"pose": views[k].pose, "reason": reason})
        X0, Y0 = problem.unpack(solution.x)[:2]
        views = views[:k] + views[k + 1:]
    return _result(problem, solution, noise, rejected, arm_accuracy)


def _adjust(views, board, mount, lens0, X0, Y0, fit_intrinsics, fit_scale, loss, arm_sigma_m, arm_sigma_rad,
            estimate_noise=True):
    problem = ViewProblem(views, board, mount, lens0, X0, Y0, fit_intrinsics, fit_scale)
    return adjust(problem, loss, arm_sigma_m, arm_sigma_rad, estimate_noise)


def adjust(problem: ViewProblem, loss: str, arm_sigma_m: float, arm_sigma_rad: float, estimate_noise: bool = True):
    """The adjustment of a view problem, its variance components re-estimated until they settle: (problem, the
    solution, the noise as estimated)."""
    problem.sigma_t, problem.sigma_r = arm_sigma_m, arm_sigma_rad
    S = problem.sparsity()
    x = problem.x0()
    n_img = 2 * len(problem.uv)
    groups = [np.arange(n_img),
              n_img + (6 * np.arange(problem.n)[:, None] + np.array([3, 4, 5])).ravel(),
              n_img + (6 * np.arange(problem.n)[:, None] + np.array([0, 1, 2])).ravel()]
    solution = None
    for _ in range(6 if estimate_noise else 0):
        solution = least_squares(problem.residuals, x, jac_sparsity=S, loss=loss, f_scale=3.0, x_scale="jac",
                                 method="trf", tr_solver="lsmr", max_nfev=8)  # a few steps: the next round goes on from here
        x = solution.x
        J = _whitened_jacobian(problem, x, S)
        reds, _ = _redundancy(J, groups)
        r = problem.residuals(x)
        factors = [float(np.sum(r[g] ** 2) / max(red, 1e-9)) for g, red in zip(groups, reds)]
        new = (problem.sigma_px * math.sqrt(factors[0]),
               float(np.clip(problem.sigma_t * math.sqrt(factors[1]), 1e-6, 5e-3)),
               float(np.clip(problem.sigma_r * math.sqrt(factors[2]), math.radians(1e-4), math.radians(0.5))))
        settled = all(abs(math.log(a / b)) < 0.05 for a, b in zip(new, (problem.sigma_px, problem.sigma_t,
                                                                       problem.sigma_r)))
        problem.sigma_px, problem.sigma_t, problem.sigma_r = new
        if settled:
            break
    solution = least_squares(problem.residuals, x, jac_sparsity=S, loss=loss, f_scale=3.0, x_scale="jac",
                             method="trf", tr_solver="lsmr", max_nfev=200)
    noise = {"pixel_px": problem.sigma_px, "arm_mm": problem.sigma_t * 1e3,
             "arm_deg": math.degrees(problem.sigma_r)}
    return problem, solution, noise


def _whitened_jacobian(problem, x, S):
    """The Jacobian of the whitened residuals (no robust weights: the covariance is the model's, not the loss's)."""
    return approx_derivative(problem.residuals, x, method="2-point", sparsity=(S, group_columns(S)))


def _worst_view(problem: ViewProblem, x) -> tuple[int, str] | None:
    """The view whose corners (or whose flange correction) stand out from the rest, with the reason; None if none
    does."""
    err = problem.project(x) - problem.uv
    rms = np.array([math.sqrt(np.mean(np.sum(err[problem.view_of == k] ** 2, axis=1))) for k in range(problem.n)])
    deltas = problem.unpack(x)[4]
    arm = np.sqrt(np.sum((deltas[:, 3:] / problem.sigma_t) ** 2, axis=1) + np.sum((deltas[:, :3] / problem.sigma_r) ** 2,
                                                                                  axis=1))
    median, spread = _robust_sigma(rms)
    z_img = (rms - median) / spread
    a_median, a_spread = _robust_sigma(arm)
    z_arm = (arm - a_median) / a_spread
    k_img, k_arm = int(np.argmax(z_img)), int(np.argmax(z_arm))
    if z_img[k_img] >= z_arm[k_arm] and z_img[k_img] > OUTLIER_Z and rms[k_img] > max(3 * median, GROSS_PX):
        return k_img, (f"reprojection RMS {rms[k_img]:.2f} px, {z_img[k_img]:.1f} robust sigmas above the median "
                       f"{median:.2f} px")
    if z_arm[k_arm] > OUTLIER_Z and arm[k_arm] > 2 * a_median:
        t = np.linalg.norm(deltas[k_arm, 3:]) * 1e3
        r = math.degrees(np.linalg.norm(deltas[k_arm, :3]))
        return k_arm, (f"the flange pose the arm reported is off by {t:.2f} mm / {r:.3f} deg from what the images "
                       f"say ({z_arm[k_arm]:.1f} robust sigmas above the other poses): was the pose recorded while "
                       "the arm moved?")
    return None


def _covariance_blocks(cov: np.ndarray, X: np.ndarray, Y: np.ndarray, floor: tuple[float, float]):
    """1-sigma of X and Y (translation, rotation about the parent's axes) and X's 95 % bounds, each with the arm's
    own accuracy `floor` (m, rad per axis) added: the part of the arm's error that is the same at every pose, in the
    flange frame (for X) or the base frame (for Y), looks exactly like a different X or Y, so no hand-eye data can
    reduce it below what the arm's calibration leaves."""
    def block(i, R):
        rot = R @ cov[i:i + 3, i:i + 3] @ R.T  # rotation vector in the child frame -> about the parent's axes
        trans = cov[i + 3:i + 6, i + 3:i + 6]
        return trans + floor[0] ** 2 * np.eye(3), rot + floor[1] ** 2 * np.eye(3)

    tX, rX = block(0, X[:3, :3])
    tY, rY = block(6, Y[:3, :3])
    sd = lambda C: np.sqrt(np.clip(np.diag(C), 0, None))  # noqa: E731 (a one-line helper)
    bound = lambda C: float(BOUND95_3D * math.sqrt(max(np.linalg.eigvalsh(C).max(), 0.0)))  # noqa: E731
    return sd(tX), sd(rX), sd(tY), sd(rY), bound(tX), bound(rX)


def _result(problem: ViewProblem, solution, noise, rejected, floor) -> HandEyeResult:
    x = solution.x
    X, Y, lens, scale, deltas = problem.unpack(x)
    J = _whitened_jacobian(problem, x, problem.sparsity())
    groups = [np.arange(2 * len(problem.uv))]
    _, Ninv = _redundancy(J, groups)
    cov = Ninv[:problem.n_global, :problem.n_global]
    sX, rX, sY, rY, bX, bR = _covariance_blocks(cov, X, Y, floor)
    err = problem.project(x) - problem.uv
    per_view = []
    for k, v in enumerate(problem.views):
        e = err[problem.view_of == k]
        per_view.append({"pose": v.pose, "n": len(v.ids), "rms_px": float(math.sqrt(np.mean(np.sum(e ** 2, axis=1)))),
                         "arm_correction_mm": float(np.linalg.norm(deltas[k, 3:]) * 1e3),
                         "arm_correction_deg": float(math.degrees(np.linalg.norm(deltas[k, :3]))), "inlier": True})
    return HandEyeResult(problem.mount, X, Y, lens, scale, sX, rX, sY, rY,
                         bX, bR, cov, problem.names()[:problem.n_global],
                         float(math.sqrt(np.mean(np.sum(err ** 2, axis=1)))), per_view, rejected, int(solution.nfev),
                         noise)


# -- pose pairs -----------------------------------------------------------------------------------------------------
def _pair_errors(X, Y, F, B, mount) -> np.ndarray:
    """(n, 6): the predicted camera->board pose times the inverse of the measured one, E = P inv(B), as a rotation
    vector and a translation, in the camera frame. A measured pose turned a little about the camera shows as a
    rotation alone here, not also as a translation of the board by the rotation times its distance."""
    P = _predicted(X, Y, F, mount)
    R = P[:, :3, :3] @ np.swapaxes(B[:, :3, :3], 1, 2)
    t = P[:, :3, 3] - np.einsum("nij,nj->ni", R, B[:, :3, 3])
    return np.hstack([Rotation.from_matrix(R).as_rotvec(), t])


def fit_pose_pairs(T_base_flange_list, T_camera_board_list, mount: str, loss: str = "soft_l1",
                   arm_accuracy: tuple[float, float] = (1e-4, math.radians(0.01))) -> HandEyeResult:
    """X and Y from pose pairs alone: the best of OpenCV's closed forms, then a robust joint refinement over every
    pair's discrepancy (`_pair_errors`), its rotation and its translation each weighed by its own sigma, estimated
    from the residuals, outlier pairs dropped with the reason, and the covariance of the result."""
    _check_mount(mount)
    F = _check_transforms(T_base_flange_list, "flange poses")
    B = _check_transforms(T_camera_board_list, "camera->board poses")
    if len(F) != len(B):
        raise CalibrationInputError(f"{len(F)} flange poses but {len(B)} camera->board poses: one of each per pose")
    if len(F) < MIN_VIEWS:
        raise CalibrationInputError(f"{len(F)} pose pairs, fewer than the {MIN_VIEWS} a hand-eye fit needs")
    check_motion(F)
    X0, Y0, _ = _best_closed_form(F, B, mount)
    names = [f"pair {k + 1}" for k in range(len(F))]
    rejected = []
    keep = np.arange(len(F))
    while True:
        X, Y, scale, L, cov, nfev = _refine_pairs(F[keep], B[keep], mount, X0, Y0, loss)
        e = _pair_errors(X, Y, F[keep], _scaled(B[keep], scale), mount)
        norm = np.linalg.norm(np.linalg.solve(L, e.T).T, axis=1)  # Mahalanobis distance of each pair
        median, spread = _robust_sigma(norm)
        z = (norm - median) / spread
        k = int(np.argmax(z))
        if z[k] <= OUTLIER_Z or norm[k] <= 2 * median or len(keep) - 1 < MIN_VIEWS:
            break
        rejected.append({"pose": names[keep[k]], "reason": f"off the others by {np.linalg.norm(e[k, 3:]) * 1e3:.2f} mm"
                         f" / {math.degrees(np.linalg.norm(e[k, :3])):.3f} deg ({z[k]:.1f} robust sigmas)"})
        keep = np.delete(keep, k)
        X0, Y0 = X, Y
    sX, rX, sY, rY, bX, bR = _covariance_blocks(cov, X, Y, arm_accuracy)
    per_view = [{"pose": names[i], "translation_mm": float(np.linalg.norm(e[j, 3:]) * 1e3),
                 "rotation_deg": float(math.degrees(np.linalg.norm(e[j, :3]))), "inlier": True}
                for j, i in enumerate(keep)]
    sd = np.sqrt(np.diag(L @ L.T))
    return HandEyeResult(mount, X, Y, None, scale, sX, rX, sY, rY, bX, bR, cov,
                         [f"X_{a}" for a in ("rx", "ry", "rz", "x", "y", "z")]
                         + [f"Y_{a}" for a in ("rx", "ry", "rz", "x", "y", "z")], None, per_view, rejected,
                         nfev, {"pair_rotation_deg": [float(math.degrees(v)) for v in sd[:3]],
                                "pair_translation_mm": [float(v * 1e3) for v in sd[3:]]})


def _scaled(B: np.ndarray, scale: float) -> np.ndarray:
    """Camera->board poses measured with the board's drawing, for a board printed `scale` times as large: PnP's
    distances come out 1/scale short."""
    out = B.copy()
    out[:, :3, 3] *= scale
    return out


def _refine_pairs(F, B, mount, X0, Y0, loss):
    """X, Y, the board's print scale, the Cholesky factor of the pairs' 6x6 error covariance, the covariance of
    (X, Y), evaluations. A board printed 0.05 % large puts every measured board 0.2 mm too close at 400 mm, often
    the largest error left in pose pairs from a good camera; but the scale is told from X's offset along the camera
    axis only by how much the distances vary. So it is fitted, and kept only when the pairs say it differs from the
    drawing (beyond 2 of its sigmas); else the refinement is done again with the drawing's scale."""
    fitted = _refine_pairs_at(F, B, mount, X0, Y0, loss, fit_scale=True)
    log_scale, sigma = fitted[-1]
    if abs(log_scale) > 2 * sigma:
        return fitted[:-1]
    return _refine_pairs_at(F, B, mount, X0, Y0, loss, fit_scale=False)[:-1]


def _refine_pairs_at(F, B, mount, X0, Y0, loss, fit_scale: bool):
    L = np.diag([math.radians(0.05)] * 3 + [5e-4] * 3)

    def errors(x):
        scale = math.exp(x[12]) if fit_scale else 1.0
        return _pair_errors(_perturbed(X0, x[:6]), _perturbed(Y0, x[6:12]), F, _scaled(B, scale), mount)

    def residuals(x):
        return np.concatenate([np.linalg.solve(L, errors(x).T).T.ravel(), x[12:] / SCALE_PRIOR])

    x, nfev = np.zeros(13 if fit_scale else 12), 0
    dof = max(len(F) - 2, 1)  # 12 parameters over 6 numbers a pair
    for _ in range(10):
        sol = least_squares(residuals, x, loss=loss, f_scale=3.0, x_scale="jac", method="trf")
        x, nfev = sol.x, nfev + sol.nfev
        e = errors(x)
        # one variance for the rotation and one for the translation: a full 6x6 from a dozen pairs is too noisy to
        # weigh by (it made the fit worse than the closed forms in the tests)
        # (robustly: from the median, so an outlier pair cannot widen them until it looks like the others)
        var = [(1.4826 * np.median(np.abs(e[:, k:k + 3]))) ** 2 * len(F) / dof for k in (0, 3)]
        var = np.r_[[max(var[0], 1e-12)] * 3, [max(var[1], 1e-14)] * 3]
        new = np.diag(np.sqrt(var))
        settled = np.allclose(new, L, rtol=0.05, atol=1e-9)
        L = new
        if settled:
            break
    sol = least_squares(residuals, x, loss=loss, f_scale=3.0, x_scale="jac", method="trf")
    J = approx_derivative(residuals, sol.x, method="2-point")
    Ninv = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
    log_scale = (float(sol.x[12]), float(math.sqrt(max(Ninv[12, 12], 0.0)))) if fit_scale else (0.0, math.inf)
    return (_perturbed(X0, sol.x[:6]), _perturbed(Y0, sol.x[6:12]), math.exp(log_scale[0]), L, Ninv[:12, :12],
            nfev + sol.nfev, log_scale)
