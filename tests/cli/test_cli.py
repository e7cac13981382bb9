"""The command line: runs, offline fits, mapping, and clear errors with exit status 2 for bad input."""

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from cellctl.cli import main

from tests.conftest import MICROCELL

SMALL = ["--param", "rows=4", "--param", "cols=4", "--param", "n_verify=6"]


def run_cli(*args):
    return main([str(a) for a in args])


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "run"
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", out, "--seed", 3, "--quiet", *SMALL) == 0
    return out


def test_run_writes_the_result_files(small_run):
    result = json.loads((small_run / "result.json").read_text())
    assert result["routine"] == "virtual-grid"
    for part in ("calibration", "verification"):
        assert set(result["stats"][part]) >= {"n", "mean_um", "max_um", "rms_um"}
    assert result["cell_time_s"] > 0
    assert set(result["truth"]) >= {"mapping_mean_um", "mapping_max_um", "centroid_rms_px"}
    assert "seed 001 Table II" in (small_run / "report.md").read_text()


def test_console_script_runs_as_a_process(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "cellctl.cli", "check", "--config", str(MICROCELL)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "valid cell file" in proc.stdout


def test_fit_and_map_from_a_run_samples_file(small_run, tmp_path, capsys):
    cal = tmp_path / "cal.json"
    # with camera 1's image size: a grid that stopped early (issue 31) may not centre the samples' extent on it
    assert run_cli("fit", "virtual-grid", "--samples", small_run / "samples.csv", "--out", cal,
                   "--image-size", "2448x2050") == 0
    fitted = json.loads(cal.read_text())
    run_result = json.loads((small_run / "result.json").read_text())
    assert fitted["stats"]["verification"]["mean_um"] == pytest.approx(run_result["stats"]["verification"]["mean_um"], rel=1e-3)

    rows = list(csv.DictReader(open(small_run / "samples.csv")))
    pixels = tmp_path / "px.csv"
    pixels.write_text("u_px,v_px\n" + "".join(f"{r['u_px']},{r['v_px']}\n" for r in rows))
    out = tmp_path / "xy.csv"
    assert run_cli("map", cal, "--pixels", pixels, "--out", out) == 0
    mapped = list(csv.DictReader(open(out)))
    err = [np.hypot(float(m["x_mm"]) - float(r["x_mm"]), float(m["y_mm"]) - float(r["y_mm"])) for m, r in zip(mapped, rows)]
    assert max(err) < 0.015  # mm: within the robot's repeatability budget


def _synthetic_samples(path, rng, n_side=(9, 7), noise_mm=0.0005, outliers=()):
    """Samples 'recorded elsewhere': a 1280x1024 camera at 20 µm/px with strong barrel distortion."""
    import cv2

    K = np.array([[2500.0, 0, 652.0], [0, 2500.0, 498.0], [0, 0, 1]])
    dist = np.array([-0.35, 0.2, 0.001, -0.0008, 0])
    rvec = np.array([0.02, -0.015, 0.4])
    tvec = np.array([0.5, -0.3, 50.0])  # mm: plane 50 mm away -> 20 µm/px
    gx, gy = np.meshgrid(np.linspace(-11, 11, n_side[0]), np.linspace(-9, 9, n_side[1]))
    xy_cal = np.column_stack([gx.ravel(), gy.ravel()])
    xy_ver = rng.uniform([-11, -9], [11, 9], size=(20, 2))

    def project(xy):
        pts = np.column_stack([xy, np.zeros(len(xy))])
        return cv2.projectPoints(pts, rvec, tvec, K, dist)[0].reshape(-1, 2)

    lines = ["x_mm,y_mm,u_px,v_px,set"]
    for xy, name in ((xy_cal, "cal"), (xy_ver, "ver")):
        uv = project(xy)
        robot = xy + 100 + rng.normal(0, noise_mm, xy.shape)
        for i, ((x, y), (u, v)) in enumerate(zip(robot, uv)):
            if name == "cal" and i in outliers:
                x += 0.05
            lines.append(f"{float(x)!r},{float(y)!r},{float(u)!r},{float(v)!r},{name}")
    path.write_text("\n".join(lines) + "\n")

    def true_map(uv):
        k1, k2, p1, p2 = dist[:4]
        xd, yd = (uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]
        x, y = xd.copy(), yd.copy()
        for _ in range(200):  # fixed-point inverse of the Brown model, to 1e-15
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
            y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
        und = np.column_stack([x, y])
        R = cv2.Rodrigues(rvec)[0]
        rays = np.column_stack([und, np.ones(len(und))])
        # plane z=0 in object coords: solve R @ [x, y, 0] + t = s * ray
        out = []
        for ray in rays:
            A = np.column_stack([R[:, 0], R[:, 1], -ray])
            x, y, _ = np.linalg.solve(A, -tvec)
            out.append([x + 100, y + 100])
        return np.array(out)

    return true_map


def test_fit_on_samples_recorded_elsewhere(tmp_path):
    rng = np.random.default_rng(11)
    samples = tmp_path / "elsewhere.csv"
    true_map = _synthetic_samples(samples, rng, outliers=(5,))
    cal = tmp_path / "cal.json"
    assert run_cli("fit", "virtual-grid", "--samples", samples, "--out", cal, "--image-size", "1280x1024",
                   "--param", "radial_terms=3") == 0
    result = json.loads(cal.read_text())
    assert [r["step"] for r in result["rejected"]] == [5]  # the 50 µm outlier is found and listed
    uv = rng.uniform([100, 100], [1180, 924], size=(200, 2))
    pixels = tmp_path / "px.csv"
    pixels.write_text("u_px,v_px\n" + "".join(f"{u},{v}\n" for u, v in uv))
    out = tmp_path / "xy.csv"
    assert run_cli("map", cal, "--pixels", pixels, "--out", out) == 0
    mapped = np.array([[float(r["x_mm"]), float(r["y_mm"])] for r in csv.DictReader(open(out))])
    err_um = np.linalg.norm(mapped - true_map(uv), axis=1) * 1e3
    assert err_um.mean() < 1.0 and err_um.max() < 4.0


@pytest.mark.parametrize("content, message", [
    ("x_mm,y_mm,u_px\n1,2,3\n", "missing column(s) v_px, set"),
    ("x_mm,y_mm,u_px,v_px,set\n", "no data rows"),
    ("x_mm,y_mm,u_px,v_px,set\n1,2,nan,4,cal\n", "row 2, column u_px"),
    ("x_mm,y_mm,u_px,v_px,set\n1,2,abc,4,cal\n", "row 2, column u_px: 'abc'"),
    ("x_mm,y_mm,u_px,v_px,set\n1,2,3,4,train\n", "set='train'; allowed: 'cal' or 'ver'"),
    ("x_mm,y_mm,u_px,v_px,set\n" + "".join(f"{i},{i},{10 * i},{10 * i + 1},cal\n" for i in range(20)), "collinear"),
    ("x_mm,y_mm,u_px,v_px,set\n1,2,10,20,cal\n3,1,40,10,cal\n2,5,20,50,cal\n", "points"),
])
def test_fit_bad_input_exit_2(tmp_path, capsys, content, message):
    samples = tmp_path / "s.csv"
    samples.write_text(content)
    out = tmp_path / "cal.json"
    assert run_cli("fit", "virtual-grid", "--samples", samples, "--out", out) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()  # nothing half-written


def test_run_bad_input_exit_2(tmp_path, capsys, small_run):
    bad_cell = tmp_path / "bad.yaml"
    bad_cell.write_text(MICROCELL.read_text().replace("repeatability_xy_um: 1.7", "repeatability_xy_um: -1")
                        .replace("cam2: {backend: sim}", "cam2: {backend: sim, colour: red}"))
    assert run_cli("run", "virtual-grid", "--config", bad_cell, "--out", tmp_path / "x", "--quiet") == 2
    err = capsys.readouterr().err
    assert "sim.robot.repeatability_xy_um" in err and "greater than or equal to 0" in err

    bad_cell.write_text(MICROCELL.read_text().replace("cam2: {backend: sim}", "cam2: {backend: sim, colour: red}"))
    assert run_cli("check", "--config", bad_cell) == 2
    assert "cameras.cam2.colour: unknown key" in capsys.readouterr().err

    bad_cell.write_text(MICROCELL.read_text().replace("backend: sim\n  limits", "backend: kuka\n  limits"))
    assert run_cli("check", "--config", bad_cell) == 2
    assert "arm.backend: unknown arm backend 'kuka'; allowed: abb, sim, sim-irb120, sim-ur5e, sim-vr, ur" in capsys.readouterr().err

    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "y", "--quiet", "--param", "rows=1") == 2
    assert "rows" in capsys.readouterr().err
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "y", "--quiet", "--param", "bogus=1") == 2
    assert "bogus: unknown parameter" in capsys.readouterr().err
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "y", "--quiet", "--param", "rows") == 2
    assert "expected KEY=VALUE" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()
    assert run_cli("run", "virtual-grid", "--config", tmp_path / "missing.yaml", "--out", tmp_path / "y") == 2
    assert "cannot read the cell file" in capsys.readouterr().err
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", small_run, "--quiet") == 2
    assert "already holds a run" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        run_cli("run", "no-such-routine", "--config", MICROCELL, "--out", tmp_path / "z")
    assert exc.value.code == 2


