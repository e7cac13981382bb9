"""`cellctl commission`: the device self-test on the simulated cells, in this process (no daemon).

Each fault knob that produces a finding (the simulated worlds' SimFaults, the protocol simulators' options, a cell
file's wrong address) is run, and the finding must name the right fix; a clean cell gives no finding. The motion
runs only when confirmed (--move): without it the check is skipped, not failed.
"""

from __future__ import annotations

import json

import pytest
import yaml

from cellctl.cli import main
from cellctl.stores.jobs import DB_FILE, JobStore

from tests.conftest import ROOT
from tests.support.cells import write_abb_cell_file
from tests.support.ports import free_port

UR_HOST = "127.0.0.57"  # the UR simulator's ports are fixed: a loopback address of this module's own


def cell_file(folder, base: str = "sim-microcell.yaml", **changes) -> str:
    """config/`base` with `changes` merged over it (as `extends:` merges), its store in `folder`."""
    path = folder / "cell.yaml"
    path.write_text(f"extends: {ROOT / 'config' / base}\n" + yaml.safe_dump({"store_dir": str(folder / "store"),
                                                                               **changes}))
    return str(path)


def commission(capsys, config: str, *args) -> tuple[int, dict]:
    code = main(["commission", "--config", str(config), "--json", *args])
    return code, json.loads(capsys.readouterr().out)


def rows(answer: dict, device: str | None = None, check: str | None = None) -> list[dict]:
    return [c for c in answer["checks"] if device in (None, c["device"]) and check in (None, c["check"])]


def the_row(answer: dict, device: str, check: str) -> dict:
    found = rows(answer, device, check)
    assert len(found) == 1, (device, check, answer["checks"])
    return found[0]


def problems(answer: dict) -> list[dict]:
    return [c for c in answer["checks"] if c["result"] == "problem"]


# -- a clean cell ------------------------------------------------------------------------------------------------


def test_a_clean_micro_cell_gives_no_finding_and_the_arm_moves_5_mm_seen_by_the_camera_on_it(tmp_path, capsys):
    code, answer = commission(capsys, cell_file(tmp_path), "--move")
    assert problems(answer) == [] and answer["problems"] == 0 and code == 0
    assert answer["moved"] is True
    devices = [c["device"] for c in answer["checks"]]
    assert devices == sorted(devices, key=["arm", "gripper", "cam1", "cam2", "cam3"].index)  # device by device
    for device in ("arm", "gripper", "cam1", "cam2", "cam3"):
        assert the_row(answer, device, "link")["result"] == "ok"
        assert the_row(answer, device, "readings")["result"] == "ok"
    assert "reported 5.000 mm" in the_row(answer, "arm", "motion")["figure"]
    seen = the_row(answer, "cam3", "motion seen")  # cam3 rides the arm: the supply's sphere moves in its view
    assert seen["result"] == "ok" and seen["figure"].startswith(("4.9", "5.0", "5.1"))
    assert the_row(answer, "gripper", "grip with nothing held")["result"] == "ok"
    assert the_row(answer, "cam3", "focus")["result"] == "ok"
    for camera in ("cam1", "cam2", "cam3"):
        assert the_row(answer, camera, "exposure")["result"] == "ok"


def test_without_a_confirmation_the_motion_is_skipped_not_failed(tmp_path, capsys):
    code, answer = commission(capsys, cell_file(tmp_path))  # stdin is no terminal here: nobody to ask
    motion = the_row(answer, "arm", "motion")
    assert motion["result"] == "skipped" and "--move" in motion["finding"]
    assert code == 0 and answer["moved"] is False and not rows(answer, check="motion seen")


def test_the_table_names_each_check_and_the_exit_status_says_a_problem_was_found(tmp_path, capsys):
    config = cell_file(tmp_path, sim={"faults": {"gripper_no_air": True}})
    assert main(["commission", "--config", config]) == 1
    out = capsys.readouterr().out
    for word in ("device", "check", "result", "figure", "finding / fix", "grip with nothing held", "problem",
                 "1 problem found"):
        assert word in out, word


# -- each fault knob, and the fix its finding names ----------------------------------------------------------

HOME_AT_CAM1 = {"motion": {"home_mm": [40.0, 30.0, 0.0]}}  # the nozzle in cam1's focus (area1), from below

