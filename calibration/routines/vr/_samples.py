"""The VR routines' sample rows (seed 000): every estimate, pose and error as plain numeric columns.

A rigid transform T (4x4) is 12 columns `PREFIX_x_m, PREFIX_y_m, PREFIX_z_m` (its translation) and
`PREFIX_r11 .. PREFIX_r33` (its rotation matrix, row by row): a CSV cell holds a float exactly, so
a resumed run reads back the very estimate an uninterrupted one keeps in memory.

  step, kind, condition, run, stop, distance_in, angle_deg, view_in, method   what the row measured
  side_frame, top_frame      the frames the estimate comes from
  arm_*                      the arm's reported tool pose (robot frame), where the routine records it
  est_side_*, est_top_*      each camera of the estimate: its world-to-camera transform V (12 columns),
                             f_px, cu_px, cv_px, and the focal-length prior f_prior_px, f_prior_rel
  est_oru_*, est_rec_*       the ORU's (fixed: the arm's reported pose) and the receptacle's pose
  err_*                      alignment error against the reference (receptacle frame): x_m, y_m, z_m of
                             the ORU's origin, rx_rad, ry_rad, rz_rad of the rotation; pos_err_in,
                             ori_err_deg: their vector sums
  sigma_*                    predicted 1-sigma of the same components; sigma_pos_in, sigma_ori_deg
  rms_px .. converged        the solver's figures
  cov_side_*, cov_top_*, cov_rec_*   the simultaneous update's covariance of each block's position
                             increments (tx, ty, tz), 3x3 row by row in m^2 (cov_rec_xy_m2, ...): Fig. 11
  status, message            ok | failed, and why
"""

from __future__ import annotations

import numpy as np

from calibration.models.model_matching import CameraState, MatchResult
from calibration.routines.vr._common import CAM, INCH, Estimate, alignment_error, alignment_sigma, error_summary

_ROTATION = tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))
_COMPONENTS = ("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad")
_CAMERA = ("f_px", "cu_px", "cv_px", "f_prior_px", "f_prior_rel")
_AXES = "xyz"
_BLOCKS = {"side": "cam0", "top": "cam1", "rec": "obj1"}  # column prefix -> the solver's block


def pose_columns(prefix: str) -> tuple[str, ...]:
    return (f"{prefix}_x_m", f"{prefix}_y_m", f"{prefix}_z_m", *(f"{prefix}_{r}" for r in _ROTATION))


def pose_cells(prefix: str, T: np.ndarray) -> dict:
    T = np.asarray(T, float)
    return dict(zip(pose_columns(prefix), (float(v) for v in (*T[:3, 3], *T[:3, :3].ravel()))))


def pose_from(row: dict, prefix: str) -> np.ndarray | None:
    values = [row.get(c) for c in pose_columns(prefix)]
    if any(v is None for v in values):
        return None
    T = np.eye(4)
    T[:3, 3] = values[:3]
    T[:3, :3] = np.reshape(values[3:], (3, 3))
    return T


def _vector_columns(prefix: str) -> tuple[str, ...]:
    return tuple(f"{prefix}_{c}" for c in _COMPONENTS)


def _vector_from(row: dict, prefix: str) -> np.ndarray | None:
    values = [row.get(c) for c in _vector_columns(prefix)]
    return None if any(v is None for v in values) else np.asarray(values, float)


ARM_COLUMNS = pose_columns("arm")
ESTIMATE_COLUMNS = (*(c for name in CAM for c in (*pose_columns(f"est_{name}"), *(f"est_{name}_{p}" for p in _CAMERA))),
                    *pose_columns("est_oru"), *pose_columns("est_rec"))
ERROR_COLUMNS = _vector_columns("err")
SIGMA_COLUMNS = _vector_columns("sigma")
COVARIANCE_COLUMNS = tuple(f"cov_{b}_{p}{q}_m2" for b in _BLOCKS for p in _AXES for q in _AXES)
SAMPLE_COLUMNS = ("step", "kind", "condition", "run", "stop", "distance_in", "angle_deg", "view_in", "method",
                  "side_frame", "top_frame", *ARM_COLUMNS, *ESTIMATE_COLUMNS, *ERROR_COLUMNS, *SIGMA_COLUMNS,
                  "pos_err_in", "ori_err_deg", "sigma_pos_in", "sigma_ori_deg", "rms_px", "max_px", "n_lines",
                  "n_points", "iterations", "converged", *COVARIANCE_COLUMNS, "status", "message")