def test_map_bad_input_exit_2(tmp_path, capsys):
    not_cal = tmp_path / "x.json"
    not_cal.write_text('{"hello": 1}')
    px = tmp_path / "px.csv"
    px.write_text("u_px,v_px\n1,2\n")
    assert run_cli("map", not_cal, "--pixels", px, "--out", tmp_path / "o.csv") == 2
    assert "no planar calibration" in capsys.readouterr().err
    not_cal.write_text("{broken")
    assert run_cli("map", not_cal, "--pixels", px, "--out", tmp_path / "o.csv") == 2
    assert "not JSON" in capsys.readouterr().err


def test_save_images_keeps_every_frame(tmp_path):
    import cv2

    out = tmp_path / "imgs"
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", out, "--quiet", "--save-images",
                   "--param", "rows=3", "--param", "cols=3", "--param", "n_verify=0") == 0
    rows = list(csv.DictReader(open(out / "samples.csv")))
    assert all(r["image"] for r in rows)
    image = cv2.imread(str(out / rows[0]["image"]), cv2.IMREAD_UNCHANGED)
    assert image.shape == (2050, 2448)


def test_device_fault_keeps_samples_exit_1_then_resume(tmp_path, capsys):
    """The arm's link drops mid-run: exit 1 naming the fault, every sample kept; resumed once the cell is
    fixed, the run completes without repeating a step."""
    broken = tmp_path / "broken.yaml"
    broken.write_text(MICROCELL.read_text().replace("  supply: {", "  faults: {arm_drop_after_moves: 10}\n  supply: {"))
    out = tmp_path / "run"
    args = ["run", "virtual-grid", "--out", out, "--quiet", "--param", "rows=3", "--param", "cols=4",
            "--param", "n_verify=0", "--param", "passes=1", "--param", "target_um=0.001"]  # all 12: none skipped
    assert run_cli(*args, "--config", broken) == 1
    assert "ConnectionLost" in capsys.readouterr().err
    kept = list(csv.DictReader(open(out / "samples.csv")))
    assert len(kept) == 10
    assert run_cli(*args, "--config", MICROCELL, "--resume") == 0  # the link is back (the sim: no fault knob)
    rows = list(csv.DictReader(open(out / "samples.csv")))
    assert [int(r["step"]) for r in rows] == list(range(12))  # nothing lost, nothing repeated


