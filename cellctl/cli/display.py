"""What the CLI shows: one progress bar (in-process runs and daemon jobs alike) and the listings."""

from __future__ import annotations

import json
import textwrap

from calibration.routines import sequences

# Listings are laid out for 100 columns, in a terminal or piped, and wrapped, never cut: a long entry goes on
# on the next line, indented (`--json` gives the service's answer whole, for programs)
WIDTH = 100


class ProgressBar:
    """step i / N, simulated cell time, and for a daemon job the ETA in cell time and the residual (rich, stderr):
    `ROUTINE (routine 3/4) ━━━━━━━╺━━━ 152/600 steps  cell 1234 s  ETA 4321 s  residual 12.34 µm`, within
    WIDTH columns. A context manager; `quiet` shows nothing; `console`: where to draw (default: stderr)."""

    def __init__(self, name: str, quiet: bool = False, console=None):
        self.name, self.quiet, self.console = name, quiet, console

    def __enter__(self) -> "ProgressBar":
        if self.quiet:
            return self
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

        console = self.console or Console(stderr=True)
        if not console.is_terminal:  # a pipe or a file: rich would lay out for 80 columns and cut
            console = Console(stderr=True, width=WIDTH)
        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(bar_width=10), MofNCompleteColumn(),
                            TextColumn("steps  cell {task.fields[cell]}  ETA {task.fields[eta]}  "
                                       "residual {task.fields[residual]}"), console=console, transient=False)
        self.bar.__enter__()
        self.task = self.bar.add_task(self.name, total=None, cell="-", eta="-", residual="-")
        return self

    def update(self, step: int, total: int | None, cell_time_s: float, eta_cell_s: float | None = None,
               residual_um: float | None = None, name: str | None = None) -> None:
        if self.quiet:
            return
        self.bar.update(self.task, description=name or self.name, completed=step, total=total,
                        cell=f"{cell_time_s:.0f} s", eta=f"{eta_cell_s:.0f} s" if eta_cell_s is not None else "-",
                        residual=f"{residual_um:.2f} µm" if residual_um is not None else "-")

    def on_progress(self, p) -> None:
        """For `run_routine`'s on_progress: an orchestrator Progress."""
        self.update(p.done, p.total, p.cell_time_s)

    def on_event(self, p: dict) -> None:
        """For a daemon's progress event."""
        self.update(p["step"], p["total"], p["cell_time_s"], p.get("eta_cell_s"), p.get("residual_um"),
                    label(p.get("routine"), p.get("item")))

    def __exit__(self, *exc) -> bool:
        if not self.quiet:
            self.bar.__exit__(*exc)
        return False


def label(routine: str | None, item: str | None) -> str:
    """What a progress bar is of: "ROUTINE (routine 2/4)" in a sequence, else the routine."""
    number = _item_number(routine, item)
    return f"{item} (routine {number})" if number else item or routine or ""


def _item_number(routine: str | None, item: str | None) -> str | None:
    """"2/4" for the second of a sequence's four routines; None for a routine run on its own."""
    sequence = sequences().get(routine or "")
    return sequence.number(item) if sequence is not None and item in sequence.names else None


def print_calibrations(cals: list[dict], where: str) -> None:
    if not cals:
        print(f"no calibrations in {where}")
        return
    target, routine = _widest(c["target"] for c in cals), _widest(c["routine"] for c in cals)
    for c in cals:
        ver = (c.get("stats") or {}).get("verification") or {}
        figure = f"  ver mean {ver['mean_um']:.2f} µm" if ver.get("mean_um") is not None else ""
        print(fill(f"{c['id']:4d}  {c['target']:{target}s} v{c['version']:<3d} {'ACTIVE' if c['active'] else '      '} "
                   f"{c['routine']:{routine}s}  {c['created']}{figure}", 6))


