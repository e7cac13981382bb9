"""The live view's parts without a daemon: a simulated camera's exposure and gain render brighter and saturate for
real (and leave the frames as they were when unset), the settings' ranges, the frame's figures, and the cell file
edited in place (only the changed keys' lines; a camera the file takes from another refused, naming it)."""

from __future__ import annotations

import difflib

import numpy as np
import pytest
import yaml

from drivers.cameras._common import CameraSettingError
from drivers.sim.render import expose

from cellctl.config import load_cell_file
from cellctl.core.cell import Cell
from cellctl.errors import InvalidRequest
from cellctl.service.cameras import defined_in, edit_camera_options, frame_stats, yaml_number

from tests.conftest import ROOT

MICRO = ROOT / "config" / "sim-microcell.yaml"


@pytest.fixture(scope="module")
def cell():
    config, text = load_cell_file(MICRO)
    with Cell(config, text) as c:
        yield c


def test_a_simulated_camera_renders_brighter_with_exposure_and_gain_and_saturates(cell):
    cam = cell.cameras["cam3"]
    nominal = cam.capture()
    assert nominal.exposure_s == pytest.approx(cam.nominal_exposure_s) and "gain_db" not in nominal.meta
    assert not (nominal.image == 255).any()
    cam.set_live({"exposure_s": cam.nominal_exposure_s * 2})
    double = cam.capture()
    assert double.exposure_s == pytest.approx(cam.nominal_exposure_s * 2)
    assert np.median(double.image) == pytest.approx(2 * np.median(nominal.image), abs=2)  # twice the light
    cam.set_live({"exposure_s": cam.nominal_exposure_s, "gain_db": 30.0})  # 31.6 times
    bright = cam.capture()
    assert bright.meta["gain_db"] == 30.0 and (bright.image == 255).mean() > 0.5  # saturated, clipped at full scale
    with pytest.raises(CameraSettingError, match=r"exposure_s: 11; allowed: 1e-05 to 10 s.*gain_db: -1; allowed: "
                                                 r"0 to 48 dB"):
        cam.set_live({"exposure_s": 11, "gain_db": -1})
    with pytest.raises(CameraSettingError, match="allowed: a number from 0 to 48 dB"):
        cam.set_live({"gain_db": True})
    assert cam.live_values() == {"exposure_s": cam.nominal_exposure_s, "gain_db": 30.0}  # nothing taken
    cam.set_live({"gain_db": 0.0})


def test_expose_is_the_identity_at_nominal_light_and_linear_below_full_scale():
    image = np.arange(256, dtype=np.uint8).reshape(16, 16)
    assert expose(image, 1.0) is image
    half = expose(image, 0.5)
    assert np.array_equal(half, np.floor(image / 2 + 0.5).astype(np.uint8))
    assert (expose(image, 2.0)[image >= 128] == 255).all()
    deep = (np.arange(256, dtype=np.uint16) * 256).reshape(16, 16)
    assert expose(deep, 4.0).dtype == np.uint16 and expose(deep, 4.0).max() == 65535


def test_frame_stats_count_saturated_pixels_and_bin_the_levels():
    image = np.zeros((10, 10), np.uint8)
    image[0, :5] = 255
    stats = frame_stats(image)
    assert stats["saturated"] == 5 and stats["saturated_pct"] == 5.0 and stats["full_scale"] == 255
    assert len(stats["histogram"]) == 64 and stats["histogram"][0] == 0.95 and stats["histogram"][-1] == 0.05
    twelve = np.full((4, 4), 4095, np.uint16)
    assert frame_stats(twelve, {"pixel_format": "Mono12"})["saturated_pct"] == 100.0
    assert frame_stats(twelve)["saturated"] == 0  # 16-bit words of a camera that does not say: 65535 is full


