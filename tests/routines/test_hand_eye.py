"""hand-eye on the simulated UR5e cell, against the hidden truth; `cellctl fit hand-eye` on pose pairs from elsewhere,
and the bad input it refuses. The figures over seeds 0-9 are tools/hand_eye_figures.py's."""

import contextlib
import csv
import io
import json
import math
import os
import re
import subprocess

import cv2
import numpy as np
import pytest

from geometry import ur

from drivers.sim.kinds import build_world

from calibration.errors import CalibrationInputError
from calibration.models.hand_eye import pose_from_dict, pose_to_dict
from calibration.routines.six_axis.hand_eye import HandEye

from cellctl.config import load_cell_file
from cellctl.core import runs
from cellctl.errors import InvalidRequest, Unavailable
from cellctl.service.local import LocalService
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.run_folder import read_samples_text

from tests.conftest import ROOT

pytestmark = pytest.mark.long  # run first: see conftest.py

CELL = ROOT / "config" / "sim-ur5e-handeye.yaml"
EYE_TO_HAND = {"mount": "eye-to-hand", "camera": "top", "squares": [6, 5], "square_mm": 15, "marker_mm": 11,
               "first_marker": 100, "target_mm": [-500, -130, 450], "camera_mm": [-500, -130, 1000],
               "radius_mm": 60, "mount_mm": [0, -60, 35], "focal_mm": 12}
POSE = ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")


@pytest.fixture(scope="module")
def cell():
    return load_cell_file(CELL)


@pytest.fixture(scope="module")
def run(cell, tmp_path_factory):
    config, text = cell
    folder = tmp_path_factory.mktemp("hand-eye")
    store = CalibrationStore(folder / "calibrations")
    return runs.run_routine("hand-eye", config, text, folder / "run", seed=3, store=store), folder / "run", store


def test_eye_in_hand_finds_the_camera_on_the_flange_within_its_stated_uncertainty(run):
    result, _, _ = run
    truth, model, stats = result["truth"], result["model"], result["stats"]
    assert truth["hand_eye_translation_error_mm"] <= 0.4  # the worst case over seeds (median 0.14)
    assert truth["hand_eye_rotation_error_deg"] <= 0.03
    assert truth["within_bound95"]
    assert 0.2 <= truth["hand_eye_error_over_sigma"] <= 3
    assert len(model["hand_eye_sigma"]["translation_mm"]) == 3 and len(model["hand_eye_sigma"]["rotation_deg"]) == 3
    assert abs(truth["board_scale_error_ppm"]) < 500 and abs(truth["intrinsics"]["fx_error_px"]) < 2
    assert stats["calibration"]["n_poses"] == 15 and stats["calibration"]["rms_px"] < 0.3
    assert stats["verification"]["n_poses"] == 5 and stats["verification"]["corner_mean_mm"] < 0.3
    assert set(truth["baseline_opencv"]) == {"TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS", "SHAH", "LI"}
    assert result["cell_time_s"] <= 90


def test_the_touch_test_lands_the_tool_tip_on_corners_the_held_out_views_located(run):
    result, _, _ = run
    truth = result["truth"]
    assert len(truth["touch_misses_mm"]) == 4 and truth["touch_mean_mm"] <= 0.3  # the goal
    table = next(t for t in result["tables"] if t["title"].startswith("Touch test"))
    assert [r[0] for r in table["rows"]] == ["touch1", "touch2", "touch3", "touch4"]
    assert [r[-1] for r in table["rows"]] == ["located by v01", "located by v02", "located by v03", "located by v04"]


def test_visiting_the_poses_in_another_order_gives_the_same_hand_eye(run, cell, tmp_path):
    config, text = cell
    again = runs.run_routine("hand-eye", config, text, tmp_path / "run", seed=3,
                             overrides={"order_seed": 1, "touches": 0})
    first, second = (pose_from_dict(r["model"]["hand_eye"]) for r in (run[0], again))
    assert np.linalg.norm(first[:3, 3] - second[:3, 3]) * 1e3 <= 0.1  # the repeat-run figure


