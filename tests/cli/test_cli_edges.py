"""The CLI's rough edges: files that are not UTF-8, a cell file's routine sections, finding the token and the store,
options after a sub-verb, listings that fit 100 columns and are never cut, and a start-up that imports no numerics."""

import io
import json
import os
import subprocess
import sys

import pytest

from cellctl.cli import build_parser, main
from cellctl.cli.display import WIDTH, ProgressBar, print_audit, print_health, print_jobs

from tests.conftest import MICROCELL


def cli(*args):
    return main([str(a) for a in args])


def plain_env(**extra) -> dict:
    """This environment without the CELLCTL_ variables a developer may have set (a daemon's URL, a store)."""
    return {**{k: v for k, v in os.environ.items() if not k.startswith("CELLCTL_")}, **extra}


def one_clear_line(err: str) -> str:
    """The error: one line, no traceback."""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# -- files that are not UTF-8 ------------------------------------------------------------------------


def test_a_latin1_cell_file_is_one_clear_error(tmp_path, capsys):
    cell = tmp_path / "latin1.yaml"
    text = MICROCELL.read_text().replace("cell:", "# caméra 1 au-dessus de la zone\ncell:", 1)
    cell.write_bytes(text.encode("latin-1"))
    assert cli("check", "--config", cell) == 2
    line = one_clear_line(capsys.readouterr().err)
    assert str(cell) in line and "not UTF-8: byte 0xe9 at line" in line and "save the cell file as UTF-8" in line


def test_a_csv_that_is_not_utf8_is_one_clear_error(tmp_path, capsys):
    samples = tmp_path / "s.csv"
    samples.write_bytes("x_mm,y_mm,u_px,v_px,set\n1,2,3,4,cal\n# relevé\n".encode("latin-1"))
    out = tmp_path / "cal.json"
    assert cli("fit", "virtual-grid", "--samples", samples, "--out", out) == 2
    line = one_clear_line(capsys.readouterr().err)
    assert f"{samples}: not UTF-8: byte 0xe9 at line 3, column 8 (offset 43)" in line
    assert "save the CSV as UTF-8" in line
    assert not out.exists()


def test_a_utf8_bom_and_crlf_csv_is_read():
    from cellctl.textfile import decode_utf8

    assert decode_utf8(b"\xef\xbb\xbfu_px,v_px\r\n1,2\r\n") == "u_px,v_px\n1,2\n"


# -- the cell file's routine sections ----------------------------------------------------------------


def _cell_with_routines(tmp_path, routines: str):
    cell = tmp_path / "cell.yaml"
    cell.write_text(f"extends: {MICROCELL}\nroutines:\n{routines}")
    return cell


@pytest.mark.parametrize("routines, expected", [
    ("  virtual-grid: {rwos: 8}\n", ["routines.virtual-grid.rwos: unknown parameter of virtual-grid (got 8); "
                                     "allowed: ", "rows, cols"]),
    ("  virtual-grid: {rows: eight}\n", ["routines.virtual-grid.rows: Input should be a valid integer", "'eight'"]),
    ("  virtual-grdi: {rows: 8}\n", ["routines.virtual-grdi: unknown routine 'virtual-grdi'; allowed: arm-kinematics, calibration-check, "]),
    ("  hybrid.area9: {n_verify: 3}\n", ["routines.hybrid.area9: 'area9' is not an area of this cell (defined: "
                                         "area1, area2, board)"]),
    ("  hybrid.area2: {n_verify: -3}\n", ["routines.hybrid.area2.n_verify: Input should be greater than"]),
])
def test_check_validates_each_routine_section(tmp_path, capsys, routines, expected):
    assert cli("check", "--config", _cell_with_routines(tmp_path, routines)) == 2
    err = capsys.readouterr().err
    assert all(part in err for part in expected), err
    assert "Traceback" not in err


def test_a_routine_section_is_checked_without_the_other_routines(tmp_path, capsys):
    """A section only sets what differs (a run gives the rest); a valid one passes, and `check` lists them."""
    cell = _cell_with_routines(tmp_path, "  hybrid.area2: {n_verify: 3}\n  repeatability: {}\n")
    assert cli("check", "--config", cell) == 0
    assert "routines: virtual-grid, hybrid, hybrid.area2" in capsys.readouterr().out


