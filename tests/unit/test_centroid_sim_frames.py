"""The centroid on frames of the simulated cameras (perspective, distortion, blur, noise), against the
truth the world knows. The centroid on independently rendered features is tested in test_centroid.py."""

import numpy as np

from drivers.interfaces import Pose
from drivers.sim.micro.world import World

from calibration.vision.centroid import blob_detector_centroid, find_blob, find_blobs


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
