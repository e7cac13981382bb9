"""Sub-pixel centroid: accuracy on rendered frames against the truth, and clear errors."""

import numpy as np
import pytest

from calibration.errors import VisionError
from calibration.vision.centroid import blob_detector_centroid, find_blob, find_blobs
from drivers.interfaces import Pose
from drivers.sim.world import World


def supersampled(size, centre, r_out, r_in=0.0, blur=1.0, noise=0.01, rng=None, dtype=np.uint8, axes=(1.0, 1.0)):
    """An independent renderer: 8x8 supersampled ring or disc (optionally elliptical), blur, noise, quantisation."""
    import cv2

    ss = 8
    h, w = size
    yy, xx = np.mgrid[0 : h * ss, 0 : w * ss]
    x = (xx + 0.5) / ss - 0.5 - centre[0]
    y = (yy + 0.5) / ss - 0.5 - centre[1]
    r = np.hypot(x / axes[0], y / axes[1])
    inside = ((r <= r_out) & (r >= r_in)).astype(np.float32)
    img = inside.reshape(h, ss, w, ss).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img, (0, 0), blur) * 0.72 + 0.08
    rng = rng or np.random.default_rng(0)
    img = np.clip(img + rng.normal(0, noise, img.shape), 0, 1)
    full = 255 if dtype == np.uint8 else 65535
    return np.rint(img * full).astype(dtype)


@pytest.mark.parametrize("kind, r_out, r_in", [("ring (nozzle)", 35.0, 20.0), ("disc (sphere)", 75.0, 0.0)])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_accuracy_on_independently_rendered_features(kind, r_out, r_in, dtype):
    rng = np.random.default_rng(1)
    err, err_cv = [], []
    for _ in range(30):
        centre = rng.uniform(90, 110, 2)
        img = supersampled((200, 200), centre, r_out, r_in, rng=rng, dtype=dtype)
        b = find_blob(img)
        err.append(np.hypot(b.u - centre[0], b.v - centre[1]))
        c = blob_detector_centroid(img)
        err_cv.append(np.hypot(c.u - centre[0], c.v - centre[1]))
        assert b.diameter_px == pytest.approx(2 * r_out, rel=0.05)
    rms, rms_cv = np.sqrt(np.mean(np.square(err))), np.sqrt(np.mean(np.square(err_cv)))
    print(f"{kind} {np.dtype(dtype).name}: ours {rms:.4f} px RMS, SimpleBlobDetector {rms_cv:.4f} px RMS")
    assert rms <= 0.02


def test_slightly_elliptical_feature():
    rng = np.random.default_rng(2)
    err = []
    for _ in range(10):
        centre = rng.uniform(90, 110, 2)
        img = supersampled((200, 200), centre, 35.0, 20.0, rng=rng, axes=(1.0, 0.99))
        b = find_blob(img)
        err.append(np.hypot(b.u - centre[0], b.v - centre[1]))
    assert np.sqrt(np.mean(np.square(err))) <= 0.02


def test_accuracy_on_simulated_camera_frames(microcell_sim):
    """The sim's camera 1 frames (perspective, distortion, blur, noise): ≤ 0.05 px RMS against the truth."""
    world = World(microcell_sim)
    rng = np.random.default_rng(3)
    err, err_cv = [], []
    for k in range(20):
        world.begin_step(k)
        world.move_arm(Pose(0.040 + rng.uniform(-7e-3, 7e-3), 0.030 + rng.uniform(-5.5e-3, 5.5e-3), 0.0))
        image = world.capture("cam1", k + 1)
        truth = world.frame_truth[("cam1", k + 1)].features_px[0]
        b, c = find_blob(image), blob_detector_centroid(image)
        err.append(np.hypot(b.u - truth[0], b.v - truth[1]))
        err_cv.append(np.hypot(c.u - truth[0], c.v - truth[1]))
    rms = np.sqrt(np.mean(np.square(err)))
    print(f"camera 1 nozzle: ours {rms:.4f} px RMS, SimpleBlobDetector {np.sqrt(np.mean(np.square(err_cv))):.4f} px RMS")
    assert rms <= 0.05


def test_find_blobs_in_a_grid_of_spheres(microcell_sim):
    """Twelve spheres on area2, seen by the top camera: all found, at their true centres."""
    world = World(microcell_sim)
    for x in np.linspace(0.100, 0.120, 4):
        for y in np.linspace(0.033, 0.047, 3):
            world.add_sphere(x, y, 0.0, diameter=1.0e-3)
    world.move_arm(Pose(0.060, 0.030, 0.030))  # the arm out of the way
    image = world.capture("cam2", 1)
    truth = np.array(world.frame_truth[("cam2", 1)].features_px[1:])  # [0] is the nozzle, out of view
    blobs = find_blobs(image)
    assert len(blobs) == 12
    found = np.array([[b.u, b.v] for b in blobs])
    nearest = np.min(np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=2), axis=1)
    assert nearest.max() < 0.1


@pytest.mark.parametrize("make, message", [
    (lambda: np.full((100, 100), 20, np.uint8), "no bright feature"),
    (lambda: np.maximum(supersampled((200, 300), (80, 100), 30), supersampled((200, 300), (220, 100), 30)),
     "2 comparable bright features"),
    (lambda: supersampled((200, 200), (10, 100), 30), "cut by the image border"),
    (lambda: np.zeros((10, 10, 3), np.uint8), "2-D grayscale"),
    (lambda: np.full((10, 10), np.nan, np.float32), "NaN"),
    (lambda: np.zeros((10, 10), np.int64), "not supported; allowed: uint8, uint16"),
])
def test_bad_frames_are_clear_errors(make, message):
    with pytest.raises(VisionError, match=message):
        find_blob(make())


def test_dark_polarity_and_roi():
    img = 255 - supersampled((200, 300), (150.3, 99.6), 30)
    b = find_blob(img, polarity="dark", roi=(50, 0, 200, 200))
    assert (b.u, b.v) == pytest.approx((150.3, 99.6), abs=0.05)
    with pytest.raises(VisionError, match="not inside"):
        find_blob(img, roi=(250, 0, 100, 100))