def test_locate_a_pixel_with_the_active_calibration(small_run, tmp_path, capsys, isolated_store):
    """`cellctl locate`: the active camera calibration answers where a pixel is in robot coordinates."""
    from cellctl.stores.calibrations import CalibrationStore

    CalibrationStore(isolated_store).save("cam1", json.loads((small_run / "result.json").read_text()), "", small_run)
    rows = list(csv.DictReader(open(small_run / "samples.csv")))
    r = rows[0]
    assert run_cli("locate", "--config", MICROCELL, "--camera", "cam1", "--pixel", r["u_px"], r["v_px"]) == 0
    out = capsys.readouterr().out
    x = float(out.split("x_mm=")[1].split()[0])
    y = float(out.split("y_mm=")[1].split()[0])
    assert abs(x - float(r["x_mm"])) < 0.02 and abs(y - float(r["y_mm"])) < 0.02
    assert run_cli("locate", "--config", MICROCELL, "--camera", "cam3", "--pixel", 1, 2) == 2
    assert "no active calibration of 'cam3'" in capsys.readouterr().err


def test_calibrations_listed_activated_and_exported_in_process(small_run, tmp_path, capsys, isolated_store):
    """Without a daemon, `cellctl calibrations` (list, activate, export) works on the cell file's store,
    through the same service verbs as the daemon's; the OpenCV export reads back with cv2.FileStorage."""
    import cv2

    from cellctl.stores.calibrations import CalibrationStore

    store = CalibrationStore(isolated_store)
    result = json.loads((small_run / "result.json").read_text())
    first, second = (store.save("cam1", result, "", small_run) for _ in range(2))
    assert run_cli("calibrations", "--config", MICROCELL) == 0
    listed = capsys.readouterr().out
    assert f"{first.id:4d}  cam1" in listed and "ACTIVE" in listed.splitlines()[1]
    assert run_cli("calibrations", "--config", MICROCELL, "activate", first.id) == 0
    assert f"calibration {first.id} (version 1 of cam1) is now active" in capsys.readouterr().out
    assert store.active("cam1").id == first.id
    assert run_cli("calibrations", "--config", MICROCELL, "export", second.id, "--format", "json") == 0
    exported = json.loads(capsys.readouterr().out)
    assert (exported["id"], exported["version"], exported["model"]) == (second.id, 2, result["model"])
    out = tmp_path / "cal.yaml"
    assert run_cli("calibrations", "--config", MICROCELL, "export", second.id, "--format", "opencv",
                   "--out", out) == 0
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert fs.getNode("target").string() == "cam1" and int(fs.getNode("version").real()) == 2
    assert list(fs.getNode("model").getNode("map").getNode("image_size").mat().ravel()) == \
        result["model"]["map"]["image_size"]
    fs.release()
    assert run_cli("calibrations", "--config", MICROCELL, "export", 999) == 2
    assert "no calibration with id 999" in capsys.readouterr().err
    assert run_cli("status", "--config", MICROCELL) == 2  # the live cell's verbs need the daemon, and say so
    assert "no daemon" in capsys.readouterr().err