def test_locate_puts_what_the_wrist_camera_sees_on_the_board_where_it_truly_is(run, cell):
    """A new pose the fit never saw: each corner's true pixel, located through the stored calibration and the
    flange pose the arm reports, lands on the corner within its reported uncertainty."""
    config, _ = cell
    _, _, store = run
    world = build_world(config.sim.model_copy(update={"seed": 3}))  # the run's hidden truth
    routine = HandEye()
    plan = routine.pose_plan(runs.routine_params(routine, config, {"plan_seed": 7, "poses": 4, "verify_poses": 0}),
                             (2448, 2048))
    service = LocalService.of_store(config, store)
    board, errors, sigmas = world.boards["table"], [], []
    for pose in plan.poses:
        world.move_joints(pose.joints)
        ids, uv = world.corner_pixels("wrist", "table", world.camera_pose("wrist"))
        flange = pose_to_dict(ur.forward(world.reported_joints()))
        for k in range(0, len(ids), 15):
            where = service.locate("wrist", *map(float, uv[k]), flange=tuple(flange[f] for f in POSE))
            true = (board.pose @ np.append(board.true_corners()[ids[k]], 1.0))[:3] * 1e3
            errors.append(np.hypot(where["x_mm"] - true[0], where["y_mm"] - true[1]))
            sigmas.append(where["sigma_um"] * 1e-3)
    assert where["plane"] == "board" and set(where["calibrations"]) == {"hand-eye:wrist"}
    assert np.mean(errors) <= 0.3 and 0.3 <= np.median(np.array(errors) / sigmas) <= 2.5
    with pytest.raises(Unavailable, match="flange pose"):
        service.locate("wrist", 100.0, 100.0)  # no daemon to ask the arm, and no flange given
    with pytest.raises(InvalidRequest, match=r"off the camera's 2448 x 2048 image"):
        service.locate("wrist", 5000.0, 100.0, flange=tuple(flange[f] for f in POSE))
    with pytest.raises(InvalidRequest, match=r"flange: the quaternion .* has length 1.414213562, not 1"):
        service.locate("wrist", 100.0, 100.0, flange=(0, 0, 500, 1, 1, 0, 0))


def test_the_report_shows_the_result_the_poses_and_opencv_beside_it_and_the_calibration_is_stored(run):
    result, out, store = run
    titles = [t["title"] for t in result["tables"]]
    assert titles[0].startswith("Hand-eye result") and "Per pose" in titles
    assert any(t.startswith("Against OpenCV") for t in titles)
    assert (out / "report.md").exists() and (out / result["files"]["plot"]).exists()
    stored = store.active("hand-eye:wrist")
    assert stored is not None and stored.model["hand_eye"] == result["model"]["hand_eye"]
    assert np.allclose(pose_from_dict(stored.model["hand_eye"]), stored.model["matrices"]["hand_eye_4x4_m"])


def test_eye_to_hand_finds_the_board_on_the_flange(cell, tmp_path):
    config, text = cell
    result = runs.run_routine("hand-eye", config, text, tmp_path / "run", seed=2, overrides=EYE_TO_HAND)
    truth = result["truth"]
    assert truth["hand_eye_translation_error_mm"] <= 0.3 and truth["hand_eye_rotation_error_deg"] <= 0.05
    assert truth["within_bound95"]


def test_a_region_out_of_reach_is_refused_before_anything_moves(cell, tmp_path):
    config, text = cell
    with pytest.raises(CalibrationInputError, match=r"the region gives 0 usable poses of 800 tried, fewer than the "
                                                    r"20 asked \(refused: out of reach 800\)"):
        runs.run_routine("hand-eye", config, text, tmp_path / "run", seed=1, overrides={"target_mm": [-1500, 0, 0]})
    assert not (tmp_path / "run" / "samples.csv").exists()