# what a fit needs of an estimate (the focal-length prior is optional)
ESTIMATE_FIT_COLUMNS = tuple(c for c in ESTIMATE_COLUMNS if "_f_prior" not in c)


def frame_ids(frames) -> dict:
    """The frames (side, top) a row's estimate comes from."""
    return {"side_frame": frames[0].frame_id, "top_frame": frames[1].frame_id}


# ------------------------------------------------------------------ the estimate

def estimate_cells(est: Estimate) -> dict:
    cells = {}
    for name, cam in zip(CAM, est.cameras):
        cells.update(pose_cells(f"est_{name}", cam.V))
        f_prior = None if cam.f_prior is None else float(cam.f_prior)
        cells.update(zip((f"est_{name}_{p}" for p in _CAMERA), (float(cam.f), float(cam.cu), float(cam.cv), f_prior,
                                                                 float(cam.f_prior_rel))))
    return dict(cells, **pose_cells("est_oru", est.oru), **pose_cells("est_rec", est.receptacle))


def has_estimate(row: dict) -> bool:
    return row.get("est_rec_x_m") is not None


def estimate_from(row: dict) -> Estimate:
    cams = []
    for name in CAM:
        f, cu, cv, f_prior, f_prior_rel = (row.get(f"est_{name}_{p}") for p in _CAMERA)
        cams.append(CameraState(pose_from(row, f"est_{name}"), float(f), float(cu), float(cv), f_prior=f_prior,
                                f_prior_rel=0.1 if f_prior_rel is None else f_prior_rel))
    return Estimate(cams, pose_from(row, "est_oru"), pose_from(row, "est_rec"))


# ------------------------------------------------------------------ errors against a reference

def error_vector(row: dict) -> np.ndarray | None:
    return _vector_from(row, "err")


def sigma_vector(row: dict) -> np.ndarray | None:
    return _vector_from(row, "sigma")


def error_cells(e: np.ndarray) -> dict:
    """The error columns of an alignment error (m, rad), with its vector sums in inches and degrees."""
    cells = dict(zip(ERROR_COLUMNS, (float(v) for v in e)))
    cells["pos_err_in"], cells["ori_err_deg"] = error_summary(np.asarray(e))
    return cells


def result_row(method: str, est: Estimate, result: MatchResult, reference: np.ndarray | None) -> dict:
    sigma = alignment_sigma(result, est)
    row = {"method": method, **estimate_cells(est), "rms_px": result.rms_px, "max_px": result.max_px,
           "n_lines": result.n_lines, "n_points": result.n_points, "iterations": result.iterations,
           "converged": int(result.converged), **dict(zip(SIGMA_COLUMNS, (float(v) for v in sigma))),
           "sigma_pos_in": float(np.linalg.norm(sigma[:3]) / INCH), "sigma_ori_deg": float(np.degrees(np.linalg.norm(sigma[3:])))}
    if reference is not None:
        row.update(error_cells(alignment_error(est.alignment(), reference)))
    return row


# ------------------------------------------------------------------ Fig. 11's covariance

def covariance_cells(result: MatchResult) -> dict:
    """The position blocks of the update's covariance (each free camera's and the receptacle's tx, ty, tz)."""
    cells = {}
    for prefix, block in _BLOCKS.items():
        names = [f"{block}.t{a}" for a in _AXES]
        if all(n in result.names for n in names):
            idx = [result.names.index(n) for n in names]
            values = result.covariance[np.ix_(idx, idx)].ravel()
            cells.update(zip((f"cov_{prefix}_{p}{q}_m2" for p in _AXES for q in _AXES), (float(v) for v in values)))
    return cells


def position_covariances(row: dict) -> dict[str, np.ndarray]:
    """{side, top, rec: 3x3 covariance of tx, ty, tz} of the blocks a row carries."""
    out = {}
    for prefix in _BLOCKS:
        values = [row.get(f"cov_{prefix}_{p}{q}_m2") for p in _AXES for q in _AXES]
        if all(v is not None for v in values):
            out[prefix] = np.reshape(np.asarray(values, float), (3, 3))
    return out