KNOBS = {
    # the arm moves 94 % of what it is told and reports what it was told: the camera that sees it says so
    "arm units, seen by cam1": (dict(HOME_AT_CAM1, faults={"arm_motion_scale": 0.94}), "cam1", "motion seen",
                                ["arm: moved 5.00 mm, cam1 saw 4.7", "check cam1's um_per_px", "the arm's units"]),
    "arm units, seen by cam3": ({"faults": {"arm_motion_scale": 0.94}}, "cam3", "motion seen",
                                ["arm: moved 5.00 mm, cam3 saw 4.7", "the arm's units"]),
    "a camera's scale": ({"faults": {"camera_scale": {"cam3": 0.9}}}, "cam3", "motion seen",
                         ["cam3 saw 4.5", "check cam3's um_per_px"]),
    "out of focus": ({"faults": {"camera_blur_px": {"cam3": 8.0}}}, "cam3", "focus",
                     ["edges blurred over", "focus cam3's lens"]),
    "saturated": ({"faults": {"camera_gain": {"cam2": 14.0}}}, "cam2", "exposure",
                  ["of pixels saturated", "lower cameras.cam2.exposure_s from 0.01 to about 0.005"]),
    "dark": ({"faults": {"camera_gain": {"cam1": 0.1}}}, "cam1", "exposure",
             ["the image is dark", "raise cameras.cam1.exposure_s from 0.01"]),
    "nozzle blocked": ({"faults": {"gripper_blocked": True}}, "gripper", "grip with nothing held",
                       ["detects an object with nothing held", "the nozzle is blocked", "clean the nozzle"]),
    "no air": ({"faults": {"gripper_no_air": True}}, "gripper", "grip with nothing held",
               ["the vacuum stayed at 0.0 kPa", "check the air supply"]),
    "no frames": ({"faults": {"camera_timeout_after_captures": 1}}, "cam2", "readings",
                  ["CaptureTimeout", "check the trigger and cable"]),
    "a protective stop on the way back": ({"faults": {"protective_stop_after_moves": 1}}, "arm", "motion",
                                          ["ProtectiveStop", "clear it on the controller"]),
    "the arm outside its box": ({"motion": {"home_mm": [40.0, 30.0, 45.0]}}, "arm", "readings",
                                ["z_mm=45.000 is outside the workspace box", "check arm.limits"]),
}


@pytest.mark.parametrize("knob", list(KNOBS))
def test_each_fault_knob_gives_its_finding_naming_the_fix(tmp_path, capsys, knob):
    sim, device, check, said = KNOBS[knob]
    code, answer = commission(capsys, cell_file(tmp_path, sim=sim), "--move")
    row = the_row(answer, device, check)
    assert row["result"] == "problem", row
    for words in said:
        assert words in row["finding"], (words, row)
    assert code == 1
    assert f"{device}: {row['finding']}" in answer["findings"]


def test_the_arm_outside_its_box_is_not_moved(tmp_path, capsys):
    _, answer = commission(capsys, cell_file(tmp_path, sim={"motion": {"home_mm": [40.0, 30.0, 45.0]}}), "--move")
    motion = the_row(answer, "arm", "motion")
    assert motion["result"] == "problem" and "stays in the workspace box" in motion["finding"]
    assert "z_mm=45.000 is outside the workspace box [-5.0, 40.0] (arm.limits)): jog the arm inwards" in motion["finding"]


# -- one device, and one that is not there -------------------------------------------------------------------


def test_one_device_only(tmp_path, capsys):
    code, answer = commission(capsys, cell_file(tmp_path), "--device", "cam2")
    assert {c["device"] for c in answer["checks"]} == {"cam2", "arm"}  # the arm's (skipped) motion, cam2 watches
    assert [c["check"] for c in rows(answer, "cam2")] == ["link", "readings", "focus", "exposure"]
    code, answer = commission(capsys, cell_file(tmp_path), "--device", "gripper")
    assert {c["device"] for c in answer["checks"]} == {"gripper"} and code == 0


def test_an_unknown_device_is_an_error_naming_the_devices(tmp_path, capsys):
    assert main(["commission", "--config", cell_file(tmp_path), "--device", "cam9"]) == 2
    err = capsys.readouterr().err
    assert "'cam9' is not a device" in err and "arm, gripper, cam1, cam2, cam3" in err


def test_the_self_test_is_audited_in_the_store(tmp_path, capsys):
    commission(capsys, cell_file(tmp_path), "--move")
    store = JobStore(tmp_path / "store" / DB_FILE)
    try:
        entries = [e for e in store.audit_log() if e["action"] == "cli commission (in-process)"]
    finally:
        store.close()
    assert len(entries) == 1 and entries[0]["outcome"] == "ok"
    assert json.loads(entries[0]["detail"])["move"] is True and '"move_mm": 5.0' in entries[0]["detail"]


# -- through the protocol simulators: the real ABB, UR, VGC10 and EPick drivers ------------------------------