# -- pose pairs from elsewhere ---------------------------------------------------------------------------------------
def _pairs_file(run, path, rows=None):
    """The run's calibration views as pose pairs (the flange pose, and the board by PnP with the fitted lens), as
    another tool would write them."""
    result, out, _ = run
    lens = result["model"]["intrinsics"]
    K = np.array([[lens["fx_px"], 0, lens["cx_px"]], [0, lens["fy_px"], lens["cy_px"]], [0, 0, 1]])
    dist = np.array([lens[k] for k in ("k1", "k2", "p1", "p2", "k3")])
    from geometry.charuco import BoardDrawing

    corners = BoardDrawing((12, 9), 0.02, 0.015).corners() * result["model"]["board_scale"]
    samples = [r for r in read_samples_text((out / "samples.csv").read_text()) if r["status"] == "ok" and r["set"] != "touch"]
    if rows is None:
        rows = []
        for pose in sorted({r["pose"] for r in samples}):
            seen = [r for r in samples if r["pose"] == pose]
            ids = np.array([int(r["corner_id"]) for r in seen])
            uv = np.array([[float(r["u_px"]), float(r["v_px"])] for r in seen])
            _, rvec, tvec = cv2.solvePnP(corners[ids], uv, K, dist)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            target = pose_to_dict(T)
            rows.append({"pose": pose, "set": seen[0]["set"], **{f"flange_{k}": seen[0][f"flange_{k}"] for k in POSE},
                         **{f"target_{k}": repr(target[k]) for k in POSE}})
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return rows


def _fit(path, out, *extra):
    return subprocess.run([str(ROOT / ".venv" / "bin" / "cellctl"), "fit", "hand-eye", "--samples", str(path),
                           "--out", str(out), *extra], capture_output=True, text=True, timeout=300)


def _fit_here(path, out, *extra) -> subprocess.CompletedProcess:
    """`cellctl fit hand-eye` as _fit runs it, through the same main() in this process (its exit status and what it
    writes): a refused file is refused by the fit, and a new interpreter's second of imports adds nothing to that."""
    from cellctl.cli import main

    args = ["fit", "hand-eye", "--samples", str(path), "--out", str(out), *extra]
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = main(args)
        except SystemExit as exc:  # argparse's refusals
            code = exc.code
    return subprocess.CompletedProcess(["cellctl", *args], code, stdout.getvalue(), stderr.getvalue())


def test_pose_pairs_from_elsewhere_fit_to_the_same_hand_eye(run, tmp_path):
    rows = _pairs_file(run, tmp_path / "pairs.csv")
    done = _fit(tmp_path / "pairs.csv", tmp_path / "cal.json")
    assert done.returncode == 0, done.stderr
    fitted = json.loads((tmp_path / "cal.json").read_text())
    X = pose_from_dict(fitted["model"]["hand_eye"])
    X_images = pose_from_dict(run[0]["model"]["hand_eye"])
    assert np.linalg.norm(X[:3, 3] - X_images[:3, 3]) < 0.5e-3  # the same camera, found from the pairs alone
    assert fitted["stats"]["verification"]["n_poses"] == sum(r["set"] == "ver" for r in rows)
    assert "hand_eye_sigma_mm" in done.stdout