def print_health(targets: dict, history: bool = False) -> None:
    if not targets:
        print("no active calibrations")
    for target, h in targets.items():
        a, last = h["active"], h["last_check"]
        print(fill(f"{target}: calibration {a['id']} (v{a['version']}, {a['routine']})  {h['verdict'].upper()}", 4))
        print(fill(f"last check {last['created']} (check {last['check']}, of calibration {last['calibration_id']})"
                   if last else "never checked", 4, first=4))
        for c in (h["history"] if history else [last] if last else []):
            d = c["drift"]
            extra = "".join(f", {k} {d[k]:.0f}" for k in ("rotation_urad", "scale_ppm") if k in d)
            print(fill(f"{c['created']}  {'DRIFT' if c['drifted'] else 'ok'}  p {c['p_value']:.3g}  "
                       f"dx {d['dx_um']:+.2f} ± {d['dx_std_um']:.2f}, dy {d['dy_um']:+.2f} ± {d['dy_std_um']:.2f} µm"
                       f"{extra}", 8, first=4))
            if c["action"]:
                print(fill(c["action"], 8, first=8))


def print_status(s: dict, where: str) -> None:
    print(f"cell {s['cell']} ({'simulated' if s['simulated'] else 'real'}) at {where}")
    for d in s["devices"]:
        print(f"  {d['kind']:8s} {d['name']:10s} {d['backend']:10s} {d['state']}"
              + (f"  ({d['error']})" if d.get("error") else ""))
    p = s.get("arm_pose")
    if p:
        print(f"  arm pose: x {p['x_mm']:.3f} y {p['y_mm']:.3f} z {p['z_mm']:.3f} mm, alpha {p['alpha_deg']:.3f} deg")
    print(f"  live job: {s['job'] if s['job'] is not None else 'none'}")
    disk = s.get("disk")
    if disk:
        low = f", BELOW the {disk['min_free_mb']:g} MB to keep: new jobs are refused" if disk["low"] else ""
        print(f"  store disk: {disk['free_mb']:.1f} MB free of {disk['total_mb']:.1f} MB ({disk['filesystem']}){low}")
    lock = s["lock"]
    print(f"  lock: held by {lock['holder']} ({lock['expires_in_s']} s left)" if lock.get("held") else "  lock: free")
    schedule = s.get("health_schedule")
    if schedule:
        waiting = f" (waiting: {schedule['waiting_for']})" if schedule.get("waiting_for") else ""
        print(f"  next calibration check: {schedule['next_check']}, every {schedule['every_h']:g} h{waiting}")


def print_jobs(jobs: list[dict]) -> None:
    """A table, one line a job; a reason that would pass WIDTH goes on the next line."""
    if not jobs:
        print("no jobs")
        return
    rows = [(str(j["id"]), j["state"], j["routine"], progress(j), _seed(j["seed"]), j["updated"], j["reason"] or "")
            for j in jobs]
    head = ("id", "state", "routine", "progress", "seed", "updated", "reason")
    widths = [max(len(r[i]) for r in (head, *rows)) for i in range(len(head) - 1)]
    for row in (head, *rows):
        line = "  ".join(cell.rjust(w) if i in (0, 3, 4) else cell.ljust(w)
                         for i, (cell, w) in enumerate(zip(row, widths)))
        if len(line) + 2 + len(row[-1]) <= WIDTH:
            print(f"{line}  {row[-1]}".rstrip())
        else:
            print(line)
            print(fill(row[-1], widths[0] + 2, first=widths[0] + 2))


def progress(job: dict) -> str:
    """A job's steps: "12/56", and for a sequence "routine 2/4: step 12/56" (each routine plans its steps when it
    starts), the same whether the job runs or has ended; "-" before its first step."""
    p = job.get("progress")
    if not p:
        return "-"
    steps = f"{p.get('step', 0)}/{p['total'] if p.get('total') is not None else '?'}"
    number = _item_number(job["routine"], p.get("item"))
    return steps if number is None else f"routine {number}: step {steps}"


def _seed(seed) -> str:
    return "-" if seed is None else str(seed)


def print_job(j: dict) -> None:
    print(fill(f"job {j['id']}: {j['routine']} {json.dumps(j['params'])} simulation seed {_seed(j['seed'])}", 4))
    print(fill(f"state {j['state']}: {j['reason']}" + ("" if j["acknowledged"] else "  (needs acknowledgement)"), 4,
               first=2))
    if j.get("progress"):
        p = j["progress"]
        item = f" ({p['item']})" if p.get("item") else ""
        print(f"  progress: {progress(j)}{item}, cell time {p['cell_time_s']:.1f} s")
    print(f"  run folder: {j['run_dir']}")
    for h in j["history"]:
        print(fill(f"{h['at']}  {h['from'] or '-':8s} -> {h['to']:8s} {h['who']}: {h['reason']}", 6, first=2))


