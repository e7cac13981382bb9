"""Real camera drivers on what runs here: UVC (OpenCV) on the simulated world written to PNGs and an
FFV1 video, GenICam on the genicam wheel's simulated producer (viky.cti), OAK on depthai's ReplayVideo.

The simulated cell is filmed by `drivers.sim.servers.camera_files` (cam2 of the micro cell,
the arm moving the nozzle round a circle); the drivers must return those frames unchanged,
so a centroid measured through a driver is the one measured in the simulator's own frame.
"""

from __future__ import annotations

import copy
import importlib.util
import itertools
import socket
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from drivers.cameras._common import (
    CameraSettingError,
    CameraSettingWarning,
    EndOfSource,
)
from drivers.interfaces import CaptureTimeout, ConnectionLost, DeviceState
from drivers.limits import WorkspaceBox
from drivers.registry import DriverContext, backend_class
from drivers.sim.kinds import build_world
from drivers.sim.micro.config import SimWorldConfig
from drivers.sim.servers.camera_files import (
    view_positions,
    write_camera_files,
    write_sequence,
    write_video,
)

from calibration.vision.centroid import find_blob

from tests.conftest import MICROCELL, microcell_data
from tests.support.contract import CameraContract

DATA = microcell_data()
CAMERA = "cam2"  # 1360 x 1024: quick to render; sees the nozzle's end face as a ~20 px ring
LIMITS = WorkspaceBox(**DATA["arm"]["limits"])
N_FRAMES = 4


def _sim_config(bit_depth: int = 8) -> SimWorldConfig:
    sim = copy.deepcopy(DATA["sim"])
    sim["cameras"][CAMERA]["bit_depth"] = bit_depth
    return SimWorldConfig(**sim)


def _same_scene(config: SimWorldConfig, poses):
    """The frames again, straight from a fresh World (no fakes, no files): (image, true nozzle centre px)."""
    world = build_world(config)
    out = []
    for i, pose in enumerate(poses):
        world.begin_step(i)
        world.move_arm(pose)
        image = world.capture(CAMERA, i + 1)
        out.append((image, world.frame_truth[(CAMERA, i + 1)].features_px[0]))
    return out


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    config = _sim_config()
    poses = view_positions(config, CAMERA, N_FRAMES)
    files = write_camera_files(build_world(config), CAMERA, tmp_path_factory.mktemp(CAMERA), poses, limits=LIMITS)
    return files, _same_scene(config, poses)


def _viky() -> str | None:
    spec = importlib.util.find_spec("genicam")
    if spec is None:
        return None
    path = Path(spec.submodule_search_locations[0]) / "viky.cti"  # the wheel puts it beside its modules
    return str(path) if path.is_file() else None


VIKY = _viky()
needs_viky = pytest.mark.skipif(VIKY is None, reason="the genicam wheel's viky.cti is not installed")


def _factory(backend, options):
    return lambda: backend_class("camera", backend).create("cam", options, DriverContext())


# --- the simulated world on file ------------------------------------------------------


def test_rendered_files_show_the_tool_moving(rendered):
    files, scene = rendered
    assert Path(files.sequence % 0).is_file() and Path(files.video).is_file()
    assert (Path(files.video).parent / "poses.csv").read_text().count("\n") == N_FRAMES + 1
    centres = [find_blob(image) for image in files.images]
    steps = [np.hypot(b.u - a.u, b.v - a.v) for a, b in itertools.pairwise(centres)]
    assert min(steps) > 20  # the nozzle is seen in a different place in every frame
    for image, (again, _) in zip(files.images, scene):
        assert np.array_equal(image, again)  # the fakes render what the World renders


def test_command_line_writes_the_files(tmp_path, capsys):
    from drivers.sim.servers.camera_files import main

    assert main(["--cell", str(MICROCELL), "--camera", CAMERA, "--out", str(tmp_path), "--frames", "2"]) == 0
    assert "2 frames of cam2 (1360x1024)" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame_0000.png", "frame_0001.png", "frames.avi", "poses.csv"]


def test_writers_refuse_what_they_cannot_write(tmp_path):
    with pytest.raises(ValueError, match="grayscale"):
        write_sequence([np.zeros((4, 4, 3), np.uint8)], tmp_path)
    with pytest.raises(ValueError, match=r"\.avi or \.mkv"):
        write_video([np.zeros((4, 4), np.uint8)], tmp_path / "x.mp4")
    assert not list(tmp_path.iterdir())  # nothing half-written


