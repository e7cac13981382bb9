"""The GenICam backend through Aravis (`backend: genicam`, `library: aravis`) against Aravis's fake GigE
Vision camera, `arv-fake-gv-camera-0.8`, on loopback: real GVCP control and GVSP frames over UDP.

The fake camera runs on 127.0.0.1 (`lo`), started and stopped here; the driver opens it by address, so
nothing is broadcast. Discovery (which broadcasts on every interface) runs in a network namespace of
its own where `lo` is the only interface (tests/drivers/aravis_netns.py).
"""

from __future__ import annotations

import gc
import json
import re
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from drivers.cameras._common import CameraSettingError, CameraSettingWarning
from drivers.interfaces import CaptureTimeout, ConnectionLost, DeviceState
from drivers.registry import DriverContext, backend_class

from tests.drivers.aravis_fake import FakeGvCamera, available, next_block_id, ramp
from tests.support.contract import CameraContract
from tests.support.wait import eventually

pytestmark = pytest.mark.skipif(available() is not None, reason=str(available()))

ROOT = Path(__file__).resolve().parents[2]
ADDRESS = "127.0.0.1"
SERIAL = "CELL1"
WIDTH, HEIGHT = 512, 512  # the fake's sensor
DEFAULT_EXPOSURE_US = 10000.0  # scale 1 in the fake's ramp


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    camera = FakeGvCamera(tmp_path_factory.mktemp("arv-fake"), serial=SERIAL, host=ADDRESS)
    camera.start()
    yield camera
    camera.stop()


@pytest.fixture
def running(fake):
    """The fake camera, freshly started: a camera keeps its registers (width, format...) until it restarts."""
    fake.stop()
    fake.start()
    return fake


def make(**options):
    return backend_class("camera", "genicam").create("cam", {"library": "aravis", "address": ADDRESS, **options},
                                                      DriverContext())


@pytest.fixture
def connected(running):
    """connect(**options) -> a connected camera, closed after the test."""
    cameras = []

    def connect(**options):
        camera = make(**options)
        cameras.append(camera)
        camera.connect()
        return camera

    yield connect
    for camera in cameras:
        camera.close()


def assert_is_the_ramp(frame, exposure_us=DEFAULT_EXPOSURE_US, gain_raw=0, bits=8):
    """The frame is the one the camera computed from these register values (±1 for log10 rounding)."""
    height, width = frame.image.shape
    expected = ramp(width, height, frame.meta["device_frame_id"], exposure_us, gain_raw, bits)
    assert frame.image.dtype == expected.dtype
    assert np.abs(frame.image.astype(np.int64) - expected.astype(np.int64)).max() <= 1


@pytest.fixture(autouse=True)
def patient_captures(monkeypatch):
    """The fake camera is a process of its own streaming over loopback; with the suite's workers busy, a frame
    can take longer than the interface's default 2 s. Captures without a time-out of their own wait 10 s (the
    tests of time-outs give theirs)."""
    from drivers.cameras.aravis import AravisCamera

    capture = AravisCamera.capture
    monkeypatch.setattr(AravisCamera, "capture", lambda self, timeout_s=10.0: capture(self, timeout_s))


# --- the contract every camera backend meets ---------------------------------------------


class TestAravisContract(CameraContract):
    @pytest.fixture
    def make_device(self, running):
        return lambda: make(serial=SERIAL)


# --- frames ---------------------------------------------------------------------------------


def test_frames_are_what_the_camera_sends(connected):
    camera = connected()
    assert camera.resolution == (WIDTH, HEIGHT)
    frames = [camera.capture() for _ in range(3)]
    for frame in frames:
        assert frame.image.shape == (HEIGHT, WIDTH)
        assert frame.meta["pixel_format"] == "Mono8"
        assert_is_the_ramp(frame)
    assert [f.frame_id for f in frames] == [1, 2, 3]
    ids = [f.meta["device_frame_id"] for f in frames]
    assert len(set(ids)) == 3


def test_frame_size_and_16_bit_pixels(connected):
    camera = connected(width=320, height=240, pixel_format="Mono16")
    assert camera.resolution == (320, 240)
    frame = camera.capture()
    assert frame.image.shape == (240, 320) and frame.image.dtype == np.uint16
    assert frame.meta["pixel_format"] == "Mono16"
    assert_is_the_ramp(frame, bits=16)  # little-endian 16-bit words, as PFNC has them
    assert frame.image.max() > 255


