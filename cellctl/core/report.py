"""result.json, the Markdown report, the terminal summary and the plots of a run.

Every routine's fit brings its own report tables and charts (`FitOutcome.tables`, `.charts`); this
renders them, whatever the routine, as does the web console from result.json.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calibration.routines.base import FitOutcome

from cellctl.stores.run_folder import RESULT, write_atomic, write_json

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
    overlays = sorted(f"images/{p.name}" for p in (folder / "images").glob("*_overlay-*.png"))
    result.update(files={"samples": "samples.csv", "report": "report.md", "plot": plot_name, "charts": charts,
                         "overlays": overlays},
                  tables=outcome.tables, charts=outcome.charts)
    write_json(folder / RESULT, result)
    write_atomic(folder / "report.md", markdown(result, folder))


def cell_text(value) -> str:
    """A table cell: a float as the routine rounded it (4 significant digits if it did not), None as '-'."""
    if value is None:
        return "-"
    if isinstance(value, float):
        text = repr(value)
        return text if len(text) <= 7 and not text.endswith(".0") else f"{value:.4g}"
    return str(value)


def figures(result: dict, folder: Path) -> list[tuple[str, str]]:
    """(caption, file) of every figure the report shows: the charts, the residual plot and the overlays the run
    kept, each only if it exists in the run folder (a figure that was not drawn is not embedded)."""
    files = result.get("files", {})
    titles = {c["name"]: c.get("title", c["name"]) for c in result.get("charts", [])}
    found = [(titles.get(name, name), file) for name, file in files.get("charts", {}).items() if file]
    if files.get("plot"):
        found.append(("residuals", files["plot"]))
    found += [(Path(file).stem.partition("_")[2], file) for file in files.get("overlays", [])]
    return [(caption, file) for caption, file in found if (Path(folder) / file).is_file()]


def markdown(result: dict, folder: Path) -> str:
    """The report: the routine's tables (its result first), the figures in the run folder, the predicted accuracy,
    the model, the samples left out, the truth (simulation, as tables) and the parameters."""
    lines = [
        f"# {result['routine']} on {result.get('cell', '?')}",
        "",
        f"Run finished {result.get('finished', '?')}; simulation seed {result.get('seed')}; "
        f"simulated cell time {result['cell_time_s']:.1f} s." if result.get("simulated") else
        f"Run finished {result.get('finished', '?')}; cell time {result['cell_time_s']:.1f} s.",
        "",
    ]
    if result.get("arm_calibration") is not None:
        lines += [f"Every move went through the arm calibration {result['arm_calibration']} (target `arm`).", ""]
    lines += tables_markdown(result.get("tables", []))
    shown = figures(result, folder)
    if shown:
        lines += ["## Figures", ""] + [f"![{caption}]({file})\n" for caption, file in shown]
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
    lines.append("")
    truth = result.get("truth")
    if truth:
        lines += [f"## {TRUTH_TITLE}", ""] + tables_markdown(truth_tables(truth), level=3)
    lines += ["## Parameters", "", "```", *(f"{k}: {v}" for k, v in result.get("params", {}).items()), "```", ""]
    return "\n".join(lines)


def tables_markdown(tables: list[dict], level: int = 2) -> list[str]:
    """A routine's report tables: title, columns, rows, optional note."""
    lines = []
    for t in tables:
        lines += [f"{'#' * level} {t['title']}", "", "| " + " | ".join(map(str, t["columns"])) + " |",
                  "|" + "---|" * len(t["columns"])]
        lines += ["| " + " | ".join(map(cell_text, row)) + " |" for row in t["rows"]]
        lines += ["", t["note"], ""] if t.get("note") else [""]
    return lines


TRUTH_TITLE = "Truth (simulation only; the fit never saw it)"


def truth_tables(truth: dict, prefix: str = "", brief: bool = False) -> list[dict]:
    """The truth section as tables, whatever a routine's truth function returns: its single values in one table,
    a table per record ({name: value}, one quantity a row), per list of records, per {name: record} and per
    {columns, rows}; deeper dictionaries give tables of their own titled by their path. `brief` (the terminal):
    the single values and the records only."""
    single, tables, deeper = [], [], []
    for key, value in truth.items():
        title = f"{prefix}{key}"
        if _flat(value):
            single.append([key, _cell(value)])
        elif _record(value):
            tables.append({"title": title, "columns": ["quantity", "value"],
                           "rows": [[k, _cell(v)] for k, v in value.items()]})
        elif brief:
            continue
        elif isinstance(value, dict) and {"columns", "rows"} <= set(value):
            tables.append({"title": title, "columns": list(value["columns"]), "rows": value["rows"]})
        elif isinstance(value, list) and value and all(_record(v) for v in value):
            tables.append(_records_table(title, "", value))
        elif isinstance(value, dict) and value and all(_record(v) or v is None for v in value.values()):
            tables.append(_records_table(title, key, [dict({key: name}, **(v or {})) for name, v in value.items()]))
        elif isinstance(value, dict):
            deeper += truth_tables(value, f"{title} / ")
        else:
            single.append([key, _short(value)])
    if single:
        tables.insert(0, {"title": prefix.removesuffix(" / ") or "quantities", "columns": ["quantity", "value"],
                          "rows": single})
    return tables + deeper


