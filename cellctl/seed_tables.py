"""Figures published in the seed papers, shown beside ours in reports (never used by a fit)."""

# Seed 001, Table II: radial error e (µm) at calibration and non-calibration (verification) points.
# The seed's "RMS" column is below its mean, so it is most likely a standard deviation; we show
# both our RMS and our SD.
TABLE_II = {
    ("area1", "hybrid"): {"calibration": (15.2, 43.2, 10.5, 56), "verification": (14.2, 50.4, 11.9, 56)},
    ("area1", "virtual-grid"): {"calibration": (3.9, 8.8, 1.7, 56), "verification": (6.3, 19.0, 3.1, 56)},
    ("area2", "hybrid"): {"calibration": (67.5, 128.3, 36.0, 192), "verification": (62.7, 103.1, 31.5, 12)},
    ("area2", "virtual-grid-area2"): {"calibration": (6.8, 20.8, 4.8, 12), "verification": (19.5, 46.2, 12.3, 12)},
}

# Seed 001, Table VII: the end-effector offset estimated on their cell (the simulated cell's default truth).
TABLE_VII = {"dx_um": -68.7, "dy_um": 137.2, "r_um": 153.44}
