"""`arm` calibrations (routine arm-kinematics: the arm's calibrated kinematic table) through the service and the CLI:
exported as URDF (and still as JSON), other targets refused as URDF naming what they allow; activated only on the
cell that made them and on an arm of the model they calibrated, while other targets activate as before."""

from __future__ import annotations

import json

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from geometry.kinematic_table import KinematicTable, nominal_table

from cellctl.cli import main
from cellctl.config import arm_model_of, load_cell_file
from cellctl.errors import Conflict, InvalidRequest
from cellctl.service import Caller
from cellctl.service.local import LocalService
from cellctl.stores.calibrations import CalibrationStore

from tests.conftest import MICROCELL, ROOT

UR5E_CELL = ROOT / "config" / "sim-ur5e-handeye.yaml"  # cell sim-ur5e-handeye, backend sim-ur5e
IRB120_CELL = ROOT / "config" / "sim-irb120-csm.yaml"  # cell sim-irb120-csm, backend sim-irb120
UR_CELL = ROOT / "config" / "sim-ur5e-handeye-ur.yaml"  # cell sim-ur5e-handeye-ur, backend ur (no model)
ABB_CELL = ROOT / "config" / "sim-irb120-abb.yaml"  # cell sim-irb120-abb, backend abb (no model)
CALLER = Caller("tester@here", credential="local")


def run_cli(*args) -> int:
    return main([str(a) for a in args])


def calibrated_table(model: str, seed: int = 0) -> KinematicTable:
    rng = np.random.default_rng(seed)
    nominal = nominal_table(model)
    table = nominal.with_vector(nominal.vector() + rng.normal(0.0, 1e-3, nominal.vector().size))
    base = np.eye(4)
    base[:3, :3] = Rotation.from_rotvec([0.01, -0.02, 0.3]).as_matrix()
    base[:3, 3] = [0.1, -0.2, 0.05]
    return KinematicTable(model, table.joints, base)


TOOL = {"x_mm": 12.5, "y_mm": -40.0, "z_mm": 65.0, "qw": 0.8, "qx": 0.2, "qy": -0.4, "qz": float(np.sqrt(0.16))}


def arm_result(cell: str, arm_model: str | None, tool: dict | None = TOOL) -> dict:
    """An `arm` calibration's result as the arm-kinematics routine stores it (the parts the service reads)."""
    table = calibrated_table(arm_model or "ur5e")
    model = {"kind": "arm-kinematics", "arm_model": arm_model, "table": table.to_dict(),
             "nominal": nominal_table(arm_model or "ur5e").to_dict(), "tool": tool, "tool_frame": "camera",
             "identified": ["a_shoulder"], "fixed": ["d_shoulder"], "sigma": {"a_shoulder": 0.01}}
    if arm_model is None:
        del model["arm_model"]
    return {"routine": "arm-kinematics", "cell": cell, "model": model, "stats": {}}


def camera_result(cell: str) -> dict:
    return {"routine": "virtual-grid", "cell": cell, "model": {"kind": "planar"}, "stats": {}}


def flange_and_tool(text: str, q) -> tuple[np.ndarray, np.ndarray]:
    model = pin.buildModelFromXML(text)
    data = model.createData()
    pin.framesForwardKinematics(model, data, np.asarray(q, dtype=float))
    return data.oMf[model.getFrameId("flange")].homogeneous, data.oMf[model.getFrameId("tool")].homogeneous


# -- export -------------------------------------------------------------------------------------------------------


def test_an_arm_calibration_exports_as_urdf_and_json_through_the_cli(tmp_path, capsys, isolated_store):
    store = CalibrationStore(isolated_store)
    arm = store.save("arm", arm_result("sim-ur5e-handeye", "ur5e"), "")
    out = tmp_path / "arm.urdf"
    assert run_cli("calibrations", "--config", UR5E_CELL, "export", arm.id, "--format", "urdf", "--out", out) == 0
    assert f"wrote calibration {arm.id} as urdf to {out}" in capsys.readouterr().out
    text = out.read_text()
    assert f"cellctl calibration {arm.id}" in text and not list(tmp_path.glob(".*"))  # no temporary file left
    table = KinematicTable.from_dict(arm.model["table"])
    from geometry.urdf import tool_transform

    T_flange_tool = tool_transform(TOOL)
    for q in np.random.default_rng(2).uniform(-3.0, 3.0, (30, 6)):
        flange, tool = flange_and_tool(text, q)
        assert np.abs(flange - table.forward(q)).max() < 1e-9
        assert np.abs(tool - table.forward(q) @ T_flange_tool).max() < 1e-9
    # to standard output, the same document
    assert run_cli("calibrations", "--config", UR5E_CELL, "export", arm.id, "--format", "urdf") == 0
    assert capsys.readouterr().out == text
    # json keeps working for an arm calibration
    assert run_cli("calibrations", "--config", UR5E_CELL, "export", arm.id, "--format", "json") == 0
    exported = json.loads(capsys.readouterr().out)
    assert exported["target"] == "arm" and exported["model"]["table"] == arm.model["table"]