@pytest.mark.parametrize("spoil, message", [
    (lambda rows: [{k: v for k, v in r.items() if k != "target_qz"} for r in rows], "missing columns: target_qz"),
    (lambda rows: [dict(r, flange_y_mm="nan") if i == 2 else r for i, r in enumerate(rows)],
     "bad.csv: row 4, column flange_y_mm: nan is not a finite number"),
    (lambda rows: [dict(r, target_qw=repr(float(r["target_qw"]) + 1e-4)) if i == 1 else r for i, r in enumerate(rows)],
     r"row 3: target_\*: the quaternion \(qw, qx, qy, qz\) has length"),
    (lambda rows: rows[:2], "2 calibration pose pairs, fewer than the 3 a hand-eye fit needs"),
    (lambda rows: rows + [dict(rows[0], pose="again")], "poses p01 and again have the same flange pose"),
    (lambda rows: rows + [dict(rows[0])], r"row \d+: pose 'p01' again \(first on row 2\)"),
])
def test_a_bad_pose_pair_file_is_refused_naming_what_is_wrong(run, tmp_path, spoil, message):
    rows = _pairs_file(run, tmp_path / "good.csv")
    _pairs_file(run, tmp_path / "bad.csv", spoil(rows))
    done = _fit_here(tmp_path / "bad.csv", tmp_path / "cal.json")
    assert done.returncode == 2
    assert re.search(message, done.stderr), done.stderr
    assert not (tmp_path / "cal.json").exists()


def test_pose_pairs_rotating_about_one_axis_are_refused_saying_what_to_add(run, tmp_path):
    rows = _pairs_file(run, tmp_path / "good.csv")
    first = pose_from_dict({k: float(rows[0][f"flange_{k}"]) for k in POSE})
    spun = []
    for i, r in enumerate(rows):
        turn = np.eye(4)
        angle = math.radians(15 * i)
        turn[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
        turn[:3, 3] = [0.01 * i, 0.0, 0.0]
        flange = pose_to_dict(first @ turn)
        spun.append(dict(r, **{f"flange_{k}": repr(flange[k]) for k in POSE}))
    _pairs_file(run, tmp_path / "spun.csv", spun)
    done = _fit_here(tmp_path / "spun.csv", tmp_path / "cal.json")
    assert done.returncode == 2
    assert "rotation axes span one direction" in done.stderr and "add poses tilted about" in done.stderr
    assert not (tmp_path / "cal.json").exists()


def test_cellctl_plan_shows_the_poses_before_anything_moves_and_refuses_a_region_out_of_reach():
    cellctl = [str(ROOT / ".venv" / "bin" / "cellctl"), "plan", "hand-eye", "--config", str(CELL)]
    shown = subprocess.run(cellctl, capture_output=True, text=True, timeout=120, env=dict(os.environ, COLUMNS="100"))
    assert shown.returncode == 0, shown.stderr
    lines = shown.stdout.splitlines()
    assert lines[0] == "hand-eye: Planned poses (flange in the base frame, nominal)"
    assert sum(line.startswith(("p", "v")) and (" cal " in line or " ver " in line) for line in lines) == 20
    assert re.search(r"rotation-axis spread 0\.\d\d", shown.stdout) and max(map(len, lines)) <= 100
    refused = subprocess.run(cellctl + ["--param", "target_mm=[-1500,0,0]"], capture_output=True, text=True,
                             timeout=120)
    assert refused.returncode == 2 and "out of reach 800" in refused.stderr
    other = subprocess.run(cellctl[:2] + ["virtual-grid", "--config", str(ROOT / "config" / "sim-microcell.yaml")],
                           capture_output=True, text=True, timeout=120)
    assert other.returncode == 2 and "virtual-grid plans no motion of its own to preview" in other.stderr


def test_stored_intrinsics_are_used_as_they_are_and_the_hand_eye_still_holds(run, cell, tmp_path):
    config, text = cell
    first, _, store = run
    result = runs.run_routine("hand-eye", config, text, tmp_path / "run", seed=3, store=store,
                              overrides={"intrinsics": "stored", "touches": 0})
    assert result["model"]["intrinsics"] == first["model"]["intrinsics"]  # held, not fitted again
    assert result["truth"]["hand_eye_translation_error_mm"] <= 0.4 and result["truth"]["within_bound95"]
    samples = read_samples_text((tmp_path / "run" / "samples.csv").read_text())
    assert float(samples[0]["fx_px"]) == first["model"]["intrinsics"]["fx_px"]  # the run says what it used
