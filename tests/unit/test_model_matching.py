"""Line- and point-based model matching (seed 000 sections IV-V): Jacobians, solvers, covariance."""

from __future__ import annotations

import numpy as np
import pytest

from geometry.transforms import look_at, pose_matrix

from calibration.models.edge_model import EdgeModel
from calibration.models.model_matching import (
    CameraState,
    ObjectState,
    Observations,
    _Layout,
    ellipse_summary,
    error_ellipse,
    increment,
    line_residuals,
    numeric_jacobian,
    pose_error,
    residuals_and_jacobian,
    solve,
)

INCH = 0.0254


@pytest.fixture(scope="module")
def models():
    return EdgeModel.load("models/oru.json"), EdgeModel.load("models/receptacle.json")


def scene():
    """Two long-lens cameras 50 deg apart looking at an ORU 20 in in front of its receptacle."""
    target = np.array([0, 10, 0]) * INCH
    side = CameraState.centred(look_at(target + 7.5 * np.array([0.79, 0.55, 0.26]), target), 5183.0, 640, 480)
    top = CameraState.centred(look_at(target + 3.5 * np.array([0.33, 0.23, 0.91]), target), 2300.0, 640, 480)
    oru = ObjectState(pose_matrix([0.01, -0.02, 0.03], np.array([0.2, 20.0, 0.1]) * INCH), free=False)
    rec = ObjectState(pose_matrix([0.02, 0.01, -0.03], np.array([0.3, -0.2, 0.5]) * INCH))
    return [side, top], [oru, rec]


def line_obs(cams, objs, models, noise=0.0, rng=None) -> Observations:
    """Every model edge in both views, image endpoints taken at 20 % and 80 % along the true projection."""
    rng = rng or np.random.default_rng(0)
    parts = []
    for i, cam in enumerate(cams):
        for j, (obj, m) in enumerate(zip(objs, models)):
            P1, P2 = m.vertices[m.edges[:, 0]], m.vertices[m.edges[:, 1]]
            X1, X2 = P1 @ obj.M[:3, :3].T + obj.M[:3, 3], P2 @ obj.M[:3, :3].T + obj.M[:3, 3]
            a, b = cam.project(X1), cam.project(X2)
            Q1, Q2 = a + 0.2 * (b - a), a + 0.8 * (b - a)
            Q1 = Q1 + rng.normal(0, noise, Q1.shape) if noise else Q1
            Q2 = Q2 + rng.normal(0, noise, Q2.shape) if noise else Q2
            n = len(P1)
            W = np.repeat(np.eye(2)[None] / max(noise, 0.5) ** 2, n, axis=0)
            parts.append(Observations(np.full(n, i), np.full(n, j), P1, P2, Q1, Q2, W))
    return Observations.concat(parts)


def point_obs(cams, objs, models, noise=0.0, rng=None) -> Observations:
    rng = rng or np.random.default_rng(1)
    parts = []
    for i, cam in enumerate(cams):
        for j, (obj, m) in enumerate(zip(objs, models)):
            X = m.vertices
            uv = cam.project(X @ obj.M[:3, :3].T + obj.M[:3, 3])
            if noise:
                uv = uv + rng.normal(0, noise, uv.shape)
            W = np.repeat(np.eye(2)[None] / max(noise, 1.0) ** 2, len(X), axis=0)
            parts.append(Observations(point_cam=np.full(len(X), i), point_obj=np.full(len(X), j), X=X, uv=uv, point_W=W))
    return Observations.concat(parts)


def perturbed(cams, objs, rng, cam_free=(True, True), f_free=True, obj_free=True, size=1.0):
    new_cams = []
    for c, free in zip(cams, cam_free):
        V = increment(np.r_[rng.normal(0, 0.02 * size, 3), rng.normal(0, 0.004 * size, 3)]) @ c.V if free else c.V
        f = c.f * (1 + rng.normal(0, 0.02 * size)) if (free and f_free) else c.f
        new_cams.append(CameraState(V, f, c.cu, c.cv, free_pose=free, free_f=free and f_free))
    M = objs[1].M @ increment(np.r_[rng.normal(0, 0.5 * INCH * size, 3), rng.normal(0, 0.02 * size, 3)]) if obj_free else objs[1].M
    return new_cams, [objs[0], ObjectState(M, free=obj_free)]


