"""The `truth` section of a simulated hand-eye run: the fitted X and Y, and each OpenCV method's, against the
hidden mount of the camera (or of the flange's board) and the hidden pose of the other board or camera.

Reads drivers.sim, which calibration/ never does.
"""

from __future__ import annotations

import math

import numpy as np

from calibration.models.hand_eye import pose_from_dict, transform_error
from calibration.routines.base import Devices, FitOutcome


def _truth_of(world, devices: Devices, params) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) as they truly are: eye-in-hand T_flange_camera and T_base_board, eye-to-hand T_flange_board and
    T_base_camera. The board is the world's board whose first marker and squares the parameters name."""
    camera = devices.cameras[params.camera]
    sim_name = getattr(camera, "sim_name", params.camera)
    boards = [b for b in world.boards.values()
              if b.config.first_marker == params.first_marker and tuple(b.config.squares) == tuple(params.squares)]
    if len(boards) != 1:
        raise LookupError(f"no board of {params.squares} squares from marker {params.first_marker} in the world")
    board, cam = boards[0], world.cameras[sim_name]
    if params.mount == "eye-in-hand":
        return cam.mount, board.pose
    return board.pose, cam.mount


def _errors(X, X_true) -> dict:
    t, r = transform_error(X, X_true)
    return {"translation_mm": float(t * 1e3), "rotation_deg": float(math.degrees(r))}


def hand_eye_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    X_true, Y_true = _truth_of(world, devices, params)
    model = outcome.model
    X, Y = pose_from_dict(model["hand_eye"]), pose_from_dict(model["world"])
    x_err, y_err = _errors(X, X_true), _errors(Y, Y_true)
    sigma = np.linalg.norm(model["hand_eye_sigma"]["translation_mm"])
    truth = {"hand_eye_translation_error_mm": x_err["translation_mm"],
             "hand_eye_rotation_error_deg": x_err["rotation_deg"],
             "world_translation_error_mm": y_err["translation_mm"], "world_rotation_error_deg": y_err["rotation_deg"],
             "hand_eye_error_over_sigma": x_err["translation_mm"] / sigma if sigma > 0 else None,
             "within_bound95": x_err["translation_mm"] <= model["hand_eye_bound95"]["translation_mm"]}
    baselines = {}
    for name, b in outcome.stats.get("opencv", {}).items():
        if b.get("hand_eye") is None:
            baselines[name] = {"error": b.get("error")}
            continue
        entry = {f"hand_eye_{k}": v for k, v in _errors(pose_from_dict(b["hand_eye"]), X_true).items()}
        if b.get("world") is not None:
            entry.update({f"world_{k}": v for k, v in _errors(pose_from_dict(b["world"]), Y_true).items()})
        baselines[name] = entry
    truth["baseline_opencv"] = baselines
    lens = model.get("intrinsics")
    if lens is not None:
        cam = world.cameras[getattr(devices.cameras[params.camera], "sim_name", params.camera)].lens
        truth["intrinsics"] = {"fx_error_px": lens["fx_px"] - cam.fx, "cx_error_px": lens["cx_px"] - cam.cx,
                               "cy_error_px": lens["cy_px"] - cam.cy}
    truth.update(_touch_truth(world, params, samples))
    board_scale = model.get("board_scale")
    if board_scale is not None:
        board = [b for b in world.boards.values() if b.config.first_marker == params.first_marker][0]
        truth["board_scale_error_ppm"] = (board_scale - board.scale) * 1e6
    return truth


def _touch_truth(world, params, samples: list[dict]) -> dict:
    """How far each touch landed from its corner: the tool tip where the arm truly put it (the world's record of
    that move, its repeatability included) against the corner where it truly is."""
    rows = [r for r in samples if r.get("set") == "touch" and r.get("status") == "ok"]
    if not rows:
        return {}
    board = [b for b in world.boards.values()
             if b.config.first_marker == params.first_marker and tuple(b.config.squares) == tuple(params.squares)][0]
    tip = np.append(np.asarray(params.tip_mm) * 1e-3, 1.0)
    misses = []
    for r in rows:
        q = np.radians([float(r[f"j{i}_deg"]) for i in range(1, 7)])
        moves = [m for m in world.moves if m.step == int(r["step"])]
        move = min(moves, key=lambda m: float(np.max(np.abs(m.joints - q))))
        corner = board.pose @ np.append(board.true_corners()[int(r["corner_id"])], 1.0)
        misses.append(float(np.linalg.norm((move.flange @ tip - corner)[:3]) * 1e3))
    return {"touch_mean_mm": float(np.mean(misses)), "touch_max_mm": float(np.max(misses)),
            "touch_misses_mm": misses}


def table_pick_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """The pick as the world saw it: how far the cup landed from the part's centre, and where the part truly lies
    after the place against where it was asked to go."""
    truth: dict = {"picked": bool(world.picks and world.picks[-1]["part"])}
    if world.picks:
        truth["pick_miss_mm"] = float(world.picks[-1]["miss_m"] * 1e3)
    if world.placements:
        lies = world.placements[-1]["centre"][:2] * 1e3
        truth["place_error_mm"] = float(np.hypot(*(lies - np.asarray(params.place_mm))))
    return truth


def hand_eye_check_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    """What truly moved since the calibration (the world's `sim.drift` knobs in force), per checked target: the
    camera's and its board's move, and how far the check's estimate of each is from it."""
    now = world.clock.now()
    truth: dict = {}
    for target in outcome.model.get("targets", []):
        camera = target.split(":", 1)[1]
        sim_name = getattr(devices.cameras.get(camera), "sim_name", camera)
        model = devices.calibrations.get(target, {})
        board = [b.name for b in world.boards.values() if b.config.first_marker == model.get("board", {}).get(
            "first_marker", -1)]
        estimate = outcome.stats.get("drift", {}).get(target, {})
        entry = {}
        for part, name in (("camera", sim_name), ("board", board[0] if board else None)):
            knob = world.config.drift.get(name) if name else None
            moved = knob is not None and knob.in_force(now)
            t = np.asarray(knob.translation_mm) if moved else np.zeros(3)
            r = np.asarray(knob.rotation_deg) if moved else np.zeros(3)
            entry[part] = {"translation_mm": float(np.linalg.norm(t)), "rotation_deg": float(np.linalg.norm(r))}
            seen = estimate.get(part, {})
            if "translation_mm" in seen:  # the estimate in the same frame as the knob: the mount's parent
                entry[part]["estimate_error_mm"] = float(np.linalg.norm(np.asarray(seen["translation_mm"]) - t))
                entry[part]["estimate_error_deg"] = float(np.linalg.norm(np.asarray(seen["rotation_deg"]) - r))
        truth[target] = entry
    truth["drifted"] = [t for t, e in truth.items()
                        if any(p["translation_mm"] > 0 or p["rotation_deg"] > 0 for p in e.values())]
    return truth
