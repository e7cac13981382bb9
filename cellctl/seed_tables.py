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

# Seed 001, Table IV: RMS error (µm) of the cross-reference test, pose p_k (rows) x estimate c (columns).
TABLE_IV = {
    "p2": {"c*": 26.2, "c2": 16.6, "c3": 24.3, "c4": 30.4, "c5": 21.0, "c6": 25.3},
    "p3": {"c*": 22.5, "c2": 41.1, "c3": 20.4, "c4": 27.6, "c5": 23.2, "c6": 28.3},
    "p4": {"c*": 28.1, "c2": 79.2, "c3": 36.1, "c4": 23.4, "c5": 49.0, "c6": 35.6},
    "p5": {"c*": 18.8, "c2": 20.7, "c3": 17.1, "c4": 21.7, "c5": 16.2, "c6": 20.3},
    "p6": {"c*": 20.1, "c2": 33.6, "c3": 22.9, "c4": 22.2, "c5": 25.5, "c6": 17.7},
}

# Seed 001, Table V: maximum error (µm) of the same test. (Table VI, the mean, has no numbers in the seed text.)
TABLE_V = {
    "p2": {"c*": 46.1, "c2": 35.0, "c3": 42.2, "c4": 51.2, "c5": 36.8, "c6": 46.5},
    "p3": {"c*": 45.4, "c2": 77.3, "c3": 42.9, "c4": 51.6, "c5": 53.8, "c6": 55.3},
    "p4": {"c*": 61.7, "c2": 121.9, "c3": 72.2, "c4": 46.3, "c5": 88.3, "c6": 69.0},
    "p5": {"c*": 45.6, "c2": 42.0, "c3": 41.0, "c4": 50.2, "c5": 42.2, "c6": 47.9},
    "p6": {"c*": 51.9, "c2": 65.5, "c3": 58.4, "c4": 49.8, "c5": 62.3, "c6": 44.1},
}