def test_colour_frames_are_grey_unless_native(connected):
    camera = connected(pixel_format="RGB8")
    gray = camera.capture()
    camera.close()
    assert gray.image.shape == (HEIGHT, WIDTH) and gray.meta["pixel_format"] == "RGB8"
    native = connected(pixel_format="RGB8", color="native").capture()
    assert native.image.shape == (HEIGHT, WIDTH, 3)


# --- exposure and gain --------------------------------------------------------------------


def test_exposure_and_gain_are_set_and_read_back(connected):
    camera = connected(exposure_s=0.005, gain_raw=2)
    assert camera.applied["exposure_s"] == pytest.approx(0.005)
    assert camera.applied["gain_raw"] == 2
    assert camera.read_feature("ExposureTimeAbs") == pytest.approx(5000.0)  # read from the camera, not cached
    assert camera.read_feature("GainRaw") == 2
    frame = camera.capture()
    assert frame.exposure_s == pytest.approx(0.005)
    assert frame.meta["gain_raw"] == 2
    assert_is_the_ramp(frame, exposure_us=5000.0, gain_raw=2)  # the camera exposes with them


def test_a_camera_keeps_what_the_last_connection_set(connected):
    """As a real camera does until it restarts: settings a cell file leaves out are the camera's current ones."""
    connected(exposure_s=0.02, gain_raw=1).close()
    camera = connected()
    assert camera.applied["exposure_s"] == pytest.approx(0.02) and camera.applied["gain_raw"] == 1
    assert_is_the_ramp(camera.capture(), exposure_us=20000.0, gain_raw=1)
    camera.close()
    camera = connected(exposure_s=0.01, gain_raw=0)
    assert_is_the_ramp(camera.capture(), exposure_us=10000.0, gain_raw=0)


# --- software trigger and timestamps ---------------------------------------------------------


def test_software_trigger_gives_exactly_one_frame_per_trigger(connected):
    camera = connected(trigger="software")
    assert camera.read_feature("TriggerMode") == "On" and camera.read_feature("TriggerSource") == "Software"
    frames, windows = [], []
    for _ in range(4):
        before = time.time()
        frames.append(camera.capture())
        windows.append((before, time.time()))
        time.sleep(0.3)  # a free-running camera sends ~7 frames meanwhile (25 Hz)
    ids = [f.meta["device_frame_id"] for f in frames]
    assert ids[1:] == [next_block_id(i) for i in ids[:-1]]  # the camera made no frame but the triggered ones
    for frame, (before, after) in zip(frames, windows):
        assert before - 1e-3 <= frame.device_timestamp_s <= after + 1e-3  # exposed after its trigger
        assert_is_the_ramp(frame)


def test_free_run_makes_frames_between_captures(connected):
    """The contrast to the trigger test: the same waits skip frames when the camera runs free."""
    camera = connected()
    first = camera.capture()
    time.sleep(0.3)
    second = camera.capture()
    assert second.meta["device_frame_id"] != next_block_id(first.meta["device_frame_id"])