@pytest.mark.parametrize("case", ["camera7", "camera6", "object6", "simultaneous20"])
@pytest.mark.parametrize("kind", ["lines", "points"])
def test_jacobian_matches_central_differences(models, case, kind):
    cams, objs = scene()
    rng = np.random.default_rng(3)
    free = {"camera7": ((True, False), True, False), "camera6": ((True, False), False, False),
            "object6": ((False, False), False, True), "simultaneous20": ((True, True), True, True)}[case]
    cams, objs = perturbed(cams, objs, rng, free[0], free[1], free[2])
    obs = (line_obs if kind == "lines" else point_obs)(*scene(), models)
    layout = _Layout(cams, objs)
    assert layout.n == {"camera7": 7, "camera6": 6, "object6": 6, "simultaneous20": 20}[case]
    _, J, _ = residuals_and_jacobian(cams, objs, obs, layout)
    J = J.reshape(-1, layout.n)
    Jn = numeric_jacobian(cams, objs, obs)
    scale = np.abs(Jn).max(axis=0)
    assert np.all(scale > 0)
    np.testing.assert_allclose(J / scale, Jn / scale, atol=2e-5)


def test_line_residual_is_the_normal_distance():
    a, b = np.array([[10.0, 10.0]]), np.array([[110.0, 10.0]])  # horizontal model line
    h, dh = line_residuals(a, b, np.array([[30.0, 13.0]]), np.array([[90.0, 7.5]]))
    np.testing.assert_allclose(np.abs(h), [[3.0, 2.5]])
    assert np.sign(h[0, 0]) != np.sign(h[0, 1])
    # derivative against finite differences of the endpoints
    eps = 1e-6
    for k in range(4):
        d = np.zeros(4)
        d[k] = eps
        hp, _ = line_residuals(a + d[:2], b + d[2:], np.array([[30.0, 13.0]]), np.array([[90.0, 7.5]]), False)
        hm, _ = line_residuals(a - d[:2], b - d[2:], np.array([[30.0, 13.0]]), np.array([[90.0, 7.5]]), False)
        np.testing.assert_allclose(dh[0, :, k], ((hp - hm) / (2 * eps))[0], atol=1e-6)


@pytest.mark.parametrize("case,kind", [("camera7", "points"), ("camera7", "lines"), ("camera6", "lines"),
                                       ("object6", "lines"), ("object6", "points"), ("simultaneous20", "lines"),
                                       ("simultaneous20", "points")])
def test_solver_recovers_a_synthetic_truth(models, case, kind):
    truth_cams, truth_objs = scene()
    obs = (line_obs if kind == "lines" else point_obs)(truth_cams, truth_objs, models)
    if case.startswith("camera"):  # camera calibration on the ORU alone, as the sequential update does
        obs = obs.select(cams=[0], objs=[0])
    free = {"camera7": ((True, False), True, False), "camera6": ((True, False), False, False),
            "object6": ((False, False), False, True), "simultaneous20": ((True, True), True, True)}[case]
    cams, objs = perturbed(truth_cams, truth_objs, np.random.default_rng(7), *free)
    res = solve(cams, objs, obs)
    assert res.converged and res.rms_px < 1e-4
    if case == "simultaneous20":
        # one frame is fixed (the ORU): the solution is then unique
        assert res.covariance.shape == (20, 20)
    for c, t in zip(res.cameras, truth_cams):
        np.testing.assert_allclose(pose_error(np.linalg.inv(c.V), np.linalg.inv(t.V)), 0, atol=1e-6)
        assert c.f == pytest.approx(t.f, rel=1e-6)
    np.testing.assert_allclose(pose_error(res.objects[1].M, truth_objs[1].M), 0, atol=1e-7)


