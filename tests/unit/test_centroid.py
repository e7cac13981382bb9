"""Sub-pixel centroid (calibration.vision.centroid) on frames rendered here, independently of
the package: coverage by 8x8 supersampling, Gaussian blur sigma 1 px, noise 1 % of full
scale, quantised to uint8 or uint16 (background 20/255, feature 200/255 of full scale)."""

import cv2
import numpy as np
import pytest

from calibration.errors import VisionError
from calibration.vision.centroid import Blob, blob_detector_centroid, find_blob, find_blobs

NOZZLE = (37.5, 20.0)  # outer, inner radius, px: a bright ring with a dark hole
SPHERE = (75.0, 0.0)  # a bright disc
BACKGROUND, FEATURE = 20 / 255, 200 / 255  # fractions of full scale


def render(features, size=(300, 300), dtype=np.uint8, rng=None, axes=1.0, angle=0.0, slope=(0.0, 0.0),
           levels=(BACKGROUND, FEATURE), ss=8):
    """features: [((u, v), r_out, r_in)]; axes < 1 squeezes the minor axis, turned by angle (rad);
    slope: background gradient in full scale per px along (u, v), zero at the frame's centre."""
    rng = rng if rng is not None else np.random.default_rng(0)
    h, w = size
    cover = np.zeros(size)
    sub = (np.arange(ss) + 0.5) / ss - 0.5  # sub-sample offsets from the pixel centre
    for (cu, cv), r_out, r_in in features:
        u0, u1 = max(int(cu - r_out) - 3, 0), min(int(cu + r_out) + 4, w)
        v0, v1 = max(int(cv - r_out) - 3, 0), min(int(cv + r_out) + 4, h)
        du = (np.arange(u0, u1)[:, None] + sub).ravel()[None, :] - cu
        dv = (np.arange(v0, v1)[:, None] + sub).ravel()[:, None] - cv
        p = du * np.cos(angle) + dv * np.sin(angle)
        q = (-du * np.sin(angle) + dv * np.cos(angle)) / axes
        r2 = p * p + q * q
        inside = (r2 <= r_out**2) & (r2 >= r_in**2)
        cover[v0:v1, u0:u1] += inside.reshape(v1 - v0, ss, u1 - u0, ss).mean(axis=(1, 3))
    rows, cols = np.indices(size)
    img = levels[0] + (levels[1] - levels[0]) * cover + slope[0] * (cols - w / 2) + slope[1] * (rows - h / 2)
    img = cv2.GaussianBlur(img, (0, 0), 1.0) + rng.normal(0.0, 0.01, size)
    full = np.iinfo(dtype).max
    return np.clip(np.rint(img * full), 0, full).astype(dtype)


def rms(errors) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def error(blob: Blob, centre) -> float:
    return float(np.hypot(blob.u - centre[0], blob.v - centre[1]))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("name, radii", [("nozzle", NOZZLE), ("sphere", SPHERE)])
def test_accuracy_against_the_true_centre(name, radii, dtype):
    rng = np.random.default_rng(10)
    ours, theirs = [], []
    for _ in range(30):
        centre = rng.uniform(140, 160, 2)
        img = render([(centre, *radii)], dtype=dtype, rng=rng)
        blob = find_blob(img)
        ours.append(error(blob, centre))
        theirs.append(error(blob_detector_centroid(img), centre))
        assert blob.diameter_px == pytest.approx(2 * radii[0], rel=0.005)
        assert blob.contrast == pytest.approx((FEATURE - BACKGROUND) * np.iinfo(dtype).max, rel=0.02)
        assert 50 < blob.snr < 90  # true 70
    assert rms(ours) <= 0.05
    # On a clean, flat-background disc SimpleBlobDetector (fed 21 well-placed levels) is at the
    # noise floor too; ours is clearly better on the ring and on a sloping background (below).
    assert rms(ours) < rms(theirs) * (1.0 if name == "nozzle" else 1.1)


@pytest.mark.parametrize("name, radii", [("nozzle", NOZZLE), ("sphere", SPHERE)])
def test_slightly_elliptical_feature_is_measured_at_its_centre(name, radii):
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(15):
        centre = rng.uniform(140, 160, 2)
        img = render([(centre, *radii)], rng=rng, axes=0.99, angle=rng.uniform(0, np.pi))
        errors.append(error(find_blob(img), centre))
    assert rms(errors) <= 0.05