def test_device_timestamps_increase(connected):
    camera = connected(frame_rate_hz=50.0)
    assert camera.applied["frame_rate_hz"] == pytest.approx(50.0)
    start = time.time()
    frames = [camera.capture() for _ in range(5)]
    stamps = [f.device_timestamp_s for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert start - 1.0 < stamps[0] and stamps[-1] <= time.time() + 1e-3  # the fake's clock is this host's
    hosts = [f.host_timestamp_s for f in frames]
    assert all(b >= a for a, b in zip(hosts, hosts[1:]))


# --- what the camera lacks or refuses ----------------------------------------------------------


def test_a_feature_the_camera_lacks_is_named(connected):
    with pytest.raises(CameraSettingError, match="gain_db: the camera has no Gain feature; it has GainRaw, in its "
                                                 "own units: set gain_raw instead"):
        make(gain_db=3.0).connect()
    with pytest.warns(CameraSettingWarning, match="gain_db"):
        camera = connected(gain_db=3.0, strict=False)  # a warning, kept, and the camera runs without it
    assert len(camera.refused) == 1 and camera.refused[0].startswith("gain_db:")
    assert camera.capture().image.shape == (HEIGHT, WIDTH)
    with pytest.raises(CameraSettingError, match="has no NoSuchFeature feature"):
        camera.read_feature("NoSuchFeature")
    assert camera.state is DeviceState.READY


def test_the_warning_is_a_warning(running):
    camera = make(gain_db=3.0, strict=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        camera.connect()
    try:
        assert [str(w.message) for w in caught if w.category is CameraSettingWarning] == [
            "cam: gain_db: the camera has no Gain feature; it has GainRaw, in its own units: set gain_raw instead"]
    finally:
        camera.close()


@pytest.mark.parametrize("options, message", [
    ({"exposure_s": 20.0}, r"exposure_s: ExposureTimeAbs refused 20000000\.0 \(Error: .*"),  # max 10 s
    ({"gain_raw": 50}, r"gain_raw: GainRaw refused 50 \(Error: .*"),  # range 0..10
    ({"pixel_format": "Mono12"}, "pixel_format: the camera offers BayerBG8, .*Mono8, RGB8, Mono16, not 'Mono12'"),
    ({"pixel_format": "BayerRG8"}, "pixel_format 'BayerRG8' is not handled; allowed: Mono8"),
    ({"serial": "OTHER"}, "the camera at 127.0.0.1 has serial 'CELL1', not 'OTHER'"),
    ({"model": "Other"}, "the camera at 127.0.0.1 has model 'Fake', not 'Other'"),
])
def test_refused_settings_name_the_setting(running, options, message):
    camera = make(**options)
    with pytest.raises(CameraSettingError, match=message):
        camera.connect()
    assert camera.state is DeviceState.CREATED
    camera.close()
    again = make()
    again.connect()  # the refused camera was let go: a new connection takes control
    again.close()


@pytest.mark.parametrize("options, message", [
    ({"library": "aravis", "producer": "/x.cti"}, r"producer\n .*only with library: harvesters"),
    ({"library": "harvesters"}, r"producer\n .*required with library: harvesters"),
    ({"producer": "/x.cti", "address": ADDRESS}, r"address\n .*only with library: aravis"),
    ({"library": "aravis", "address": ADDRESS, "index": 0}, r"index\n .*not with address"),
    ({"library": "gentl"}, "library"),
    ({"library": "aravis", "gain_raw": -1}, "gain_raw"),
])
def test_settings_are_checked(options, message):
    with pytest.raises(ValidationError, match=message):
        backend_class("camera", "genicam").create("cam", options, DriverContext())


# --- a camera that vanishes ------------------------------------------------------------------


def test_a_vanished_camera_times_out_then_reports_the_link_down(connected, fake):
    camera = connected()
    camera.capture()
    fake.kill()

    def timed_out() -> CaptureTimeout | None:
        try:
            camera.capture(timeout_s=0.5)
        except CaptureTimeout as exc:
            return exc
        return None  # a frame already on its way when the camera died (it streams at 25 Hz)

    caught = eventually(timed_out, timeout=10, every=0, what="a capture timing out once the camera vanished")
    # a frame cut off by the death is dropped and counted in the message: "(1 incomplete frame(s) dropped: ...)"
    assert re.search(r"no frame within 0.5 s( \(\d+ incomplete frame\(s\) dropped: [^)]*\))?, and the camera at "
                     r"127.0.0.1 does not answer \(.*\): the link is down; .*connect\(\) again", str(caught)), caught
    assert not isinstance(caught, ConnectionLost)
    assert camera.state is DeviceState.FAULTED
    with pytest.raises(ConnectionLost, match=r"reconnect the camera \(connect\(\)\)"):
        camera.capture()
    with pytest.raises(ConnectionLost):
        camera.capture()  # stays down: no silent reconnect
    fake.start()  # the camera is back; the operator reconnects
    camera.connect()
    assert camera.state is DeviceState.READY
    assert_is_the_ramp(camera.capture())


def test_a_camera_restarted_behind_the_drivers_back_is_a_lost_link(connected, fake):
    camera = connected()
    camera.capture()
    fake.kill()
    fake.start()  # a power cycle: the camera answers again, but no longer streams to us nor grants us control
    with pytest.raises((CaptureTimeout, ConnectionLost), match="no longer grants this host control"):
        camera.capture(timeout_s=0.5)  # CaptureTimeout, or ConnectionLost if Aravis's heartbeat noticed first
    assert camera.state is DeviceState.FAULTED
    with pytest.raises(ConnectionLost):
        camera.capture()
    camera.connect()
    assert camera.capture().image.shape == (HEIGHT, WIDTH)


def test_a_vanished_camera_in_trigger_mode_is_a_lost_link_at_the_trigger(connected, fake):
    camera = connected(trigger="software")
    camera.capture()
    fake.kill()
    with pytest.raises(ConnectionLost, match=r"did not answer TriggerSoftware .*connect\(\) again"):
        camera.capture(timeout_s=0.5)  # the camera did not acknowledge the trigger
    assert camera.state is DeviceState.FAULTED
    # Aravis's own release (giving control back to a dead camera) takes about 7 s and runs on a thread: close()
    # must not wait for it. The bound is well below those 7 s and well above a loaded machine's scheduling delays.
    start = time.monotonic()
    camera.close()
    assert time.monotonic() - start < 5.0
    assert camera.state is DeviceState.CLOSED
    start = time.monotonic()
    gc.collect()  # the errors' tracebacks hold driver objects: freeing them must not be what lets the camera go
    assert time.monotonic() - start < 5.0


def test_a_camera_another_program_controls_is_a_clear_error(connected):
    first = connected()
    second = make()
    with pytest.raises(ConnectionLost, match="the camera at 127.0.0.1 is controlled by another program"):
        second.connect()
    assert second.state is DeviceState.CREATED
    assert first.capture().image.shape == (HEIGHT, WIDTH)  # the first keeps it
    first.close()
    second.connect()  # once the first let go
    assert second.capture().image.shape == (HEIGHT, WIDTH)
    second.close()


def test_no_camera_at_the_address_is_a_clear_error(running):
    camera = backend_class("camera", "genicam").create("cam", {"library": "aravis", "address": "127.0.0.9"},
                                                        DriverContext())
    with pytest.raises(ConnectionLost, match="no GigE Vision camera answers at 127.0.0.9"):
        camera.connect()
    assert camera.state is DeviceState.CREATED
    camera.close()


# --- discovery, in a network namespace where lo is the only interface ---------------------------


def _unshare() -> list[str] | str:
    """The command that runs a process in a network namespace of its own (with a user namespace where
    needed), or why there is none."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip (util-linux, iproute2) is missing"
    for command in (["unshare", "-n"], ["unshare", "-r", "-n"]):
        probe = subprocess.run([*command, "true"], capture_output=True, text=True)
        if probe.returncode == 0:
            return command
    return f"no network namespace can be made here: {probe.stderr.strip()}"


UNSHARE = _unshare()


@pytest.mark.skipif(isinstance(UNSHARE, str), reason=str(UNSHARE))
def test_discovery_chooses_by_serial_model_and_index():
    done = subprocess.run([*UNSHARE, sys.executable, "-m", "tests.drivers.aravis_netns"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    results = json.loads(done.stdout.strip().splitlines()[-1])
    found = ("found: [0] Fake serial NSA (Aravis-Fake-NSA) at 127.0.0.1; "
             "[1] Fake serial NSB (Aravis-Fake-NSB) at 127.0.0.2")
    assert results == {
        "serial": "ok NSB 127.0.0.2",
        "none": f"CameraSettingError: cam: 2 devices match (no serial/model/index); set serial, model or index; "
                f"{found}",
        "model_index": "ok NSB 127.0.0.2",
        "unknown_serial": f"CameraSettingError: cam: no device with serial 'NOPE' among the cameras Aravis "
                          f"discovered; {found}",
    }


def test_exposure_and_gain_change_while_it_runs(connected):
    """The live view's controls (drivers/cameras/live.py): each value checked against its range, then set on the
    running camera, which exposes the next frames with it."""
    camera = connected()
    specs = {s.key: s for s in camera.live_specs()}
    assert set(specs) == {"exposure_s", "gain_raw"}  # this camera has GainRaw, no Gain in dB
    with pytest.raises(CameraSettingError, match=r"exposure_s: 120; allowed: 1e-06 to 60 s.*gain_raw: 1.5; allowed: "
                                                 r"a whole number"):
        camera.set_live({"exposure_s": 120, "gain_raw": 1.5})
    assert camera.set_live({"exposure_s": 0.005, "gain_raw": 2}) == {"exposure_s": pytest.approx(0.005), "gain_raw": 2}
    assert camera.read_feature("ExposureTimeAbs") == pytest.approx(5000.0) and camera.read_feature("GainRaw") == 2
    camera.capture()  # one that may have been exposed before
    frame = camera.capture()
    assert frame.exposure_s == pytest.approx(0.005) and frame.meta["gain_raw"] == 2
    assert_is_the_ramp(frame, exposure_us=5000.0, gain_raw=2)