def test_predicted_covariance_matches_the_spread_of_repeated_solutions(models):
    """Object localisation from noisy points, many times: the spread matches (J^T W J)^-1."""
    truth_cams, truth_objs = scene()
    truth_cams = [CameraState(c.V, c.f, c.cu, c.cv, free_pose=False, free_f=False) for c in truth_cams]
    rng = np.random.default_rng(11)
    errors, predicted = [], None
    for _ in range(150):
        obs = point_obs(truth_cams, truth_objs, models, noise=1.5, rng=rng).select(objs=[1])
        res = solve(truth_cams, [truth_objs[0], ObjectState(truth_objs[1].M @ increment([0.002, 0, 0, 0, 0.005, 0]))],
                    obs)
        errors.append(pose_error(res.objects[1].M, truth_objs[1].M))
        predicted = res.covariance
    spread = np.std(errors, axis=0)
    ratio = spread / np.sqrt(np.diag(predicted))
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio


def test_incremental_form_keeps_the_fixed_object_and_moves_the_free_ones(models):
    truth_cams, truth_objs = scene()
    cams, objs = perturbed(truth_cams, truth_objs, np.random.default_rng(5))
    res = solve(cams, objs, line_obs(truth_cams, truth_objs, models))
    assert np.array_equal(res.objects[0].M, objs[0].M)
    assert res.names[:7] == ["cam0.tx", "cam0.ty", "cam0.tz", "cam0.rx", "cam0.ry", "cam0.rz", "cam0.f_rel"]
    assert res.names[-6:] == ["obj1.tx", "obj1.ty", "obj1.tz", "obj1.rx", "obj1.ry", "obj1.rz"]


def test_too_few_measurements_are_refused(models):
    cams, objs = scene()
    obs = point_obs(cams, objs, models).select(cams=[0], objs=[1])
    few = Observations(point_cam=obs.point_cam[:2], point_obj=obs.point_obj[:2], X=obs.X[:2], uv=obs.uv[:2],
                       point_W=obs.point_W[:2])
    with pytest.raises(ValueError, match="equations for 20 unknowns"):
        solve(cams, objs, few)


def test_error_ellipse_satisfies_eq_52():
    cov = np.array([[4.0, 1.2, 0], [1.2, 1.0, 0], [0, 0, 9.0]])
    pts = error_ellipse(cov, 0, 1)
    s = ellipse_summary(cov, 0, 1)
    x, y = pts[:, 0] / s["sigma_i"], pts[:, 1] / s["sigma_j"]
    np.testing.assert_allclose(x**2 - 2 * s["rho"] * x * y + y**2, 1 - s["rho"] ** 2, atol=1e-9)
    assert s["rho"] == pytest.approx(0.6)


def test_jacobian_of_mixed_shuffled_measurements_matches_central_differences(models):
    """Lines and points together, in no order of camera or object: each row's derivatives land in its own
    camera's and object's columns."""
    cams, objs = perturbed(*scene(), np.random.default_rng(8))
    lines = line_obs(*scene(), models)
    order = np.random.default_rng(9).permutation(lines.n_lines)
    obs = Observations.concat([lines.select_lines(np.ones(lines.n_lines, bool)), point_obs(*scene(), models)])
    obs = Observations(obs.line_cam[order], obs.line_obj[order], obs.P1[order], obs.P2[order], obs.Q1[order],
                       obs.Q2[order], obs.line_W[order], obs.point_cam[::-1], obs.point_obj[::-1], obs.X[::-1],
                       obs.uv[::-1], obs.point_W[::-1])
    layout = _Layout(cams, objs)
    r, J, W = residuals_and_jacobian(cams, objs, obs, layout)
    Jn = numeric_jacobian(cams, objs, obs)
    scale = np.abs(Jn).max(axis=0)
    np.testing.assert_allclose(J.reshape(-1, layout.n) / scale, Jn / scale, atol=2e-5)
    # without the Jacobian: the same residuals and weights
    r2, J2, W2 = residuals_and_jacobian(cams, objs, obs, layout, with_jacobian=False)
    assert J2 is None
    np.testing.assert_array_equal(r2, r)
    np.testing.assert_array_equal(W2, W)


@pytest.mark.parametrize("size", [0.0, 1e-12, 1e-7, 1e-3, 0.3, 3.0])
def test_increment_is_the_pose_of_a_rotation_vector(size):
    xi = np.r_[0.1, -0.2, 0.3, np.array([0.3, -0.5, 0.8]) * size]
    np.testing.assert_allclose(increment(xi), pose_matrix(xi[3:], xi[:3]), rtol=0, atol=1e-15)