# --- UVC (OpenCV VideoCapture) -------------------------------------------------------


class TestUvcImageSequence(CameraContract):
    @pytest.fixture
    def make_device(self, rendered):
        return _factory("uvc", {"source": rendered[0].sequence})


class TestUvcVideoFile(CameraContract):
    @pytest.fixture
    def make_device(self, rendered):
        return _factory("uvc", {"source": rendered[0].video})


@pytest.mark.parametrize("kind", ["sequence", "video"])
def test_uvc_returns_the_simulated_frames_unchanged(rendered, kind):
    files, scene = rendered
    camera = _factory("uvc", {"source": getattr(files, kind)})()
    camera.connect()
    try:
        assert camera.resolution == files.resolution
        frames = [camera.capture() for _ in range(N_FRAMES)]
    finally:
        camera.close()
    for frame, (image, true_centre) in zip(frames, scene):
        assert frame.image.dtype == image.dtype and np.array_equal(frame.image, image)
        seen, simulated = find_blob(frame.image), find_blob(image)
        assert (seen.u, seen.v) == (simulated.u, simulated.v)
        assert np.hypot(seen.u - true_centre[0], seen.v - true_centre[1]) < 0.1
    assert [f.frame_id for f in frames] == sorted({f.frame_id for f in frames})
    if kind == "video":  # the media time of each frame (10 fps)
        assert [f.device_timestamp_s for f in frames] == pytest.approx([0.0, 0.1, 0.2, 0.3])
    else:
        assert all(f.device_timestamp_s is None for f in frames)


def test_uvc_keeps_16_bit_frames(tmp_path):
    config = _sim_config(bit_depth=16)
    poses = view_positions(config, CAMERA, 2)
    files = write_camera_files(build_world(config), CAMERA, tmp_path, poses, video=False, limits=LIMITS)
    camera = _factory("uvc", {"source": files.sequence})()
    camera.connect()
    try:
        for image in files.images:
            frame = camera.capture()
            assert frame.image.dtype == np.uint16 and np.array_equal(frame.image, image)
            assert image.max() > 255
    finally:
        camera.close()


def test_uvc_end_of_file_is_an_error_or_a_loop(rendered):
    files, _ = rendered
    camera = _factory("uvc", {"source": files.sequence})()
    camera.connect()
    for _ in range(N_FRAMES):
        camera.capture()
    with pytest.raises(EndOfSource, match="at_end: loop"):
        camera.capture()
    camera.close()
    camera = _factory("uvc", {"source": files.sequence, "at_end": "loop"})()
    camera.connect()
    frames = [camera.capture() for _ in range(N_FRAMES + 1)]
    camera.close()
    assert np.array_equal(frames[-1].image, files.images[0])
    assert frames[-1].frame_id == N_FRAMES + 1


def test_uvc_reports_a_refused_property(rendered):
    source = rendered[0].sequence
    with pytest.raises(CameraSettingError, match="exposure_s: .*CV_IMAGES"):
        _factory("uvc", {"source": source, "exposure_s": 0.01})().connect()
    with pytest.raises(CameraSettingError, match=r"width: refused .*asked 640"):
        _factory("uvc", {"source": source, "width": 640})().connect()
    camera = _factory("uvc", {"source": source, "gain": 2.0, "strict": False})()
    with pytest.warns(CameraSettingWarning, match="gain"):
        camera.connect()
    assert camera.refused and "gain" in camera.refused[0]
    assert camera.capture().image.shape == rendered[0].images[0].shape
    camera.close()


@pytest.mark.parametrize("source, message", [
    ("/nonexistent/frame_%04d.png", "source '/nonexistent/frame_%04d.png': no image matches"),
    ("/nonexistent/video.avi", "source '/nonexistent/video.avi': no such video file"),
    ("frames/frame_%s.png", "needs one integer field"),
    (57, "source 57 could not be opened"),
])
def test_uvc_bad_source_names_the_setting(source, message):
    camera = _factory("uvc", {"source": source})()
    with pytest.raises(CameraSettingError, match=message):
        camera.connect()
    assert camera.state is DeviceState.CREATED
    camera.close()


def test_uvc_settings_are_checked():
    with pytest.raises(ValidationError, match="exposure"):
        _factory("uvc", {"source": 0, "exposure": 5})()
    with pytest.raises(ValidationError, match="at_end"):
        _factory("uvc", {"source": 0, "at_end": "rewind"})()