def print_audit(entries: list[dict]) -> None:
    """One line an entry; its detail (a request's body) below it, wrapped to WIDTH."""
    if not entries:
        print("no audit entries")
        return
    client, action = _widest(a["client"] for a in entries), _widest(a["action"] for a in entries)
    for a in entries:
        print(fill(f"{a['at']}  {a['client']:{client}s}  {a['action']:{action}s}  {a['target']}  {a['outcome']}", 4))
        if a["detail"]:
            print(fill(a["detail"], 4, first=4))


def _widest(texts, most: int = 32) -> int:
    """A column's width: its widest entry, up to `most` (a longer one pushes its line on)."""
    return min(max((len(t) for t in texts), default=0), most)


def fill(text: str, indent: int, first: int = 0) -> str:
    """`text` wrapped at spaces to WIDTH columns, never cut: the first line indented `first`, the rest `indent`."""
    return textwrap.fill(text, WIDTH, initial_indent=" " * first, subsequent_indent=" " * indent,
                         break_long_words=False, break_on_hyphens=False)


# what an operator request says besides its identity, timing and the ways to answer it
_REQUEST_PLUMBING = {"id", "kind", "answer_with", "instruction", "posted", "timeout_s", "expires_in_s", "job",
                     "model_points", "edges", "image_size", "n_points", "colour"}


def print_operator(state: dict, console: str | None) -> None:
    """The pending operator request and how to answer it (`cellctl operator`)."""
    if not state.get("answered_here"):
        print(f"this cell's operator is backend {state['backend']!r}: its requests are not answered through the "
              "daemon (operator: {backend: web} in the cell file makes them so)")
    req = state.get("request")
    if req is None:
        last = state.get("last")
        print("no operator request pending" + (f" (the last, request {last['request']} ({last['kind']}), ended "
                                               f"{last.get('outcome', '?')})" if last else ""))
        return
    job = f", job {req['job']}" if req.get("job") is not None else ""
    print(f"operator request {req['id']} ({req['kind']}{job}), expires in {req['expires_in_s']:.0f} s")
    print(f"  {req['instruction']}")
    about = {k: v for k, v in req.items() if k not in _REQUEST_PLUMBING and not k.endswith("_url") and v is not None}
    if about:
        print("  " + ", ".join(f"{k} {v}" for k, v in about.items()))
    if req["answer_with"] == "clicks":
        print(f"  answer it at the web console{f': {console}' if console else ''} (click on the frame, or decline "
              "there if too few points are visible); it cannot be answered from the CLI")
    else:
        print(f"  answer: cellctl operator done {req['id']}  |  cellctl operator decline {req['id']} --reason TEXT")


RESULT_STYLE = {"ok": "green", "problem": "bold red", "skipped": "yellow", "info": "cyan"}


def print_checks(answer: dict, console=None) -> None:
    """The device self-test (cellctl commission) as a table: device, check, result, figure, finding / fix; then the
    findings counted. rich, wrapped within WIDTH columns when not on a terminal."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    if not console.is_terminal:
        console = Console(width=WIDTH, no_color=True, highlight=False)
    moved = "with" if answer.get("moved") else "without"
    table = Table(title=f"cell {answer['cell']}: self-test of {answer.get('device') or 'every device'} ({moved} "
                        "the arm's move)", show_lines=True, title_justify="left")
    for column, ratio in (("device", None), ("check", None), ("result", None), ("figure", 3), ("finding / fix", 4)):
        table.add_column(column, ratio=ratio, overflow="fold")
    for c in answer["checks"]:
        table.add_row(c["device"], c["check"], f"[{RESULT_STYLE.get(c['result'], '')}]{c['result']}[/]",
                      c["figure"] or "-", c["finding"] or "")
    console.print(table)
    n = answer["problems"]
    console.print(f"{n} problem{'s' if n != 1 else ''} found" + (": fix them and run the self-test again" if n else
                                                                   "") + f" ({answer['seconds']:.1f} s)",
                  highlight=False)