def test_a_parameter_given_for_an_area_overrides_the_area_section():
    """`hybrid` on area2 with n_verify given: the caller's value wins over the cell file's hybrid.area2 (a
    repeated key used to raise TypeError instead of being merged)."""
    from calibration.routines import routine_class

    from cellctl.config import load_cell_file
    from cellctl.core.runs import routine_params

    config, _ = load_cell_file(MICROCELL)
    params = routine_params(routine_class("hybrid")(), config, {"area": "area2", "n_verify": 3})
    assert (params.area, params.n_verify, params.n_register) == ("area2", 3, 4)


def test_an_in_process_run_is_refused_below_the_store_floor_before_anything_moves(tmp_path, capsys):
    cell = tmp_path / "cell.yaml"
    cell.write_text(MICROCELL.read_text() + "\nstore: {min_free_mb: 10000000}\n")
    assert run_cli("run", "virtual-grid", "--config", cell, "--out", tmp_path / "run", "--quiet", *SMALL) == 2
    err = capsys.readouterr().err
    assert "a new run is refused" in err and "below the 1e+07 MB the cell file asks to keep free" in err, err
    assert "store.min_free_mb" in err and not (tmp_path / "run").exists()


def test_an_in_process_run_refuses_a_store_that_fails_its_check(tmp_path, capsys, isolated_store):
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "first", "--quiet", *SMALL) == 0
    db = isolated_store / "calibrations.sqlite"
    for wal in (db.with_name(db.name + "-wal"), db.with_name(db.name + "-shm")):
        wal.unlink(missing_ok=True)
    db.write_bytes(b"\xa5\x5a" * 2048)  # torn to garbage
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "second", "--quiet", *SMALL) == 2
    err = capsys.readouterr().err
    assert f"{isolated_store / 'calibrations.sqlite'} fails SQLite's integrity check" in err, err
    assert "Nothing is served or run from it" in err and "cellctl fleet restore" in err  # no backup: the plant's
    assert not (tmp_path / "second").exists()
