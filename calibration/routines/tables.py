"""Report tables several routines share: seed 001's radial error e (section 5.3, Table II's form)."""

from __future__ import annotations

from dataclasses import replace

from calibration.routines.base import FitOutcome, Table

RADIAL_ERROR_TITLE = "Radial error e (µm), seed 001 section 5.3"
RADIAL_ERROR_COLUMNS = ["points", "source", "mean", "max", "RMS", "SD", "n"]
STAT_KEYS = ("mean_um", "max_um", "rms_um", "sd_um", "n")
POINT_SETS = (("calibration", "calibration"), ("registration", "registration points"),
              ("uncompensated", "unseen, uncompensated"), ("verification", "verification (unseen)"))


def radial_error_tables(stats: dict, seed: dict | None = None, seed_label: str = "") -> list[Table]:
    """Per set of points: ours, the OpenCV baseline on the same samples (if the fit ran one), and the seed's
    row. `seed`: {set: (mean, max, "RMS", n)} as the seed prints it. No error statistics: no table."""
    rows = []
    for part, label in POINT_SETS:
        ours = stats.get(part, {})
        if "mean_um" not in ours:
            continue
        rows.append([label, "cellctl", *_figures(ours)])
        baseline = stats.get("baseline_opencv", {}).get(part)
        if baseline:
            rows.append(["", "OpenCV baseline, same samples", *_figures(baseline)])
        if seed and part in seed:
            mean, largest, rms, n = seed[part]
            rows.append(["", seed_label, mean, largest, rms, None, n])
    if not rows:
        return []
    table = Table(title=RADIAL_ERROR_TITLE, columns=RADIAL_ERROR_COLUMNS, rows=rows)
    if any(row[1] == seed_label for row in rows):
        table["note"] = "The seed's RMS column is below its mean: it is most likely a standard deviation (compare SD)."
    return [table]


def _figures(stats: dict) -> list:
    return [None if stats.get(k) is None else stats[k] if k == "n" else round(stats[k], 2) for k in STAT_KEYS]


def with_seed_table_ii(outcome: FitOutcome, seed_table_ii: dict, area: str) -> FitOutcome:
    """The outcome with its radial error table, beside the seed's Table II row for the area (if it has one)."""
    return replace(outcome, tables=radial_error_tables(outcome.stats, seed_table_ii.get(area),
                                                       f"seed 001 Table II, {area}"))