@pytest.mark.parametrize("name, radii", [("nozzle", NOZZLE), ("sphere", SPHERE)])
def test_slowly_varying_background_does_not_pull_the_centre(name, radii):
    rng = np.random.default_rng(12)
    ours, theirs = [], []
    for _ in range(15):
        centre = rng.uniform(140, 160, 2)
        slope = rng.uniform(-3e-4, 3e-4, 2)  # up to 0.3 % of full scale per 10 px, 9 % across the frame
        img = render([(centre, *radii)], rng=rng, slope=slope, levels=(50 / 255, 230 / 255))  # never clipped
        ours.append(error(find_blob(img), centre))
        theirs.append(error(blob_detector_centroid(img), centre))
    assert rms(ours) <= 0.05
    assert rms(ours) < rms(theirs) / 1.5


def test_find_blobs_finds_a_grid_of_spheres_row_by_row():
    rng = np.random.default_rng(13)
    truth = [(150 + 200 * i + rng.uniform(-2, 2), 150 + 200 * j + rng.uniform(-2, 2))
             for j in range(3) for i in range(4)]  # row-major, rows slightly uneven
    img = render([(c, *SPHERE) for c in truth], size=(700, 900), rng=rng)
    blobs = find_blobs(img)
    assert len(blobs) == 12
    found = np.array([(b.u, b.v) for b in blobs])
    assert np.abs(found - np.array(truth)).max() < 0.02  # same order and at the true centres
    assert all(b.diameter_px == pytest.approx(150, rel=0.005) for b in blobs)


def test_find_blobs_skips_features_cut_by_the_border_and_returns_none_for_a_blank_frame():
    img = render([((100.3, 150.2), *NOZZLE), ((290.0, 150.0), *NOZZLE)], size=(300, 300))
    (blob,) = find_blobs(img)
    assert (blob.u, blob.v) == pytest.approx((100.3, 150.2), abs=0.02)
    assert find_blobs(render([], size=(100, 100))) == []


def test_full_size_frame():
    rng = np.random.default_rng(14)
    centre = rng.uniform([200, 200], [2248, 1850])
    img = render([(centre, *NOZZLE)], size=(2050, 2448), dtype=np.uint16, rng=rng)
    blob = find_blob(img)
    assert error(blob, centre) <= 0.05


def test_dark_feature_and_roi():
    img = np.iinfo(np.uint8).max - render([((90.4, 100.7), *NOZZLE), ((250.2, 99.1), *NOZZLE)], size=(200, 350))
    with pytest.raises(VisionError, match=r"2 comparable dark features found, at \(u, v\) ≈ \(\d+, \d+\), \(\d+, "):
        find_blob(img, polarity="dark")
    blob = find_blob(img, polarity="dark", roi=(170, 0, 180, 200))
    assert (blob.u, blob.v) == pytest.approx((250.2, 99.1), abs=0.02)
    with pytest.raises(VisionError, match="not inside the 350x200 image"):
        find_blob(img, roi=(300, 0, 100, 100))


@pytest.mark.parametrize("make, message", [
    (lambda: render([], size=(200, 200)), r"no bright feature of diameter ≥ 10 px found; background 20\.0"),
    (lambda: render([((80, 100), 30, 0), ((220, 100), 30, 0)], size=(200, 300)), "2 comparable bright features"),
    (lambda: render([((12, 100), 30, 0)], size=(200, 200)), "cut by the image border"),
    (lambda: np.zeros((50, 50, 3), np.uint8), r"2-D grayscale array, got shape \(50, 50, 3\)"),
    (lambda: np.full((50, 50), np.nan, np.float32), "NaN"),
    (lambda: np.zeros((50, 50), np.int64), "dtype int64 not supported; allowed: uint8, uint16, float32, float64"),
    (lambda: np.zeros((0, 50), np.uint8), "empty"),
    (lambda: [[0, 1], [2, 3]], "numpy array"),
])
def test_frames_that_cannot_be_measured_are_clear_errors(make, message):
    with pytest.raises(VisionError, match=message):
        find_blob(make())
