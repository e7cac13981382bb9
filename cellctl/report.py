"""result.json, the Markdown report, the terminal summary and the plots of a run.

Every routine's fit brings its own report tables and charts (`FitOutcome.tables`, `.charts`); this
renders them, whatever the routine, as does the web console from result.json.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calibration.routines.base import FitOutcome

from .store import RESULT, write_atomic, write_json

PREDICTED_LABELS = {
    "residual_sigma_um": "residual sigma per axis (µm)",
    "map_rms_um": "map uncertainty, 1 σ radial RMS over the verification pixels (µm)",
    "condition_number": "condition number of the fit",
    "offset_std_um": "1 σ uncertainty of the fitted offset (µm)",
}


def write_result(folder: Path, result: dict, outcome: FitOutcome) -> None:
    """Write result.json, report.md and the plots; `result` gains what result.json adds to it (the files,
    the tables and the charts), so a summary printed from it shows the same."""
    folder = Path(folder)
    plot_name = plot_residuals(folder / "residuals.png", outcome.plot, result.get("routine", ""))
    charts = {c["name"]: plot_chart(folder / f"{c['name']}.png", c) for c in outcome.charts}
    result.update(files={"samples": "samples.csv", "report": "report.md", "plot": plot_name, "charts": charts},
                  tables=outcome.tables, charts=outcome.charts)
    write_json(folder / RESULT, result)
    write_atomic(folder / "report.md", markdown(result))


def cell_text(value) -> str:
    """A table cell: a float as the routine rounded it (4 significant digits if it did not), None as '-'."""
    if value is None:
        return "-"
    if isinstance(value, float):
        text = repr(value)
        return text if len(text) <= 7 and not text.endswith(".0") else f"{value:.4g}"
    return str(value)


def markdown(result: dict) -> str:
    lines = [
        f"# {result['routine']} on {result.get('cell', '?')}",
        "",
        f"Run finished {result.get('finished', '?')}; seed {result.get('seed')}; "
        f"simulated cell time {result['cell_time_s']:.1f} s." if result.get("simulated") else
        f"Run finished {result.get('finished', '?')}; cell time {result['cell_time_s']:.1f} s.",
        "",
    ]
    lines += tables_markdown(result.get("tables", []))
    lines += [f"![{name}]({file})\n" for name, file in result.get("files", {}).get("charts", {}).items() if file]
    pred = result["stats"].get("predicted")
    if pred:
        lines += ["## Predicted accuracy (from the fit alone)", ""]
        lines += [f"- {PREDICTED_LABELS.get(k, k)}: {_short(v)}" for k, v in pred.items()]
        lines.append("")
    scalars = {k: v for k, v in result.get("model", {}).items() if isinstance(v, (int, float, str))}
    if scalars:
        lines += ["## Model", ""] + [f"- {k}: {_short(v)}" for k, v in scalars.items()] + [""]
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


def tables_markdown(tables: list[dict]) -> list[str]:
    """A routine's report tables: title, columns, rows, optional note."""
    lines = []
    for t in tables:
        lines += [f"## {t['title']}", "", "| " + " | ".join(map(str, t["columns"])) + " |",
                  "|" + "---|" * len(t["columns"])]
        lines += ["| " + " | ".join(map(cell_text, row)) + " |" for row in t["rows"]]
        lines += ["", t["note"], ""] if t.get("note") else [""]
    return lines


def print_summary(result: dict, folder: Path) -> None:
    """The run on the terminal: the routine's tables, its charts' files, the model, the truth (simulation)."""
    from rich.console import Console
    from rich.table import Table

    console = Console()
    for spec in result.get("tables", []):
        table = Table(title=f"{result['routine']}: {spec['title']}", caption=spec.get("note"))
        for i, col in enumerate(spec["columns"]):  # numbers to the right, words to the left
            numeric = any(isinstance(row[i], (int, float)) for row in spec["rows"])
            table.add_column(str(col), justify="right" if numeric else "left")
        for row in spec["rows"]:
            table.add_row(*map(cell_text, row))
        console.print(table)
    charts = [file for file in result.get("files", {}).get("charts", {}).values() if file]
    if charts:
        console.print("charts: " + ", ".join(str(Path(folder) / f) for f in charts))
    scalars = {k: v for k, v in result.get("model", {}).items() if isinstance(v, float)}
    if scalars:
        console.print("model: " + ", ".join(f"{k} {v:.3f}" for k, v in scalars.items()))
    truth = {k: v for k, v in (result.get("truth") or {}).items() if isinstance(v, float)}
    if truth:
        console.print("truth (simulation only; the fit never saw it): "
                      + ", ".join(f"{k} {v:.4g}" for k, v in truth.items()))
    console.print(f"cell time {result['cell_time_s']:.1f} s; report {Path(folder) / 'report.md'}; "
                  f"result {Path(folder) / 'result.json'}")


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
    ax.margins(0.12)  # room for the arrows at the edge of the field (quiver does not count them)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{title}: {plot.get('title', '')}; arrow of 1 mm = {1e3 / gain:.1f} µm")
    ax.legend(loc="best")
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