def test_urdf_of_another_target_is_refused_naming_the_formats_it_allows(tmp_path, capsys, isolated_store):
    store = CalibrationStore(isolated_store)
    cam = store.save("cam1", camera_result("sim-microcell"), "")
    out = tmp_path / "cam1.urdf"
    out.write_text("what was there")
    assert run_cli("calibrations", "--config", MICROCELL, "export", cam.id, "--format", "urdf", "--out", out) == 2
    err = capsys.readouterr().err
    assert f"calibration {cam.id} is of target 'cam1'" in err and "allowed for it: json, opencv" in err
    assert out.read_text() == "what was there"  # nothing written over
    assert run_cli("calibrations", "--config", MICROCELL, "export", cam.id, "--format", "opencv", "--out",
                   tmp_path / "cam1.yaml") == 0  # as before


def test_the_service_refuses_what_cannot_be_a_urdf(isolated_store):
    config, _ = load_cell_file(UR5E_CELL, routines=False)
    store = CalibrationStore(isolated_store)
    service = LocalService.of_store(config, store)
    cam = store.save("cam1", camera_result("sim-ur5e-handeye"), "")
    with pytest.raises(InvalidRequest, match=r"allowed for it: json, opencv$"):
        service.export(cam.id, "urdf")
    with pytest.raises(InvalidRequest, match="format: 'xml'; allowed: json, opencv, urdf"):
        service.export(cam.id, "xml")
    broken = store.save("arm", {"routine": "arm-kinematics", "cell": "sim-ur5e-handeye",
                                "model": {"kind": "arm-kinematics", "arm_model": "ur5e"}, "stats": {}}, "")
    with pytest.raises(InvalidRequest, match="no kinematic table"):
        service.export(broken.id, "urdf")
    no_tool = store.save("arm", arm_result("sim-ur5e-handeye", "ur5e", tool=None), "")
    doc = service.export(no_tool.id, "urdf")
    assert (doc.media_type, doc.filename) == ("application/xml", f"calibration-{no_tool.id}.urdf")
    assert "<link name=\"tool\"" not in doc.text and "<link name=\"flange\"" in doc.text
    service.close()


# -- activate -----------------------------------------------------------------------------------------------------


def service_on(cell_file, store_dir) -> tuple[LocalService, CalibrationStore]:
    config, text = load_cell_file(cell_file, routines=False)
    store = CalibrationStore(store_dir)
    return LocalService.of_store(config, store, text), store


def test_the_cells_arm_model():
    models = {f.name: arm_model_of(load_cell_file(f, routines=False)[0])
              for f in (UR5E_CELL, IRB120_CELL, UR_CELL, ABB_CELL, MICROCELL)}
    assert models == {UR5E_CELL.name: "ur5e", IRB120_CELL.name: "irb120", UR_CELL.name: None, ABB_CELL.name: None,
                      MICROCELL.name: None}


@pytest.mark.parametrize("cell_file, cell, model, other_model", [
    (UR5E_CELL, "sim-ur5e-handeye", "ur5e", "irb120"),
    (IRB120_CELL, "sim-irb120-csm", "irb120", "ur5e"),
])
def test_an_arm_calibration_activates_only_on_its_cell_and_arm_model(isolated_store, cell_file, cell, model,
                                                                     other_model):
    service, store = service_on(cell_file, isolated_store)
    own = store.save("arm", arm_result(cell, model), "", activate=False)
    foreign = store.save("arm", arm_result("cell-b", model), "", activate=False)
    other = store.save("arm", arm_result(cell, other_model), "", activate=False)
    unnamed = store.save("arm", arm_result(cell, None), "", activate=False)

    assert service.activate(CALLER, own.id)["active"] is True
    with pytest.raises(Conflict) as refused:
        service.activate(CALLER, foreign.id)
    assert f"arm of cell 'cell-b', and this cell is {cell!r}" in str(refused.value)
    with pytest.raises(Conflict) as refused:
        service.activate(CALLER, other.id)
    assert f"calibrated a {other_model!r} arm, and this cell's arm is a {model!r}" in str(refused.value)
    with pytest.raises(Conflict, match=f"no stated model.*this cell's arm is a {model!r}"):
        service.activate(CALLER, unnamed.id)
    assert store.active("arm").id == own.id  # the refusals changed nothing
    outcomes = [e["outcome"][:11] for e in service._audit_log.audit_log() if e["action"] == "activate"]
    assert sorted(outcomes) == ["ok"] + ["refused 409"] * 3
    service.close()