def ur_cell(folder, **changes) -> str:
    servers = {"servers": [{"protocol": "ur", "host": UR_HOST},
                           {"protocol": "epick", "host": UR_HOST, "port": free_port(UR_HOST),
                            **changes.pop("epick", {})}]}
    port = servers["servers"][1]["port"]
    return cell_file(folder, "sim-microcell-ur.yaml", sim=servers,
                     arm={"host": changes.pop("arm_host", UR_HOST)}, gripper={"host": UR_HOST, "port": port})


def test_the_abb_and_vgc10_cell_through_its_simulators_is_clean(tmp_path, capsys):
    code, answer = commission(capsys, write_abb_cell_file(tmp_path, extra=f"store_dir: {tmp_path / 'store'}"),
                              "--move")
    assert problems(answer) == [] and code == 0
    link = the_row(answer, "arm", "link")["figure"]
    assert "software" in link and "pose read" in link  # the controller's robot info, and its latency
    assert "reported 5.000 mm" in the_row(answer, "arm", "motion")["figure"]


def test_an_abb_arm_on_a_wrong_port_is_a_finding_not_a_traceback(tmp_path, capsys):
    config = write_abb_cell_file(tmp_path, extra=f"store_dir: {tmp_path / 'store'}")
    wrong = free_port()  # the arm's motion port is not its simulator's: nothing listens there
    kept = [line for line in config.read_text().splitlines() if not line.startswith("arm:")]
    config.write_text("\n".join(kept) + f"\narm: {{motion_port: {wrong}, logger_port: {wrong + 1}}}\n")
    code, answer = commission(capsys, str(config), "--move")
    link = the_row(answer, "arm", "link")
    assert link["result"] == "problem" and code == 1
    assert "no answer from the ABB controller" in link["finding"]
    assert f"motion_port {wrong}" in link["finding"] and "check host, motion_port and logger_port" in link["finding"]
    for check in ("readings", "motion"):
        assert the_row(answer, "arm", check)["result"] == "skipped"
    assert the_row(answer, "gripper", "link")["result"] == "ok"  # the others are still checked


def test_a_wrong_vgc10_unit_id_names_the_one_that_answers(tmp_path, capsys):
    config = write_abb_cell_file(tmp_path, extra=f"store_dir: {tmp_path / 'store'}")
    config.write_text(config.read_text().replace("gripper: {port:", "gripper: {device_id: 12, port:"))
    code, answer = commission(capsys, config, "--device", "gripper")
    link = the_row(answer, "gripper", "link")
    assert link["result"] == "problem" and code == 1
    assert link["finding"].startswith("no answer from device 12 on 127.0.0.1:")
    assert "(Modbus TCP): check device_id (the gripper answers as 65: set device_id: 65)" in link["finding"]


def test_the_ur_and_epick_cell_through_its_simulators_is_clean(tmp_path, capsys):
    code, answer = commission(capsys, ur_cell(tmp_path), "--move")
    assert problems(answer) == [] and code == 0
    assert "robot mode" in the_row(answer, "arm", "link")["figure"]
    assert "reported 5.000 mm" in the_row(answer, "arm", "motion")["figure"]


def test_a_wrong_ur_address_and_a_wrong_epick_device_id_name_their_fixes(tmp_path, capsys):
    config = ur_cell(tmp_path, arm_host="127.0.0.58", epick={"options": {"device_id": 1}})
    code, answer = commission(capsys, config, "--move")
    arm = the_row(answer, "arm", "link")
    assert arm["result"] == "problem" and "no answer from the UR controller (host 127.0.0.58)" in arm["finding"]
    gripper = the_row(answer, "gripper", "link")
    assert gripper["result"] == "problem" and code == 1
    assert gripper["finding"].startswith(f"no answer from device 9 on {UR_HOST}:")
    assert "check device_id (the gripper answers as 1: set device_id: 1)" in gripper["finding"]
    assert "device 1 answered" in gripper["finding"]


def test_a_slow_gripper_link_is_a_finding(tmp_path, capsys):
    config = ur_cell(tmp_path, epick={"options": {"reply_delay_s": 0.12}})
    code, answer = commission(capsys, config, "--device", "gripper")
    link = the_row(answer, "gripper", "link")
    assert link["result"] == "problem" and "the link is slow" in link["finding"] and code == 1


# -- six-axis cells ----------------------------------------------------------------------------------------------


def test_a_clean_six_axis_cell_gives_no_finding_and_its_wrist_camera_sees_the_move(tmp_path, capsys):
    code, answer = commission(capsys, cell_file(tmp_path, "sim-ur5e-handeye.yaml"), "--move")
    assert problems(answer) == [] and code == 0
    seen = the_row(answer, "wrist", "motion seen")  # no scale without a calibration: the pixels it saw
    assert seen["result"] == "info" and " px (" in seen["figure"] and "calibrate it" in seen["finding"]
    assert the_row(answer, "wrist", "focus")["result"] == the_row(answer, "top", "focus")["result"] == "ok"


