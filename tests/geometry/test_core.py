"""Exact checks of the shared numpy geometry: rotations, Sim3 (Umeyama + RANSAC), camera models."""

import numpy as np
import pytest

from mvrecon.geometry import camera, rotation, sim3


def random_rotation(rng):
    return rotation.angle_axis_to_rotmat(rng.normal(size=3))


def test_quaternion_round_trip_including_half_turns():
    rng = np.random.default_rng(1)
    for R in [random_rotation(rng) for _ in range(20)] + [rotation.angle_axis_to_rotmat([np.pi, 0, 0]),
                                                           rotation.angle_axis_to_rotmat([0, np.pi, 0])]:
        q = rotation.rotmat_to_quat(R)
        assert q[0] >= 0 and np.isclose(np.linalg.norm(q), 1)
        np.testing.assert_allclose(rotation.quat_to_rotmat(q), R, atol=1e-12)


def test_rotation_error_and_vector_angle():
    R = rotation.angle_axis_to_rotmat([0, 0, np.radians(7.5)])
    assert rotation.rotation_error_deg(R, np.eye(3)) == pytest.approx(7.5)
    assert rotation.vector_angle_deg([1, 0, 0], [0, 2, 0]) == pytest.approx(90)
    assert rotation.vector_angle_deg([0, 0, 0], [1, 0, 0]) == 180.0


def test_umeyama_recovers_similarity_exactly():
    rng = np.random.default_rng(2)
    T = sim3.Sim3(3.7, random_rotation(rng), rng.normal(size=3))
    X = rng.normal(size=(30, 3))
    est = sim3.umeyama(X, T.apply(X))
    assert est.scale == pytest.approx(3.7)
    np.testing.assert_allclose(est.R, T.R, atol=1e-10)
    np.testing.assert_allclose(est.inverse().apply(T.apply(X)), X, atol=1e-10)


def test_ransac_sim3_ignores_outliers():
    rng = np.random.default_rng(3)
    T = sim3.Sim3(0.5, random_rotation(rng), rng.normal(size=3))
    X = rng.normal(size=(50, 3))
    Y = T.apply(X) + rng.normal(scale=1e-4, size=X.shape)
    Y[:15] += rng.normal(scale=3, size=(15, 3))
    est, inliers = sim3.ransac_umeyama(X, Y, threshold=0.01)
    assert inliers[15:].all() and not inliers[:15].any()
    assert rotation.rotation_error_deg(est.R, T.R) < 0.05
    assert est.scale == pytest.approx(0.5, rel=1e-3)


@pytest.mark.parametrize("model,params", [
    ("SIMPLE_PINHOLE", [500, 320, 240]),
    ("PINHOLE", [500, 520, 320, 240]),
    ("SIMPLE_RADIAL", [500, 320, 240, -0.08]),
    ("RADIAL", [500, 320, 240, -0.1, 0.02]),
    ("OPENCV", [500, 510, 320, 240, -0.2, 0.05, 0.001, -0.002]),
])
def test_projection_and_unprojection_are_inverse(model, params):
    rng = np.random.default_rng(4)
    X = rng.uniform([-1, -0.8, 2], [1, 0.8, 4], size=(200, 3))
    uv = camera.project(model, params, X)
    xy = camera.pixels_to_normalized(model, params, uv)
    np.testing.assert_allclose(xy, X[:, :2] / X[:, 2:], atol=1e-9)
    # the projection is COLMAP's for that model (a round trip alone would pass with k's sign flipped)
    import pycolmap

    reference = pycolmap.Camera(model=model, width=640, height=480, params=params).img_from_cam(X)
    np.testing.assert_allclose(uv, reference, atol=1e-6)


def test_projection_matches_opencv():
    cv2 = pytest.importorskip("cv2")
    p = [500, 510, 320, 240, -0.2, 0.05, 0.001, -0.002]
    X = np.random.default_rng(5).uniform([-1, -0.8, 2], [1, 0.8, 4], size=(50, 3))
    ours = camera.project("OPENCV", p, X)
    theirs, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), camera.calibration_matrix("OPENCV", p),
                                  camera.distortion_coefficients("OPENCV", p))
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-8)


def test_bad_camera_parameters_are_named():
    with pytest.raises(ValueError, match="SIMPLE_RADIAL takes 4 parameters"):
        camera.check_model("SIMPLE_RADIAL", [1, 2, 3])
    with pytest.raises(ValueError, match="unknown camera model"):
        camera.default_params("FISHEYE9", 100, 10, 10)


@pytest.mark.parametrize("model,params", [
    ("OPENCV", [430.0, 430.0, 512.0, 384.0, -0.22, 0.05, 0.001, -0.0008]),  # the wide_orbit lens
    ("SIMPLE_RADIAL", [400.0, 320.0, 240.0, 0.1]),
    ("RADIAL", [400.0, 320.0, 240.0, -0.1, 0.02]),
])
def test_undistort_inverts_distort(model, params):
    x = np.random.default_rng(0).uniform(-0.9, 0.9, (5000, 2))  # inside the fold of the strongest lens
    back = camera.undistort_normalized(model, params, camera.distort(model, params, x))
    np.testing.assert_allclose(back, x, atol=1e-10)
