"""result.json, the Markdown report and the residual-arrow plot of a run."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calibration.routines.base import FitOutcome

from .seed_tables import TABLE_II, TABLE_VII
from .store import RESULT, write_atomic, write_json

STAT_COLUMNS = ("mean_um", "max_um", "rms_um", "sd_um", "n")
TABLE_HEAD = ("points", "source", "mean", "max", "RMS", "SD", "n")
PREDICTED_LABELS = {
    "residual_sigma_um": "residual sigma per axis (µm)",
    "map_rms_um": "map uncertainty, 1 σ radial RMS over the verification pixels (µm)",
    "condition_number": "condition number of the fit",
    "offset_std_um": "1 σ uncertainty of the fitted offset (µm)",
}


def write_result(folder: Path, result: dict, outcome: FitOutcome) -> None:
    folder = Path(folder)
    plot_name = plot_residuals(folder / "residuals.png", outcome.plot, result.get("routine", ""))
    tables = outcome.extra.get("tables", [])
    charts = {c["name"]: plot_chart(folder / f"{c['name']}.png", c) for c in outcome.extra.get("charts", [])}
    result = dict(result, files={"samples": "samples.csv", "report": "report.md", "plot": plot_name,
                                 "charts": charts})
    if tables:
        result["tables"] = tables
    write_json(folder / RESULT, result)
    write_atomic(folder / "report.md", markdown(result))


def comparison_rows(result: dict) -> list[list]:
    """Rows (points, source, mean, max, RMS, SD, n): ours beside the seed's Table II row for the same area."""
    area = result.get("params", {}).get("area", "area1")
    seed = TABLE_II.get((area, result["routine"]))
    rows = []
    parts = (("calibration", "calibration"), ("registration", "registration points"),
             ("uncompensated", "unseen, uncompensated"),
             ("verification", "verification (unseen)"))
    for part, label in parts:
        if part not in result["stats"]:
            continue
        stats = result["stats"][part]
        if "mean_um" not in stats:
            continue
        rows.append([label, "cellctl", *(_fmt(stats.get(k), k) for k in STAT_COLUMNS)])
        baseline = result["stats"].get("baseline_opencv", {}).get(part)
        if baseline:
            rows.append(["", "OpenCV baseline, same samples", *(_fmt(baseline.get(k), k) for k in STAT_COLUMNS)])
        if seed and part in seed:
            mean, mx, rms, n = seed[part]
            rows.append(["", f"seed 001 Table II, {area}", mean, mx, rms, "-", n])
    return rows


def _fmt(value, key):
    if value is None:
        return "-"
    return value if key == "n" else round(value, 2)


def markdown(result: dict) -> str:
    lines = [
        f"# {result['routine']} on {result.get('cell', '?')}",
        "",
        f"Run finished {result.get('finished', '?')}; seed {result.get('seed')}; "
        f"simulated cell time {result['cell_time_s']:.1f} s." if result.get("simulated") else
        f"Run finished {result.get('finished', '?')}; cell time {result['cell_time_s']:.1f} s.",
        "",
    ]
    rows = comparison_rows(result)
    if rows:  # routines measuring a radial error in µm (seed 001)
        lines += ["## Radial error e (µm), seed 001 section 5.3", "", "| " + " | ".join(TABLE_HEAD) + " |",
                  "|" + "---|" * len(TABLE_HEAD), *("| " + " | ".join(map(str, row)) + " |" for row in rows), ""]
        if any(row[1].startswith("seed") for row in rows):
            lines += ["The seed's RMS column is below its mean: it is most likely a standard deviation (compare SD).", ""]
    lines += cross_reference_tables(result["stats"].get("cross_reference"))
    lines += routine_tables(result.get("tables", []))
    lines += [f"![{name}]({file})\n" for name, file in result.get("files", {}).get("charts", {}).items() if file]
    pred = result["stats"].get("predicted")
    if pred:
        lines += ["## Predicted accuracy (from the fit alone)", ""]
        lines += [f"- {PREDICTED_LABELS.get(k, k)}: {_short(v)}" for k, v in pred.items()]
        lines.append("")
    scalars = {k: v for k, v in result.get("model", {}).items() if isinstance(v, (int, float, str))}
    if scalars:
        lines += ["## Model", ""] + [f"- {k}: {_short(v)}" for k, v in scalars.items()] + [""]
    if result["routine"] == "rotation-sweep":
        lines += ["Seed 001 Table VII (their cell): " + ", ".join(f"{k} {v}" for k, v in TABLE_VII.items()), ""]
    lines += ["## Samples left out", ""]
    if result.get("rejected"):
        lines += [f"- step {r.get('step')}: {r.get('reason')}"
                  + (f" (residual {r['residual_um']:.1f} µm)" if r.get("residual_um") is not None else "")
                  for r in result["rejected"]]
    else:
        lines.append("None: every sample was measured and kept.")
    lines += ["", "## Residuals", "", "![residual arrows](residuals.png)", ""]
    truth = result.get("truth")
    if truth:
        lines += ["## Truth (simulation only; the fit never saw it)", ""]
        lines += [f"- {k}: {_short(v)}" for k, v in truth.items()]
        lines.append("")
    lines += ["## Parameters", "", "```", *(f"{k}: {v}" for k, v in result.get("params", {}).items()), "```", ""]
    return "\n".join(lines)


