"""Error statistics shared by the fits, the routines' reports and the OpenCV baseline."""

from __future__ import annotations

import numpy as np


def error_stats(errors_m: np.ndarray) -> dict:
    """Seed 001 Table II columns for radial errors given in metres: n, mean, max, RMS (and SD) in µm."""
    e = np.asarray(errors_m, dtype=float) * 1e6
    if e.size == 0:
        return {"n": 0, "mean_um": None, "max_um": None, "rms_um": None, "sd_um": None}
    return {
        "n": int(e.size),
        "mean_um": float(np.mean(e)),
        "max_um": float(np.max(e)),
        "rms_um": float(np.sqrt(np.mean(e**2))),
        "sd_um": float(np.std(e)),
    }