class _StallingStream:
    """A TCP video source that sends the first part of a file, then goes quiet (a stalled camera)."""

    def __init__(self, data: bytes):
        self.data = data
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(5.0)
        self.port = self.server.getsockname()[1]
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        while not self.done.is_set():
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            with conn:
                conn.sendall(self.data)
                self.done.wait()

    def close(self):
        self.done.set()
        self.server.close()
        self.thread.join(5.0)


def test_uvc_stream_that_stalls_times_out_then_reports_the_link_down(tmp_path):
    small = [np.full((48, 64), 10 * i, np.uint8) for i in range(20)]  # many small frames: FFMPEG reads ahead
    video = Path(write_video(small, tmp_path / "small.mkv")).read_bytes()
    stream = _StallingStream(video[: len(video) * 2 // 3])
    camera = _factory("uvc", {"source": f"tcp://127.0.0.1:{stream.port}", "timeout_s": 0.4})()
    try:
        camera.connect()
        outcomes = []
        for _ in range(len(small)):
            try:
                camera.capture()
                outcomes.append("frame")
            except CaptureTimeout:
                outcomes.append("timeout")
                break
        assert outcomes[0] == "frame" and outcomes[-1] == "timeout"
        with pytest.raises(ConnectionLost, match="connect"):
            camera.capture()  # the stream is dead after the stall
        assert camera.state is DeviceState.FAULTED
        with pytest.raises(ConnectionLost):
            camera.capture()  # stays down: no silent reconnect
    finally:
        camera.close()
        stream.close()
    assert not stream.thread.is_alive()


# --- GenICam (harvesters + viky.cti) ------------------------------------------------------


@needs_viky
class TestGenICamViky(CameraContract):
    @pytest.fixture
    def make_device(self):
        return _factory("genicam", {"producer": VIKY, "serial": "1", "pixel_format": "Mono8"})


@needs_viky
def test_genicam_frames_are_grayscale_with_the_device_count():
    camera = _factory("genicam", {"producer": VIKY, "model": "Viky", "index": 2})()  # RGBa8 by default
    camera.connect()
    try:
        assert camera.resolution == (400, 400)
        frame = camera.capture()
        assert frame.image.shape == (400, 400) and frame.image.dtype == np.uint8
        assert frame.meta["pixel_format"] == "RGBa8" and frame.meta["device_frame_id"] >= 1
        assert frame.device_timestamp_s is None  # viky has no timestamps
    finally:
        camera.close()
    camera = _factory("genicam", {"producer": VIKY, "serial": "0", "color": "native"})()
    camera.connect()
    try:
        assert camera.capture().image.shape == (400, 400, 4)
    finally:
        camera.close()


@needs_viky
def test_genicam_absent_features_are_named():
    with pytest.raises(CameraSettingError, match="exposure_s: the camera has no ExposureTime"):
        _factory("genicam", {"producer": VIKY, "serial": "1", "exposure_s": 0.005})().connect()
    with pytest.raises(CameraSettingError, match="trigger: the camera has no TriggerMode"):
        _factory("genicam", {"producer": VIKY, "serial": "1", "trigger": "software"})().connect()
    camera = _factory("genicam", {"producer": VIKY, "serial": "1", "exposure_s": 0.005, "gain_db": 3.0,
                                  "strict": False})()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        camera.connect()
    try:
        assert {str(w.message).split(":")[1].strip() for w in caught if w.category is CameraSettingWarning} == \
            {"exposure_s", "gain_db"}
        assert camera.capture().image.shape == (400, 400)
    finally:
        camera.close()


@needs_viky
def test_genicam_capture_timeout_leaves_the_camera_ready():
    camera = _factory("genicam", {"producer": VIKY, "serial": "1", "frame_rate_hz": 1.0})()
    camera.connect()
    try:
        camera.capture(timeout_s=3.0)
        start = time.monotonic()
        with pytest.raises(CaptureTimeout, match="0.2 s"):
            camera.capture(timeout_s=0.2)  # the next frame is a second away
        assert time.monotonic() - start < 1.0
        assert camera.state is DeviceState.READY
        assert camera.capture(timeout_s=3.0).frame_id == 2
    finally:
        camera.close()


@needs_viky
@pytest.mark.parametrize("options, message", [
    ({"producer": "/nonexistent/producer.cti"}, "producer '/nonexistent/producer.cti': no such GenTL producer"),
    ({"serial": "9"}, r"no device with serial '9' .*found: \[0\] Viky serial 0"),
    ({}, "3 devices match .*set serial, model or index"),
    ({"model": "Viky", "index": 5}, "index 5 but only 3 matching"),
    ({"serial": "1", "pixel_format": "BayerRG8"}, "pixel_format 'BayerRG8' is not handled; allowed: Mono8"),
    ({"serial": "1", "pixel_format": "Mono16"}, "pixel_format: the camera offers RGBa8, Mono8"),
])
def test_genicam_bad_settings_name_the_setting(options, message):
    camera = _factory("genicam", {"producer": VIKY, **options})()
    with pytest.raises(CameraSettingError, match=message):
        camera.connect()
    camera.close()


# --- OAK (depthai ReplayVideo, host only) ----------------------------------------------------


class TestOakReplay(CameraContract):
    @pytest.fixture
    def make_device(self, rendered):
        return _factory("oak", {"replay": rendered[0].video, "fps": 1000})


def test_oak_replay_gives_the_simulated_frames_in_order(rendered):
    files, scene = rendered
    camera = _factory("oak", {"replay": files.video, "fps": 1000})()
    camera.connect()
    try:
        assert camera.resolution == files.resolution
        frames = [camera.capture() for _ in range(N_FRAMES)]
        with pytest.raises(EndOfSource, match="at_end: loop"):
            camera.capture()
    finally:
        camera.close()
    assert [f.meta["sequence_number"] for f in frames] == list(range(N_FRAMES))
    assert np.all(np.diff([f.device_timestamp_s for f in frames]) > 0)
    assert abs(frames[-1].host_timestamp_s - time.monotonic()) < 60  # depthai's host clock is the monotonic one
    for frame, (image, _) in zip(frames, scene):
        assert np.array_equal(frame.image, image)  # FFV1: lossless through ReplayVideo
        seen, simulated = find_blob(frame.image), find_blob(image)
        assert (seen.u, seen.v) == (simulated.u, simulated.v)


def test_oak_replay_gives_a_slow_reader_every_frame(rendered):
    """depthai closes the queue at the end of the file with frames still in it; the driver must not lose them."""
    camera = _factory("oak", {"replay": rendered[0].video, "fps": 1000})()
    camera.connect()
    try:
        frames = []
        for _ in range(N_FRAMES):
            time.sleep(0.05)  # a reader behind the replay (a move between captures): the queue is full at the end
            frames.append(camera.capture())
        with pytest.raises(EndOfSource, match="at_end: loop"):
            camera.capture()
    finally:
        camera.close()
    assert [f.meta["sequence_number"] for f in frames] == list(range(N_FRAMES))


def test_oak_replay_loops(rendered):
    camera = _factory("oak", {"replay": rendered[0].video, "fps": 1000, "at_end": "loop"})()
    camera.connect()
    try:
        frames = [camera.capture() for _ in range(N_FRAMES + 2)]
    finally:
        camera.close()
    assert np.array_equal(frames[N_FRAMES].image, rendered[0].images[0])
    assert [f.frame_id for f in frames] == list(range(1, N_FRAMES + 3))


def test_oak_bad_settings_name_the_setting(rendered):
    with pytest.raises(CameraSettingError, match="replay '/nonexistent.avi': no such video file"):
        _factory("oak", {"replay": "/nonexistent.avi"})().connect()
    with pytest.raises(CameraSettingError, match="device 'NOSUCHOAK' not found"):
        _factory("oak", {"device": "NOSUCHOAK"})().connect()
    with pytest.raises(CameraSettingError, match="exposure_s: does not apply to a replayed video"):
        _factory("oak", {"replay": rendered[0].video, "exposure_s": 0.01})().connect()
    with pytest.raises(ValidationError, match="socket: 'CAM_Z' is not a board socket; allowed: CAM_A"):
        _factory("oak", {"socket": "CAM_Z"})()
    with pytest.raises(CameraSettingError, match="trigger: an OAK camera streams"):
        _factory("oak", {"replay": rendered[0].video, "trigger": "software"})().connect()
    camera = _factory("oak", {"replay": rendered[0].video, "fps": 1000, "trigger": "software", "strict": False})()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        camera.connect()
    try:
        assert any("trigger" in str(w.message) for w in caught if w.category is CameraSettingWarning)
        assert camera.capture().image.ndim == 2
    finally:
        camera.close()