def cross_reference_tables(table: dict | None) -> list[str]:
    """Seed 001 Tables IV-VI: error at each pose p_k of the axis location estimated from pose l alone (c_l)
    or from all poses (c*)."""
    if not table:
        return []
    lines = ["Error of eq. (5) at pose p_k against the sphere's position seen at pose 1 (E_jk of the seed); "
             "the verification figures above compare with where the spheres were placed instead.", ""]
    for kind, title in (("rms_um", "IV, RMS"), ("max_um", "V, maximum"), ("mean_um", "VI, mean")):
        rows = table[kind]
        estimates = list(next(iter(rows.values())))
        lines += [f"## Cross-reference test (seed Table {title} error, µm)", "",
                  "| pose | " + " | ".join(estimates) + " | min | max |", "|" + "---|" * (len(estimates) + 3)]
        for pose, values in rows.items():
            v = [values[e] for e in estimates]
            lines.append(f"| {pose} | " + " | ".join(f"{x:.1f}" for x in v) + f" | {min(v):.1f} | {max(v):.1f} |")
        lines.append("")
    return lines


def routine_tables(tables: list[dict]) -> list[str]:
    """Tables a routine adds to its report (e.g. a seed's experiments): title, columns, rows, optional note."""
    lines = []
    for t in tables:
        lines += [f"## {t['title']}", "", "| " + " | ".join(map(str, t["columns"])) + " |",
                  "|" + "---|" * len(t["columns"])]
        lines += ["| " + " | ".join(_short(v) if isinstance(v, float) else str(v) for v in row) + " |"
                  for row in t["rows"]]
        lines += ["", t["note"], ""] if t.get("note") else [""]
    return lines


def plot_chart(path: Path, chart: dict) -> str | None:
    """A line chart a routine asks for: {name, title, x_label, y_label, series: {label: [[x, y], ...]}, log_y}."""
    if not chart.get("series"):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, points in chart["series"].items():
        xy = np.asarray(points, dtype=float).reshape(-1, 2)
        ax.plot(xy[:, 0], xy[:, 1], marker="o", markersize=3, label=str(label))
    ax.set_title(chart.get("title", chart["name"]))
    ax.set_xlabel(chart.get("x_label", ""))
    ax.set_ylabel(chart.get("y_label", ""))
    if chart.get("log_y"):
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def _short(value):
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={_short(v)}" for k, v in value.items())
    if isinstance(value, list):
        return "[" + ", ".join(_short(v) for v in value) + "]"
    return str(value)


def plot_residuals(path: Path, plot: dict, title: str) -> str | None:
    """Residual arrows over the image, amplified (like seed 001 Fig. 8); or error arrows in robot coordinates."""
    if plot and "series" in plot:
        return plot_series(path, plot, title)
    if not plot or "cal_uv" not in plot:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    width, height = plot.get("image_size") or (None, None)
    errs = [np.linalg.norm(plot[k], axis=1) for k in ("cal_err", "ver_err") if k in plot and len(plot[k])]
    biggest = max((float(e.max()) for e in errs), default=0.0)
    span = max(width or 1000, height or 1000)
    gain = 0.06 * span / biggest if biggest > 0 else 1.0  # the longest arrow is 6 % of the image
    fig, ax = plt.subplots(figsize=(8, 6.5), dpi=110)
    for key_uv, key_err, colour, label in (("cal_uv", "cal_err", "tab:blue", "calibration"),
                                           ("ver_uv", "ver_err", "tab:red", "verification")):
        if key_uv not in plot or not len(plot[key_uv]):
            continue
        uv, err = np.asarray(plot[key_uv]), np.asarray(plot[key_err])
        ax.quiver(uv[:, 0], uv[:, 1], err[:, 0] * gain, err[:, 1] * gain, color=colour, angles="xy",
                  scale_units="xy", scale=1, width=0.003, label=f"{label} ({len(uv)})")
        ax.plot(uv[:, 0], uv[:, 1], ".", color=colour, markersize=3)
    if width and height:
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
    else:
        ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    um_per_px_arrow = 1e6 / gain if gain else math.nan
    ax.set_title(f"{title}: residual e (fitted - robot), arrow of 100 px = {100 * um_per_px_arrow:.1f} µm")
    ax.legend(loc="upper right")
    return _save(fig, path)


def plot_series(path: Path, plot: dict, title: str) -> str | None:
    """Error arrows at robot positions (mm), one colour per series, drawn at a common scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = [s for s in plot["series"] if len(s["err"])]
    biggest = max(float(np.linalg.norm(s["err"], axis=1).max()) for s in series)
    span = max(float(np.ptp(np.vstack([s["xy_mm"] for s in series]), axis=0).max()), 1.0)
    gain = 0.08 * span / (biggest * 1e3) if biggest > 0 else 1.0  # the longest arrow is 8 % of the field
    fig, ax = plt.subplots(figsize=(8, 6.5), dpi=110)
    for s in series:
        xy, err = np.asarray(s["xy_mm"]), np.asarray(s["err"]) * 1e3
        ax.quiver(xy[:, 0], xy[:, 1], err[:, 0] * gain, err[:, 1] * gain, color=s["colour"], angles="xy",
                  scale_units="xy", scale=1, width=0.003, label=s["label"])
        ax.plot(xy[:, 0], xy[:, 1], ".", color=s["colour"], markersize=3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{title}: {plot.get('title', '')}; arrow of 1 mm = {1e3 / gain:.1f} µm")
    ax.legend(loc="upper right")
    return _save(fig, path)


def _save(fig, path: Path) -> str:
    """Write the figure through a temporary file, so a crash leaves no half-written PNG."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)
    return path.name
