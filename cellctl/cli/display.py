"""What the CLI shows: one progress bar (in-process runs and daemon jobs alike) and the listings."""

from __future__ import annotations

import json


class ProgressBar:
    """step i / N, simulated cell time, and for a daemon job the ETA in cell time and the residual (rich, stderr).

    A context manager; `quiet` shows nothing."""

    def __init__(self, name: str, quiet: bool = False):
        self.name, self.quiet = name, quiet

    def __enter__(self) -> "ProgressBar":
        if self.quiet:
            return self
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("steps  cell {task.fields[cell]}  ETA {task.fields[eta]}  "
                                       "residual {task.fields[residual]}"), TimeElapsedColumn(),
                            console=Console(stderr=True), transient=False)
        self.bar.__enter__()
        self.task = self.bar.add_task(self.name, total=None, cell="-", eta="-", residual="-")
        return self

    def update(self, step: int, total: int | None, cell_time_s: float, eta_cell_s: float | None = None,
               residual_um: float | None = None, name: str | None = None) -> None:
        if self.quiet:
            return
        self.bar.update(self.task, description=name or self.name, completed=step, total=total,
                        cell=f"{cell_time_s:.1f} s", eta=f"{eta_cell_s:.0f} s" if eta_cell_s is not None else "-",
                        residual=f"{residual_um:.2f} µm" if residual_um is not None else "-")

    def on_progress(self, p) -> None:
        """For `run_routine`'s on_progress: an orchestrator Progress."""
        self.update(p.done, p.total, p.cell_time_s)

    def on_event(self, p: dict) -> None:
        """For a daemon's progress event."""
        self.update(p["step"], p["total"], p["cell_time_s"], p.get("eta_cell_s"), p.get("residual_um"),
                    p.get("item") or p.get("routine"))

    def __exit__(self, *exc) -> bool:
        if not self.quiet:
            self.bar.__exit__(*exc)
        return False


def print_calibrations(cals: list[dict], where: str) -> None:
    if not cals:
        print(f"no calibrations in {where}")
    for c in cals:
        ver = (c.get("stats") or {}).get("verification") or {}
        figure = f"ver mean {ver['mean_um']:.2f} µm" if ver.get("mean_um") is not None else ""
        print(f"{c['id']:4d}  {c['target']:8s} v{c['version']:<3d} {'ACTIVE' if c['active'] else '      '} "
              f"{c['routine']:16s} {c['created']}  {figure}")


def print_health(targets: dict, history: bool = False) -> None:
    if not targets:
        print("no active calibrations")
    for target, h in targets.items():
        a, last = h["active"], h["last_check"]
        when = f"last check {last['created']} (check {last['check']}, of calibration {last['calibration_id']})" \
            if last else "never checked"
        print(f"{target:8s} calibration {a['id']} (v{a['version']}, {a['routine']})  {h['verdict'].upper():9s} {when}")
        for c in (h["history"] if history else [last] if last else []):
            d = c["drift"]
            extra = "".join(f", {k} {d[k]:.0f}" for k in ("rotation_urad", "scale_ppm") if k in d)
            print(f"    {c['created']}  {'DRIFT' if c['drifted'] else 'ok   '}  dx {d['dx_um']:+.2f} ± "
                  f"{d['dx_std_um']:.2f}, dy {d['dy_um']:+.2f} ± {d['dy_std_um']:.2f} µm{extra}  p {c['p_value']:.3g}"
                  f"  {c['action']}")


def print_status(s: dict, where: str) -> None:
    print(f"cell {s['cell']} ({'simulated' if s['simulated'] else 'real'}) at {where}")
    for d in s["devices"]:
        print(f"  {d['kind']:8s} {d['name']:10s} {d['backend']:10s} {d['state']}"
              + (f"  ({d['error']})" if d.get("error") else ""))
    p = s.get("arm_pose")
    if p:
        print(f"  arm pose: x {p['x_mm']:.3f} y {p['y_mm']:.3f} z {p['z_mm']:.3f} mm, alpha {p['alpha_deg']:.3f} deg")
    print(f"  live job: {s['job'] if s['job'] is not None else 'none'}")
    lock = s["lock"]
    print(f"  lock: held by {lock['holder']} ({lock['expires_in_s']} s left)" if lock.get("held") else "  lock: free")
    schedule = s.get("health_schedule")
    if schedule:
        waiting = f" (waiting: {schedule['waiting_for']})" if schedule.get("waiting_for") else ""
        print(f"  next calibration check: {schedule['next_check']}, every {schedule['every_h']:g} h{waiting}")


def print_jobs(jobs: list[dict]) -> None:
    if not jobs:
        print("no jobs")
    for j in jobs:
        p = j.get("progress") or {}
        steps = f"{p.get('step', 0)}/{p.get('total', '?')}" if p else "-"
        print(f"{j['id']:5d}  {j['state']:8s} {j['routine']:20s} {steps:>9s}  seed {j['seed']}  {j['updated']}  "
              f"{j['reason']}")


def print_job(j: dict) -> None:
    print(f"job {j['id']}: {j['routine']} {json.dumps(j['params'])} seed {j['seed']}")
    print(f"  state {j['state']}: {j['reason']}" + ("" if j["acknowledged"] else "  (needs acknowledgement)"))
    if j.get("progress"):
        p = j["progress"]
        print(f"  progress: step {p['step']}/{p['total']}, cell time {p['cell_time_s']:.1f} s")
    print(f"  run folder: {j['run_dir']}")
    for h in j["history"]:
        print(f"  {h['at']}  {h['from'] or '-':8s} -> {h['to']:8s} {h['who']}: {h['reason']}")


def print_audit(entries: list[dict]) -> None:
    for a in entries:
        print(f"{a['at']}  {a['client']:28s} {a['action']:32s} {a['target']:16s} {a['outcome']}"
              + (f"  {a['detail']}" if a["detail"] else ""))


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
