"""`cellctl camera CAM`: the live camera view from the command line (through the daemon, as every verb).

    cellctl camera cam2                              exposure and gain (now, in the cell file, allowed) and a frame's figures
    cellctl camera cam2 --snapshot out.png           one live frame as the console draws it (saturated pixels,
                                                     features, the calibrated grid), written atomically
    cellctl camera cam2 --set exposure_s=0.004       change a setting on the camera now (needs the operator lock)
    cellctl camera cam2 --save [--yes]               the cell file's diff for the changed settings; --yes writes it

Kept light (no numerics imported): the daemon does the work.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from cellctl.cli.args import InputError

LAYERS = ("features", "grid", "saturation")


def camera_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("camera", help="a camera of the cell file (cellctl status lists them)")
    p.add_argument("--snapshot", metavar="PNG", help="write one live frame, drawn, as PNG (refused while a job "
                                                     "uses the camera)")
    p.add_argument("--layers", default=",".join(LAYERS), help="what --snapshot draws, comma-separated: "
                   f"{', '.join(LAYERS)} (default: all); 'none': the frame alone")
    p.add_argument("--width", type=int, help="--snapshot: scale down to this width (px; default: full size)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a setting on the camera now, e.g. exposure_s=0.004 or gain_db=6 (its keys and "
                        "ranges: cellctl camera CAM); needs the operator lock while someone holds it")
    p.add_argument("--save", action="store_true", help="show the cell file's diff for the settings changed live")
    p.add_argument("--yes", action="store_true", help="with --save: write the cell file (atomically)")
    p.add_argument("--json", action="store_true", help="print the service's answers as JSON")


def _layers(text: str) -> tuple[str, ...]:
    if text.strip() == "none":
        return ()
    chosen = tuple(t.strip() for t in text.split(",") if t.strip())
    bad = [t for t in chosen if t not in LAYERS]
    if bad:
        raise InputError(f"--layers: {', '.join(bad)}; allowed: {', '.join(LAYERS)}, or none")
    return chosen


def _values(pairs: list[str]) -> dict:
    out = {}
    for pair in pairs:
        key, eq, text = pair.partition("=")
        if not eq or not key.strip():
            raise InputError(f"--set {pair!r}: expected KEY=VALUE, e.g. exposure_s=0.004")
        try:
            out[key.strip()] = float(text)
        except ValueError:
            raise InputError(f"--set {pair!r}: {text!r} is not a number") from None
    return out


def _check_writable(path: Path) -> None:
    """Before the daemon is asked: a path a PNG can be written to, or a clear error."""
    if path.is_dir():
        raise InputError(f"--snapshot {path}: is a folder; give a file name, e.g. {path / 'frame.png'}")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"--snapshot {path}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise InputError(f"--snapshot {path}: cannot write there (permission denied)")




def _print_settings(answer: dict) -> None:
    print(f"{answer['camera']} ({answer['backend']})")
    if answer.get("note"):
        print(f"  {answer['note']}")
    for key, s in answer["settings"].items():
        value = "-" if s["value"] is None else f"{s['value']:g}"
        in_file = "not set" if s["in_file"] is None else f"{s['in_file']:g}"
        mark = "  (changed: --save writes it)" if s["changed"] else ""
        print(f"  {s['label']:<9} {key:<11} {value:>10} {s['unit']:<13} cell file: {in_file:<9} allowed: "
              f"{s['minimum']:g} to {s['maximum']:g} {s['unit']}{mark}")


def _print_stats(stats: dict) -> None:
    print(f"  frame {stats['width']}x{stats['height']}: mean {stats['mean_pct']:.1f} % of full scale "
          f"({stats['full_scale']}), min {stats['min']}, max {stats['max']}, saturated {stats['saturated']} px "
          f"({stats['saturated_pct']:.3g} %)" + (f", {len(stats['features'])} feature(s) found"
                                                  if "features" in stats else ""))


def camera(s, caller, args) -> int:
    values = _values(args.set)
    layers = _layers(args.layers)
    out = Path(args.snapshot) if args.snapshot else None
    if out is not None:
        _check_writable(out)
    if args.yes and not args.save:
        raise InputError("--yes: only with --save (it writes the cell file)")
    answers: dict = {}
    if values:
        answers["settings"] = s.set_camera_settings(caller, args.camera, values)
    if out is not None:
        blob = s.live_frame(args.camera, layers, args.width, "png")
        try:
            from cellctl.stores.run_folder import write_atomic  # here: the other verbs start without it

            write_atomic(out, blob.data)  # (an OSError says the file system's reason; main() reports it)
        except OSError as exc:
            raise InputError(f"--snapshot {out}: {exc.strerror or exc}") from None
        stats = json.loads(blob.headers.get("X-Live-Stats", "{}"))
        answers["snapshot"] = {"file": str(out), "frame_id": blob.headers.get("X-Frame-Id"), "stats": stats}
    if args.save:
        answers["save"] = s.save_camera_settings(caller, args.camera, confirm=args.yes)
    if not answers:  # nothing asked: what the camera uses, and a frame's figures
        answers["settings"] = s.camera_settings(args.camera)
        blob = s.live_frame(args.camera, (), 256, "jpeg")
        answers["frame"] = json.loads(blob.headers.get("X-Live-Stats", "{}"))
    if args.json:
        print(json.dumps(answers, indent=2))
        return 0
    if "settings" in answers:
        _print_settings(answers["settings"])
    if "frame" in answers:
        _print_stats(answers["frame"])
    if "snapshot" in answers:
        snap = answers["snapshot"]
        print(f"{args.camera}: frame {snap['frame_id']} written to {snap['file']}")
        _print_stats(snap["stats"])
    if "save" in answers:
        save = answers["save"]
        if save["diff"]:
            print(save["diff"], end="" if save["diff"].endswith("\n") else "\n")
        print(save["message"] + ("" if save["written"] or not save["diff"] else " (add --yes)"))
    return 0
