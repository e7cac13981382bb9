"""The simulated cameras render only the pixels a feature can reach, and render them as an exact trace would.

The reference here is the plain renderer: every pixel of a feature's window traced back through the true
camera's exact inverse, blurred at full resolution. The fast one interpolates the inverse distortion between
exact grid points and renders far-defocused features coarser; noise-free, the two must agree to under a grey
level and their features' centroids to two thousandths of a pixel.
"""

import cv2
import numpy as np
import pytest

from drivers.interfaces import Pose
from drivers.sim.micro.world import World
from drivers.sim.render import COARSE_ABOVE_SIGMA_PX, NoiseBank, _blur_sigma, _contrast, _covers_view, render


def reference_render(camera, cfg, discs) -> np.ndarray:
    image = np.full((camera.height, camera.width), cfg.background, dtype=np.float64)
    for disc in discs:
        depth = camera.depth_of(disc.centre)
        mpp, sigma = depth / camera.fx, _blur_sigma(camera, cfg, depth)
        c = camera.project(disc.centre)[0]
        half = disc.outer_radius / mpp * 1.05 + 4 * sigma + 3
        u0, u1 = int(np.floor(c[0] - half)), int(np.ceil(c[0] + half)) + 1
        v0, v1 = int(np.floor(c[1] - half)), int(np.ceil(c[1] + half)) + 1
        if max(u0, 0) >= min(u1, camera.width) or max(v0, 0) >= min(v1, camera.height):
            continue
        if disc.inner_radius == 0 and _covers_view(camera, disc, mpp):
            image += _contrast(cfg, disc)
            continue
        uu, vv = np.meshgrid(np.arange(u0, u1, dtype=float), np.arange(v0, v1, dtype=float))
        plane = camera.backproject_to_plane(np.column_stack([uu.ravel(), vv.ravel()]), disc.centre[2])
        r = np.hypot(plane[:, 0] - disc.centre[0], plane[:, 1] - disc.centre[1]).reshape(uu.shape) / mpp
        cover = np.clip(disc.outer_radius / mpp - r + 0.5, 0, 1)
        if disc.inner_radius > 0:
            cover -= np.clip(disc.inner_radius / mpp - r + 0.5, 0, 1)
        patch = cv2.GaussianBlur(cover * _contrast(cfg, disc), (0, 0), sigmaX=sigma, borderType=cv2.BORDER_CONSTANT)
        cu0, cu1, cv0, cv1 = max(u0, 0), min(u1, camera.width), max(v0, 0), min(v1, camera.height)
        image[cv0:cv1, cu0:cu1] += patch[cv0 - v0:cv1 - v0, cu0 - u0:cu1 - u0]
    return np.clip(image, 0, 1) * (255 if cfg.bit_depth == 8 else 65535)


def local_centroid(image: np.ndarray, camera, disc) -> np.ndarray:
    """Intensity centroid of a feature's neighbourhood over its local background."""
    u, v = camera.project(disc.centre)[0]
    half = int(disc.outer_radius / (camera.depth_of(disc.centre) / camera.fx) * 1.5) + 6
    u0, v0 = max(int(u) - half, 0), max(int(v) - half, 0)
    window = image[v0:int(v) + half, u0:int(u) + half].astype(float)
    w = np.abs(window - np.median(np.concatenate([window[0], window[-1], window[:, 0], window[:, -1]])))
    vv, uu = np.indices(window.shape)
    return np.array([(w * uu).sum() / w.sum() + u0, (w * vv).sum() / w.sum() + v0])