@pytest.mark.parametrize("knob, device, check, said", [
    ({"camera_blur_px": {"wrist": 9.0}}, "wrist", "focus", "focus wrist's lens"),
    ({"camera_gain": {"top": 6.0}}, "top", "exposure", "lower cameras.top.exposure_s"),
    ({"gripper_blocked": True}, "gripper", "grip with nothing held", "the nozzle is blocked"),
])
def test_six_axis_fault_knobs_give_their_findings(tmp_path, capsys, knob, device, check, said):
    code, answer = commission(capsys, cell_file(tmp_path, "sim-ur5e-handeye.yaml", sim={"faults": knob}))
    row = the_row(answer, device, check)
    assert row["result"] == "problem" and said in row["finding"] and code == 1


def test_the_irb120_cell_is_clean(tmp_path, capsys):
    # the arm starts with the fixture's plate facing up in the cameras' view (as an operator would jog it)
    code, answer = commission(capsys, cell_file(tmp_path, "sim-irb120-csm.yaml",
                                                sim={"robot": {"home_deg": [0, 10, 10, 0, 70, 0]}}), "--move")
    assert problems(answer) == [] and code == 0
    assert "reported 5.000 mm" in the_row(answer, "arm", "motion")["figure"]
    for camera in ("cam1", "cam2"):  # they follow the fixture's white mark (no scale without a calibration)
        seen = the_row(answer, camera, "motion seen")
        assert seen["result"] == "info" and " px (" in seen["figure"] and "tracked" in seen["figure"], seen


def test_a_calibrated_camera_measures_the_move_with_its_active_calibration(tmp_path, capsys):
    config = cell_file(tmp_path, sim=HOME_AT_CAM1)
    assert main(["run", "virtual-grid", "--config", config, "--out", str(tmp_path / "run"), "--quiet",
                 "--param", "rows=4", "--param", "cols=4", "--param", "n_verify=6"]) == 0
    capsys.readouterr()
    code, answer = commission(capsys, config, "--move")
    seen = the_row(answer, "cam1", "motion seen")  # the nozzle, seen from below in focus
    assert seen["result"] == "ok" and "scale: its active calibration" in seen["figure"], seen
    assert seen["figure"].startswith(("4.9", "5.0")) and code == 0


@pytest.mark.parametrize("said, moved", [("y", True), ("", False)])
def test_on_a_terminal_the_move_is_asked_first(tmp_path, said, moved):
    """y moves the arm; anything else (Enter) skips the motion check."""
    import os
    import pty
    import subprocess
    import sys

    config = cell_file(tmp_path)
    leader, follower = pty.openpty()
    try:
        proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "commission", "--config", config, "--device",
                                 "cam3", "--json"], stdin=follower, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                cwd=ROOT, env={**os.environ, "CELLCTL_STORE": str(tmp_path / "store")})
        os.write(leader, f"{said}\n".encode())
        out, err = proc.communicate(timeout=120)
    finally:
        os.close(leader)
        os.close(follower)
    assert b"moves the arm 5 mm and back" in err and b"[y/N]" in err
    answer = json.loads(out)
    assert answer["moved"] is moved
    assert the_row(answer, "arm", "motion")["result"] == ("ok" if moved else "skipped")


def test_the_vr_cell_is_clean(tmp_path, capsys):
    code, answer = commission(capsys, cell_file(tmp_path, "sim-vr.yaml"), "--move")
    assert problems(answer) == [] and code == 0
    assert {c["device"] for c in answer["checks"]} == {"arm", "side", "top"}  # no gripper: no grip check


def test_an_epick_on_a_serial_line_answering_another_id_names_the_port_and_the_id(tmp_path, capsys, pty_pair):
    """The EPick simulator on one end of a pty pair answers as device 1; the cell file asks device 9 (its default)."""
    driver_end, simulator_end = pty_pair
    config = cell_file(tmp_path, "sim-microcell-ur.yaml", gripper={"transport": "serial", "serial_port": driver_end},
                       sim={"servers": [{"protocol": "epick", "serial_port": simulator_end,
                                         "options": {"device_id": 1}}]})
    code, answer = commission(capsys, config, "--device", "gripper")
    link = the_row(answer, "gripper", "link")
    assert link["result"] == "problem" and code == 1
    assert link["finding"].startswith(f"no answer from device 9 on {driver_end} at 115200: check device_id")
    assert "device 1 answered" in link["finding"]