def test_a_run_names_the_cell_file_section_a_bad_parameter_came_from(tmp_path):
    """A cell file loaded without its routine sections checked (the token, the store): a run still refuses the
    bad value, and says it came from the cell file, not from --param."""
    from calibration.routines import routine_class

    from cellctl.config import load_cell_file
    from cellctl.core.runs import ParamError, routine_params

    config, _ = load_cell_file(_cell_with_routines(tmp_path, "  virtual-grid: {rwos: 8, rows: 4}\n"), routines=False)
    with pytest.raises(ParamError) as exc:
        routine_params(routine_class("virtual-grid")(), config, {"cols": "x"})
    message = str(exc.value)
    assert "rwos: unknown parameter (got 8, from the cell file's routines.virtual-grid)" in message
    assert "cols: Input should be a valid integer, unable to parse string as an integer (got 'x')\n" in message


def test_the_routine_table_names_each_routine_by_its_own_name():
    from calibration.routines import all_routines, routine_names

    routines = all_routines()
    assert list(routines) == list(routine_names()) and all(cls.name == name for name, cls in routines.items())


# -- finding the token and the store; options after a sub-verb -------------------------------------------


def test_token_reads_the_store_of_CELLCTL_STORE(isolated_store, capsys):
    from cellctl.service.auth import load_or_create_token

    isolated_store.mkdir(parents=True, exist_ok=True)
    token = load_or_create_token(isolated_store)
    assert cli("token") == 0
    assert capsys.readouterr().out.strip() == token


def test_connection_options_work_after_the_sub_verb():
    parse = build_parser().parse_args
    after = parse(["calibrations", "activate", "7", "--config", "c.yaml", "--url", "http://x", "--token", "t"])
    assert (after.action, after.id, after.config, after.url, after.token) == ("activate", 7, "c.yaml", "http://x", "t")
    before = parse(["calibrations", "--config", "c.yaml", "export", "7", "--format", "opencv"])
    assert (before.action, before.config, before.url) == ("export", "c.yaml", None)  # not reset by the sub-verb


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("edges") / "run"
    assert cli("run", "virtual-grid", "--config", MICROCELL, "--out", out, "--seed", 3, "--quiet",
               "--param", "rows=3", "--param", "cols=3", "--param", "n_verify=3") == 0
    return out


def test_calibrations_activate_with_the_config_after_it(small_run, isolated_store, capsys):
    from cellctl.stores.calibrations import CalibrationStore

    result = json.loads((small_run / "result.json").read_text())
    first, _ = (CalibrationStore(isolated_store).save("cam1", result, "", small_run) for _ in range(2))
    assert cli("calibrations", "activate", first.id, "--config", MICROCELL) == 0
    assert f"calibration {first.id} (version 1 of cam1) is now active" in capsys.readouterr().out
    assert cli("calibrations", "--json", "--config", MICROCELL) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [c["active"] for c in listed] == [True, False]


# -- terminal output ----------------------------------------------------------------------------------


def _fits(out: str) -> list[str]:
    lines = out.splitlines()
    assert lines and all(len(line) <= WIDTH for line in lines), "\n".join(lines)
    assert "…" not in out
    return lines


def _job(id_, routine, state, progress, seed=None, reason="finished"):
    return {"id": id_, "routine": routine, "state": state, "seed": seed, "updated": "2026-12-03T08:00:19.689Z",
            "reason": reason, "progress": progress}


def test_jobs_fit_100_columns_show_no_seed_None_and_count_a_sequence_alike_running_and_done(capsys):
    print_jobs([
        _job(3, "calibrate-cell", "running", {"routine": "calibrate-cell", "item": "virtual-grid", "step": 301,
                                               "total": 600}, reason="started"),
        _job(4, "calibrate-cell", "done", {"routine": "calibrate-cell", "item": "onboard-camera", "step": 29,
                                            "total": 29}),
        _job(5, "virtual-grid", "aborted", {"item": None, "step": 12, "total": 38}, seed=3,
             reason="aborted by operator@cell-pc (console); the arm is stopped and the samples so far are kept: "
                    "resume is not possible, submit it again"),
        _job(6, "calibration-check", "queued", None, reason="submitted"),
    ])
    lines = _fits(capsys.readouterr().out)
    assert "None" not in "\n".join(lines)
    running, done = lines[1], lines[2]
    assert "routine 1/4: step 301/600" in running and "routine 4/4: step 29/29" in done
    assert "12/38" in lines[3] and "submit it again" in "\n".join(lines[4:])