def scene(microcell_sim, where: str):
    world = World(microcell_sim)
    if where == "cam1 nozzle ring":
        world.move_arm(Pose(0.0405, 0.0302, 0.0))
        return world, "cam1"
    if where == "cam1 dot grid":
        world.set_fixture("grid-area1", True)
        world.move_arm(Pose(0.040, 0.030, 0.020))  # the nozzle far above: out of focus, behind the grid
        return world, "cam1"
    if where == "cam2 sphere":
        world.add_sphere(0.1103, 0.0398, 0.0)
        world.move_arm(Pose(0.110, 0.040, 0.015))
        return world, "cam2"
    if where == "cam3 sphere out of focus":
        world.add_sphere(0.0352, 0.0050, 0.0)
        world.move_arm(Pose(0.010, 0.000, 0.0))  # cam3 focuses 20 mm below the tip: the floor sphere is blurred
        return world, "cam3"
    raise AssertionError(where)


@pytest.mark.parametrize("where", ["cam1 nozzle ring", "cam1 dot grid", "cam2 sphere", "cam3 sphere out of focus"])
def test_fast_render_matches_the_exact_trace(microcell_sim, where):
    world, name = scene(microcell_sim, where)
    # noise-free, and 16-bit so that rounding does not hide what the renderers do
    cfg = world.config.cameras[name].model_copy(update={"noise_pct": 0.0, "bit_depth": 16})
    camera = world.camera_now(name)
    discs = [d for d in world.features() if not (cfg.mounted_on_arm and d.inner_radius > 0)]
    bank = NoiseBank(camera.width, camera.height, cfg.noise_pct, cfg.bit_depth, np.random.default_rng(0))
    fast = render(camera, cfg, discs, np.random.default_rng(1), bank) / 65535
    exact = reference_render(camera, cfg, discs) / 65535
    # the interpolated distortion changes nothing visible; the coarse rendering of a far-defocused feature
    # (blur >= 16 px) up to a quarter of an 8-bit grey level, a tenth of the sensor noise
    assert np.abs(fast - exact).max() <= 0.25 / 255
    checked = 0
    for disc in discs:  # the features in focus, which the routines measure: where their centres are
        u, v = camera.project(disc.centre)[0]
        depth = camera.depth_of(disc.centre)
        inside = 0 <= u < camera.width and 0 <= v < camera.height
        sharp = _blur_sigma(camera, cfg, depth) <= COARSE_ABOVE_SIGMA_PX
        if inside and sharp and not (disc.inner_radius == 0 and _covers_view(camera, disc, depth / camera.fx)):
            checked += 1
            np.testing.assert_allclose(local_centroid(fast, camera, disc), local_centroid(exact, camera, disc),
                                       atol=2e-3)
    assert checked >= (where != "cam3 sphere out of focus")


def test_noise_is_fresh_where_features_are_and_banked_elsewhere(microcell_sim):
    world, name = scene(microcell_sim, "cam2 sphere")
    cfg = world.config.cameras[name]
    camera = world.camera_now(name)
    discs = world.features()
    bank = NoiseBank(camera.width, camera.height, cfg.noise_pct, cfg.bit_depth, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    a, b = (render(camera, cfg, discs, rng, bank).astype(float) for _ in range(2))
    u, v = np.round(camera.project(discs[-1].centre)[0]).astype(int)
    near = (slice(v - 5, v + 5), slice(u - 5, u + 5))
    assert np.std(a[near] - b[near]) > 0  # fresh noise on the feature in every frame
    full_scale = 255
    assert np.std(a[:100, :100]) == pytest.approx(cfg.noise_pct / 100 * full_scale, rel=0.2)  # noisy background


@pytest.mark.parametrize("name", ["cam1", "cam3"])
def test_interpolated_inverse_distortion_is_the_exact_one(microcell_sim, name):
    camera = World(microcell_sim).cameras[name]
    us, vs = np.arange(0, camera.width, 3.0), np.arange(5, camera.height, 7.0)  # a whole frame, strided
    x, y = camera.undistort_grid(us, vs)
    uu, vv = np.meshgrid(us, vs)
    xe, ye = camera.undistort(np.column_stack([uu.ravel(), vv.ravel()]))
    assert np.abs(x.ravel() - xe).max() * camera.fx < 1e-6  # px
    assert np.abs(y.ravel() - ye).max() * camera.fy < 1e-6