def test_a_cell_file_that_does_not_state_its_arm_model_checks_the_cell_and_says_how_to_state_it(tmp_path,
                                                                                                isolated_store):
    service, store = service_on(UR_CELL, isolated_store)
    own_ur5e = store.save("arm", arm_result("sim-ur5e-handeye-ur", "ur5e"), "", activate=False)
    own_irb = store.save("arm", arm_result("sim-ur5e-handeye-ur", "irb120"), "", activate=False)
    foreign = store.save("arm", arm_result("sim-ur5e-handeye", "ur5e"), "", activate=False)
    assert service.activate(CALLER, own_ur5e.id)["active"]
    assert service.activate(CALLER, own_irb.id)["active"]  # the model is unknown here: not checked
    with pytest.raises(Conflict) as refused:
        service.activate(CALLER, foreign.id)
    message = str(refused.value)
    assert "arm of cell 'sim-ur5e-handeye', and this cell is 'sim-ur5e-handeye-ur'" in message
    assert "does not state its arm's model (arm backend 'ur'): give it as arm.model" in message
    service.close()

    stated = tmp_path / "stated.yaml"  # the same cell stating its model: now the model is checked too
    stated.write_text(f"extends: {UR_CELL}\narm:\n  model: ur5e\n")
    service, store = service_on(stated, isolated_store)
    assert arm_model_of(service.config) == "ur5e"
    with pytest.raises(Conflict, match="calibrated a 'irb120' arm, and this cell's arm is a 'ur5e'"):
        service.activate(CALLER, own_irb.id)
    assert service.activate(CALLER, own_ur5e.id)["active"]
    service.close()


def test_an_abb_cell_states_its_model_in_the_arm_settings(tmp_path, isolated_store):
    stated = tmp_path / "abb.yaml"
    stated.write_text(f"extends: {ABB_CELL}\narm:\n  model: irb120\n")
    service, store = service_on(stated, isolated_store)
    assert arm_model_of(service.config) == "irb120"
    ur5e = store.save("arm", arm_result("sim-irb120-abb", "ur5e"), "", activate=False)
    with pytest.raises(Conflict, match="calibrated a 'ur5e' arm, and this cell's arm is a 'irb120'"):
        service.activate(CALLER, ur5e.id)
    service.close()
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text(f"extends: {ABB_CELL}\narm:\n  model: ur5e\n")
    with pytest.raises(ValueError, match="arm.model"):
        load_cell_file(wrong, routines=False)


def test_other_targets_activate_as_before_whatever_their_cell(isolated_store, capsys):
    service, store = service_on(UR5E_CELL, isolated_store)
    cam = store.save("cam1", camera_result("another-cell"), "", activate=False)
    assert service.activate(CALLER, cam.id)["active"]
    service.close()
    foreign = store.save("arm", arm_result("another-cell", "ur5e"), "", activate=False)
    # the CLI's local activate goes through the same service verb, and says why it refused
    assert run_cli("calibrations", "--config", UR5E_CELL, "activate", foreign.id) == 2
    assert "arm of cell 'another-cell', and this cell is 'sim-ur5e-handeye'" in capsys.readouterr().err
    assert run_cli("calibrations", "--config", UR5E_CELL, "activate", cam.id) == 0


def test_an_arm_calibration_is_turned_off_and_on_again(isolated_store, capsys):
    """deactivate takes the version out of use (the target has none: moves go by the controller's table);
    activate brings it back; the CLI does the same."""
    service, store = service_on(UR5E_CELL, isolated_store)
    own = store.save("arm", arm_result("sim-ur5e-handeye", "ur5e"), "")
    assert "arm" in store.active_models()
    off = service.deactivate(CALLER, own.id)
    assert off["active"] is False and "arm" not in store.active_models()
    assert service.activate(CALLER, own.id)["active"] and "arm" in store.active_models()
    service.close()
    store.close()
    assert run_cli("calibrations", "--config", UR5E_CELL, "deactivate", own.id) == 0
    assert "is out of use: arm has no active calibration" in capsys.readouterr().out
    store = CalibrationStore(isolated_store)
    assert "arm" not in store.active_models()
    store.close()
