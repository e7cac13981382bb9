"""The local line detector of seed 000 section III, on rendered step edges."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.vision.lines import (
    SOBEL_NOISE_GAIN,
    depth_buffer,
    detect_lines,
    edge_image,
    estimate_noise,
    visible_segments,
)

W, H = 240, 180


def step_image(p0, angle, *, levels=(0.2, 0.7), extra=None, noise=0.01, blur=0.8, rng=None, s=8):
    """An anti-aliased step edge through p0 with normal `angle` (brighter on the normal's side); `extra`: a second
    edge (offset px along the normal, level beyond it)."""
    rng = rng or np.random.default_rng(0)
    n = np.array([np.cos(angle), np.sin(angle)])
    ys, xs = np.mgrid[0:H * s, 0:W * s]
    u, v = (xs - (s - 1) / 2) / s, (ys - (s - 1) / 2) / s
    d = (u - p0[0]) * n[0] + (v - p0[1]) * n[1]
    fine = np.where(d > 0, levels[1], levels[0]).astype(np.float32)
    if extra is not None:
        fine = np.where(d > extra[0], extra[1], fine).astype(np.float32)
    img = cv2.resize(fine, (W, H), interpolation=cv2.INTER_AREA)
    img = (cv2.GaussianBlur(img, (0, 0), blur) if blur > 0 else img) + rng.standard_normal((H, W)).astype(np.float32) * noise
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), n


def predicted_segment(p0, n, offset, half=30.0):
    t = np.array([-n[1], n[0]])
    return p0 - half * t + offset * n, p0 + half * t + offset * n


@pytest.mark.parametrize("angle_deg", [0, 12, 30, 45, 62, 90, 135, 171, 250])
def test_finds_a_step_edge_to_a_twentieth_of_a_pixel(angle_deg):
    p0 = np.array([120.3, 90.6])
    img, n = step_image(p0, np.radians(angle_deg))
    A, B = predicted_segment(p0, n, offset=4.0)
    m = detect_lines(img, A[None], B[None])
    assert m.ok[0] and m.n_points[0] >= 20
    # the image line's endpoints lie on the true edge
    for Q in (m.Q1[0], m.Q2[0]):
        assert abs((Q - p0) @ n) < 0.05
    # h is measured along (-s, c) of the model line (eq. 8): here the edge is 4 px back along -n
    d = (B - A) / np.linalg.norm(B - A)
    assert np.allclose(m.h[0], -4.0 * (n @ np.array([-d[1], d[0]])), atol=0.06)


def test_weights_follow_eqs_2_to_4_and_11():
    p0 = np.array([120.0, 90.0])
    img, n = step_image(p0, 0.3)
    A, B = predicted_segment(p0, n, offset=2.0)
    m = detect_lines(img, A[None], B[None], sigma_sys=0.5)
    W_img = m.W_img[0]
    assert np.all(np.linalg.eigvalsh(W_img) > 0)
    # eq. 11 equals eq. 10
    np.testing.assert_allclose(m.W[0], np.linalg.inv(np.linalg.inv(W_img) + 0.25 * np.eye(2)), rtol=1e-9)
    # a good straight edge: the image measurement alone is far below a pixel, the systematic term dominates
    assert np.sqrt(np.linalg.inv(W_img).diagonal()).max() < 0.1
    assert np.sqrt(np.linalg.inv(m.W[0]).diagonal()).min() >= 0.5
    # noisier image: larger variances (smaller image weights)
    noisy, _ = step_image(p0, 0.3, noise=0.05, rng=np.random.default_rng(4))
    m2 = detect_lines(noisy, A[None], B[None], sigma_sys=0.5)
    assert np.trace(m2.W_img[0]) < np.trace(W_img) / 5


def test_the_nearest_of_two_parallel_edges_wins():
    p0 = np.array([120.0, 90.0])
    img, n = step_image(p0, np.radians(20), levels=(0.2, 0.5), extra=(9.0, 0.9))  # a stronger edge 9 px further
    for offset, expected in ((2.0, 0.0), (7.0, 9.0)):
        A, B = predicted_segment(p0, n, offset=offset)
        m = detect_lines(img, A[None], B[None])
        assert m.ok[0]
        assert abs((m.Q1[0] - p0) @ n - expected) < 0.15, offset


def test_no_edge_no_line():
    img = (np.random.default_rng(2).normal(0.3, 0.01, (H, W)) * 255).astype(np.uint8)
    m = detect_lines(img, np.array([[60.0, 60.0]]), np.array([[160.0, 80.0]]))
    assert not m.ok[0]


def test_blooming_term_when_one_side_is_saturated():
    p0 = np.array([120.0, 90.0])
    img, n = step_image(p0, 0.5, levels=(0.2, 1.2))  # over-exposed side
    A, B = predicted_segment(p0, n, offset=1.0)
    plain = detect_lines(img, A[None], B[None], blooming=False)
    bloom = detect_lines(img, A[None], B[None], blooming=True, sigma_bloom=2.0)
    assert bloom.bloomed[0] and not plain.bloomed[0]
    np.testing.assert_allclose(bloom.W[0], np.linalg.inv(np.linalg.inv(bloom.W_img[0]) + (0.25 + 4.0) * np.eye(2)),
                               rtol=1e-9)
    normal_img, _ = step_image(p0, 0.5)
    assert not detect_lines(normal_img, A[None], B[None], blooming=True).bloomed[0]


def test_noise_estimate():
    img, _ = step_image(np.array([120.0, 90.0]), 0.2, noise=0.02, blur=0.0)
    assert estimate_noise(img) == pytest.approx(0.02 * 255, rel=0.25)


def cube(centre, half):
    c = np.asarray(centre, float)
    v = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)]) * half + c
    faces = [[0, 2, 6, 4], [1, 5, 7, 3], [0, 4, 5, 1], [2, 3, 7, 6], [0, 1, 3, 2], [4, 6, 7, 5]]
    return v, [np.array(f[::-1]) for f in faces]


def test_z_buffer_hides_what_lies_behind():
    f, cu, cv = 500.0, (W - 1) / 2, (H - 1) / 2
    near_v, near_f = cube([0.0, 0.0, 2.0], 0.1)  # camera coordinates, z forward
    far_v, far_f = cube([0.15, 0.0, 3.0], 0.2)
    z = depth_buffer(W, H, [near_v[k] for k in near_f] + [far_v[k] for k in far_f], f, cu, cv)
    assert z[int(cv), int(cu)] == pytest.approx(1.9, abs=1e-6)  # the near cube's front face
    assert np.isinf(z[2, 2])
    # a vertical edge of the far cube passes behind the near cube: only its parts clear of it are visible
    E1, E2 = np.array([[-0.05, -0.2, 2.8]]), np.array([[-0.05, 0.2, 2.8]])
    segs = visible_segments(z, E1, E2, f, cu, cv, segment_px=5.0, margin_px=2)
    total = int(round(np.linalg.norm(f * (E2[0, :2] - E1[0, :2]) / 2.8) / 5.0))
    assert 0 < len(segs) < total
    # the near cube's own front edge is visible along its whole length
    E1, E2 = np.array([[-0.1, -0.1, 1.9]]), np.array([[-0.1, 0.1, 1.9]])
    segs = visible_segments(z, E1, E2, f, cu, cv, segment_px=5.0, margin_px=2)
    assert len(segs) == int(round(np.linalg.norm(f * (E2[0, :2] - E1[0, :2]) / 1.9) / 5.0))


def test_segments_together_are_measured_as_each_alone():
    """All segments are processed in one pass: none may change another's result, at any angle, near or across
    the image border, too short or without an edge."""
    rng = np.random.default_rng(3)
    p0 = np.array([120.0, 90.0])
    img, n = step_image(p0, 0.4, levels=(0.2, 1.2), extra=(6.0, 0.5), noise=0.02, rng=rng)  # saturated side too
    centres = np.vstack([p0 + rng.uniform(-12, 12, (30, 2)), rng.uniform([-10, -10], [W + 10, H + 10], (20, 2))])
    angles = np.r_[np.full(30, 0.4 + np.pi / 2), rng.uniform(0, 2 * np.pi, 20)] + rng.normal(0, 0.05, 50)
    lengths = rng.uniform(2, 50, 50)
    d = np.column_stack([np.cos(angles), np.sin(angles)]) * lengths[:, None] / 2
    A, B = centres - d, centres + d
    together = detect_lines(img, A, B)
    assert 10 <= together.ok.sum() < 50 and together.bloomed.any()
    for i in range(len(A)):
        alone = detect_lines(img, A[i:i + 1], B[i:i + 1])
        for name in ("ok", "n_points", "bloomed"):
            assert getattr(alone, name)[0] == getattr(together, name)[i], (i, name)
        for name in ("Q1", "Q2", "h", "W_img", "W"):
            np.testing.assert_allclose(getattr(alone, name)[0], getattr(together, name)[i], rtol=1e-12, atol=1e-12)


def test_an_edge_image_made_once_serves_every_detection():
    p0 = np.array([120.0, 90.0])
    img, n = step_image(p0, 0.7)
    A, B = predicted_segment(p0, n, offset=3.0)
    prepared = edge_image(img)
    for a, b in ((A, B), (A + 5, B + 5)):
        direct, reused = detect_lines(img, a[None], b[None]), detect_lines(prepared, a[None], b[None])
        assert direct.ok[0] and reused.ok[0]
        np.testing.assert_array_equal(direct.h, reused.h)
        np.testing.assert_array_equal(direct.W, reused.W)


@pytest.mark.parametrize("noise", [0.0, 0.003, 0.02, 0.5, 3.0])
def test_noise_estimate_is_the_median_sobel_response(noise):
    """The 8-bit shortcut (a histogram) gives np.median's value, also where the median is beyond 255."""
    img, _ = step_image(np.array([120.0, 90.0]), 0.2, noise=noise, blur=0.0, rng=np.random.default_rng(6))
    g = cv2.Sobel(img.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    assert estimate_noise(img) == max(1.4826 * float(np.median(np.abs(g))) / SOBEL_NOISE_GAIN, 0.3)


@pytest.mark.parametrize("margin", [0, 2, 25])
def test_visibility_takes_the_largest_depth_around_each_test_point(margin):
    """A test point is seen when it is no deeper than the deepest face in its 3x3 neighbourhood (so points on a
    face's border are seen), also at the image border."""
    rng = np.random.default_rng(margin)
    f, cu, cv = 300.0, (W - 1) / 2, (H - 1) / 2
    faces = []
    for _ in range(4):
        v, fl = cube(rng.uniform([-0.5, -0.4, 1.0], [0.5, 0.4, 3.0]), rng.uniform(0.05, 0.4))
        faces += [v[k] for k in fl]
    z = depth_buffer(W, H, faces, f, cu, cv)
    zmax = cv2.dilate(np.where(np.isfinite(z), z, 1e30).astype(np.float32), np.ones((3, 3), np.uint8))
    E1, E2 = (rng.uniform([-0.8, -0.6, 0.8], [0.8, 0.6, 3.5], (40, 3)) for _ in range(2))
    expected = []
    for k, (a, b) in enumerate(zip(E1, E2)):
        n_seg = max(1, int(round(np.linalg.norm(f * (b[:2] / b[2] - a[:2] / a[2])) / 7.0)))
        for s in range(n_seg):
            P = a + (s + np.array([0.1, 0.3, 0.5, 0.7, 0.9]))[:, None] / n_seg * (b - a)
            u, v = np.round(f * P[:, 0] / P[:, 2] + cu).astype(int), np.round(f * P[:, 1] / P[:, 2] + cv).astype(int)
            inside = (u >= margin) & (u < W - margin) & (v >= margin) & (v < H - margin)
            seen = P[inside, 2] <= zmax[v[inside], u[inside]] * (1 + 0.005)
            if inside.sum() >= 4 and seen.sum() >= 4:
                expected.append(k)
    got = [k for k, _, _ in visible_segments(z, E1, E2, f, cu, cv, segment_px=7.0, margin_px=margin)]
    assert got == expected and 0 < len(got)