def _flat(value) -> bool:
    return value is None or isinstance(value, (bool, int, float, str)) or (
        isinstance(value, list) and all(isinstance(v, (int, float)) for v in value))


def _record(value) -> bool:
    return isinstance(value, dict) and bool(value) and all(_flat(v) for v in value.values())


def _cell(value):
    return _short(value) if isinstance(value, list) else value


def _records_table(title: str, first: str, records: list[dict]) -> dict:
    columns = list(dict.fromkeys(k for r in records for k in r))
    if first:
        columns = [first] + [c for c in columns if c != first]
    return {"title": title, "columns": columns, "rows": [[_cell(r.get(c)) for c in columns] for r in records]}


SUMMARY_WIDTH = 100  # the terminal's tables fit this many columns; piped output is laid out at this width


def print_summary(result: dict, folder: Path, console=None) -> None:
    """The run on the terminal: the routine's tables, its charts' files, the model, the truth (simulation)."""
    from rich.console import Console

    if console is None:
        console = Console()
        if not console.is_terminal or console.width > SUMMARY_WIDTH:
            console = Console(width=SUMMARY_WIDTH)
    for spec in result.get("tables", []):
        _print_table(console, f"{result['routine']}: {spec['title']}", spec)
    charts = [file for file in result.get("files", {}).get("charts", {}).values() if file]
    if charts:
        console.print("charts: " + ", ".join(str(Path(folder) / f) for f in charts))
    scalars = {k: v for k, v in result.get("model", {}).items() if isinstance(v, float)}
    if scalars:
        console.print("model: " + ", ".join(f"{k} {v:.3f}" for k, v in scalars.items()))
    for spec in truth_tables(result.get("truth") or {}, brief=True):
        _print_table(console, f"{TRUTH_TITLE}: {spec['title']}", spec)
    console.print(f"cell time {result['cell_time_s']:.1f} s")
    for name in ("report.md", "result.json"):  # a path on a line of its own, never folded (it is to be copied)
        console.print(f"{name.split('.')[0]}: {Path(folder) / name}", soft_wrap=True)


def print_tables(routine: str, tables: list[dict], console=None) -> None:
    """Report tables on the terminal, as a run's summary shows them (`cellctl plan`)."""
    from rich.console import Console

    if console is None:
        console = Console()
        if not console.is_terminal or console.width > SUMMARY_WIDTH:
            console = Console(width=SUMMARY_WIDTH)
    for spec in tables:
        _print_table(console, f"{routine}: {spec['title']}", spec)


def _print_table(console, title: str, spec: dict) -> None:
    """A report table on the terminal: its title and note as lines of their own (not squeezed to the table's
    width), numbers to the right, words to the left. Where the table is wider than the terminal, the headers
    wrap first (a name's underscores become spaces, where it may wrap), then cells fold: never cut."""
    from rich import box
    from rich.table import Table
    from rich.text import Text

    headers = [str(c).replace("_", " ") for c in spec["columns"]]
    cells = [[cell_text(v) for v in row] for row in spec["rows"]]
    widths = _column_widths(headers, cells, console.width - 2 * (len(headers) - 1))  # 2: the gap between columns
    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, collapse_padding=True)
    for i, (header, width) in enumerate(zip(headers, widths)):
        numeric = any(isinstance(row[i], (int, float)) for row in spec["rows"] if i < len(row))
        table.add_column(header, justify="right" if numeric else "left", overflow="fold", width=width)
    for row in cells:
        table.add_row(*row)
    console.print(Text(title, style="bold"))
    console.print(table)
    if spec.get("note"):
        console.print(Text(spec["note"]))
    console.print()


def _column_widths(headers: list[str], cells: list[list[str]], room: int) -> list[int | None]:
    """Column widths that fit `room` (None each: the table fits as it is). Every column is at least as wide as
    its longest word; what room is left goes first to the columns that need least to show their cells whole,
    so numbers stay whole and a long text column wraps between words."""
    from rich.cells import cell_len

    def longest_word(text: str) -> int:
        return max((cell_len(w) for w in text.split()), default=0)

    columns = [[row[i] for row in cells if i < len(row)] for i in range(len(headers))]
    whole = [max([cell_len(h)] + [cell_len(c) for c in col]) for h, col in zip(headers, columns)]
    if sum(whole) <= room:
        return [None] * len(headers)
    widths = [max([longest_word(h)] + [longest_word(c) for c in col]) for h, col in zip(headers, columns)]
    cells_whole = [max([longest_word(h)] + [cell_len(c) for c in col]) for h, col in zip(headers, columns)]
    spare = room - sum(widths)
    for i in sorted(range(len(widths)), key=lambda i: cells_whole[i] - widths[i]):
        add = max(0, min(cells_whole[i] - widths[i], spare))
        widths[i] += add
        spare -= add
    return widths


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