def test_numbers_are_written_as_yaml_reads_them_back():
    for value in (0.004, 1e-05, 6.0, 3, 1.5e-7, 12.25):
        assert yaml.safe_load(f"v: {yaml_number(value)}")["v"] == value


def changed_lines(before: str, after: str) -> list[str]:
    return [line for line in difflib.ndiff(before.splitlines(), after.splitlines()) if line[:1] in "+-"]


def test_a_flow_mapping_gets_the_key_and_keeps_its_comment():
    text = MICRO.read_text()
    out = edit_camera_options(text, "cam2", {"exposure_s": 0.004})
    assert changed_lines(text, out) == ["-   cam2: {backend: sim}   # top view of area2",
                                        "+   cam2: {backend: sim, exposure_s: 0.004}   # top view of area2"]
    again = edit_camera_options(out, "cam2", {"exposure_s": 1e-05, "gain_db": 6.0})
    assert changed_lines(out, again) == [
        "-   cam2: {backend: sim, exposure_s: 0.004}   # top view of area2",
        "+   cam2: {backend: sim, exposure_s: 1.0e-05, gain_db: 6.0}   # top view of area2"]


def test_a_block_keeps_its_comments_and_other_lines():
    text = ("cell: {name: x}\ncameras:\n  # the top camera\n  top:\n    backend: genicam   # GigE\n"
            "    producer: /opt/x.cti\n    exposure_s: 0.01   # tuned on day 1\n\n  side: {backend: sim}\n"
            "areas: {}\n")
    out = edit_camera_options(text, "top", {"exposure_s": 0.004, "gain_db": 3.5})
    assert changed_lines(text, out) == ["-     exposure_s: 0.01   # tuned on day 1",
                                        "+     exposure_s: 0.004   # tuned on day 1", "+     gain_db: 3.5"]
    assert yaml.safe_load(out)["cameras"]["top"] == {"backend": "genicam", "producer": "/opt/x.cti",
                                                     "exposure_s": 0.004, "gain_db": 3.5}


def test_a_camera_the_file_takes_from_another_is_refused_naming_it():
    text = (ROOT / "config" / "sim-microcell-ur.yaml").read_text()
    with pytest.raises(InvalidRequest, match=r"ur.yaml: cannot write cam2's settings: it extends "
                                             r"sim-microcell.yaml, and cameras.cam2 is in sim-microcell.yaml"):
        edit_camera_options(text, "cam2", {"exposure_s": 0.004}, "ur.yaml")
    assert defined_in(ROOT / "config" / "sim-microcell-ur.yaml", "cam2") == str(MICRO)
    overriding = text + "\ncameras:\n  cam2: {backend: sim, gain_db: 2}\n"  # its own entry: edited there
    out = edit_camera_options(overriding, "cam2", {"gain_db": 4.0}, "ur.yaml")
    assert changed_lines(overriding, out) == ["-   cam2: {backend: sim, gain_db: 2}",
                                              "+   cam2: {backend: sim, gain_db: 4.0}"]
    with pytest.raises(InvalidRequest, match="edit it by hand"):
        edit_camera_options("cameras:\n  cam2: !!map {backend: sim}\n", "cam2", {"gain_db": 4.0})


def test_a_file_source_has_nothing_to_change_and_says_so(tmp_path):
    import cv2

    from drivers.cameras.live import supports_live
    from drivers.registry import DriverContext, backend_class

    for i in range(2):
        cv2.imwrite(str(tmp_path / f"frame_{i:04d}.png"), np.full((8, 8), 40 * i, np.uint8))
    camera = backend_class("camera", "uvc").create("cam", {"source": str(tmp_path / "frame_%04d.png")},
                                                   DriverContext())
    camera.connect()
    try:
        assert supports_live(camera) and camera.live_specs() == [] and camera.live_values() == {}
        with pytest.raises(CameraSettingError, match="is a sequence, which has no exposure or gain to change"):
            camera.set_live({"gain": 1})
    finally:
        camera.close()