def test_health_and_logs_fit_100_columns(capsys):
    check = {"created": "2026-12-03T08:00:00+0000", "check": 12, "calibration_id": 41, "drifted": True,
             "p_value": 5.55e-121, "drift": {"dx_um": 5.23, "dx_std_um": 0.96, "dy_um": -22.1, "dy_std_um": 0.96,
                                             "rotation_urad": 45826.0, "scale_ppm": -3165.0},
             "action": "recalibrate: the drift does not fit its model (rotation and scale); run virtual-grid "
                       "on area1, then check again"}
    print_health({"virtual-grid-area2-cam": {"active": {"id": 41, "version": 12, "routine": "virtual-grid-area2"},
                                             "verdict": "drift", "last_check": check, "history": [check, check]}},
                 history=True)
    print_audit([{"at": "2026-12-03T07:59:57.435Z", "client": "operator-with-a-long-name@cell-pc-07.plant.example",
                  "action": "POST /calibrations/41/activate", "target": "calibration 41", "outcome": "refused 409",
                  "detail": json.dumps({"routine": "virtual-grid", "params": {f"p{i}": i for i in range(20)}})}])
    out = capsys.readouterr().out
    _fits(out)
    assert "p19" in out and "then check again" in out and "-3165" in out  # wrapped, not cut


def test_a_sequence_progress_bar_fits_a_100_column_terminal():
    """The longest routine of the longest sequence, with big figures, on one line of a 100-column terminal."""
    from rich.console import Console

    terminal = Console(force_terminal=True, width=WIDTH, file=io.StringIO())
    with ProgressBar("job 7", console=terminal) as bar:
        bar.on_event({"routine": "seed-001", "item": "virtual-grid-area2", "step": 152, "total": 600,
                      "cell_time_s": 1234.4, "eta_cell_s": 43210.0, "residual_um": 123.45})
        shown = Console(width=WIDTH, record=True, file=io.StringIO())
        shown.print(bar.bar.make_tasks_table(bar.bar.tasks))
    line = shown.export_text().rstrip("\n")
    assert "\n" not in line and "…" not in line and len(line) <= WIDTH, line
    assert "virtual-grid-area2 (routine 5/7)" in line and "152/600 steps" in line and "residual 123.45 µm" in line


def test_piped_output_is_laid_out_for_100_columns_never_cut(tmp_path):
    """`cellctl check` and an in-process run's progress bar through a pipe (rich would assume 80 columns)."""
    proc = subprocess.run([sys.executable, "-m", "cellctl.cli", "check", "--config", str(MICROCELL)],
                          capture_output=True, text=True, env=plain_env(COLUMNS="60"))
    assert proc.returncode == 0, proc.stderr
    assert "pick-place, calibration-check" in proc.stdout
    _fits(proc.stdout)
    proc = subprocess.run([sys.executable, "-m", "cellctl.cli", "run", "virtual-grid", "--config", str(MICROCELL),
                           "--out", str(tmp_path / "run"), "--param", "rows=3", "--param", "cols=3",
                           "--param", "n_verify=0"], capture_output=True, text=True,
                          env=plain_env(CELLCTL_STORE=str(tmp_path / "store")))
    assert proc.returncode == 0, proc.stderr
    bar = [line for line in proc.stderr.splitlines() if "steps" in line]
    assert bar and "residual" in bar[-1] and "…" not in proc.stderr, proc.stderr


# -- start-up: no numerics to parse the command line -----------------------------------------------------

HEAVY = ("numpy", "scipy", "cv2", "pydantic", "fastapi", "matplotlib", "pinocchio", "rich", "psycopg")


@pytest.mark.parametrize("argv, allowed", [
    (["--help"], ()),
    (["run", "--help"], ()),
    # nothing listens: exit 1, after the request was tried; httpx imports rich itself (its own CLI)
    (["status", "--url", "http://127.0.0.1:1"], ("rich",)),
])
def test_the_command_line_starts_without_the_numerics(argv, allowed):
    """What `cellctl --help` and `cellctl status` import (their start-up time: tools/bench_startup.py)."""
    code = ("import sys\nfrom cellctl.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "print(' '.join(sorted({m.partition('.')[0] for m in sys.modules})))")
    proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, env=plain_env())
    loaded = set(proc.stdout.strip().splitlines()[-1].split())
    assert "cellctl" in loaded
    assert not loaded & (set(HEAVY) - set(allowed)), sorted(loaded & set(HEAVY))
