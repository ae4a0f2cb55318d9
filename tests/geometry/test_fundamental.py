"""Eight-point F, Sampson distance, RANSAC, epipoles and rectification against exact synthetic geometry, and our F
against OpenCV's on a real pair."""


import numpy as np
import pytest

from mvrecon.geometry.fundamental import RansacConfig, eight_point, epipoles, ransac_fundamental, sampson_distance
from mvrecon.geometry.rectification import (
    apply_homography,
    calibrated_rectification,
    fit_to_canvas,
    hartley_rectification,
)
from mvrecon.geometry.rotation import angle_axis_to_rotmat
from tests.helpers import DATA


def two_view(n=200, seed=0, rvec=(0.05, -0.2, 0.03), t=(-1.0, 0.1, 0.2)):
    """Points in front of two cameras: x_cam2 = R x_cam1 + t; returns pixels, K, R, t."""
    rng = np.random.default_rng(seed)
    K = np.array([[800.0, 0, 320], [0, 780, 240], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 9, n)])
    R = angle_axis_to_rotmat(np.array(rvec))
    t = np.array(t)
    x1 = (X / X[:, 2:]) @ K.T
    X2 = X @ R.T + t
    x2 = (X2 / X2[:, 2:]) @ K.T
    return x1[:, :2], x2[:, :2], K, R, t


def true_F(K, R, t):
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ tx @ R @ Kinv
    return F / np.linalg.norm(F)


def test_eight_point_exact_on_noise_free_points():
    x1, x2, K, R, t = two_view()
    F = eight_point(x1, x2)
    assert np.linalg.matrix_rank(F, tol=1e-10) == 2
    assert np.max(sampson_distance(F, x1, x2)) < 1e-6
    Ft = true_F(K, R, t)
    assert min(np.linalg.norm(F - Ft), np.linalg.norm(F + Ft)) < 1e-6
    e1, e2 = epipoles(F)
    c2_in_1 = -R.T @ t  # camera 2's centre seen by camera 1 is the epipole e1
    proj = K @ c2_in_1
    assert np.allclose(e1[:2] / e1[2], proj[:2] / proj[2], atol=1e-4)
    proj2 = K @ t  # camera 1's centre (origin) in camera 2
    assert np.allclose(e2[:2] / e2[2], proj2[:2] / proj2[2], atol=1e-4)


def test_ransac_finds_inliers_among_outliers():
    x1, x2, K, R, t = two_view(n=300, seed=1)
    rng = np.random.default_rng(2)
    x1 = x1 + rng.normal(0, 0.3, x1.shape)
    x2 = x2 + rng.normal(0, 0.3, x2.shape)
    bad = rng.random(len(x1)) < 0.35
    x2[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
    F, inliers = ransac_fundamental(x1, x2, RansacConfig(threshold=1.5))
    assert (inliers & ~bad).sum() >= 0.95 * (~bad).sum()
    assert (inliers & bad).sum() <= 0.05 * bad.sum()
    assert np.median(sampson_distance(F, x1[~bad], x2[~bad])) < 0.5
    with pytest.raises(ValueError, match="at least 8"):
        ransac_fundamental(x1[:7], x2[:7])


def test_hartley_rectification_aligns_rows():
    x1, x2, K, R, t = two_view(n=150, seed=3)
    F = eight_point(x1, x2)
    H1, H2 = hartley_rectification(F, x1, x2, (640, 480))
    frame = fit_to_canvas(H1, H2, (640, 480), x1, x2)
    p1, p2 = apply_homography(frame.H1, x1), apply_homography(frame.H2, x2)
    assert np.max(np.abs(p1[:, 1] - p2[:, 1])) < 1e-6
    d = p1[:, 0] - p2[:, 0]
    assert d.min() > 0 and np.percentile(d, 1) == pytest.approx(8.0)  # disparities shifted to start at 8 px
    assert 0.5 < frame.width / 640 < 2 and 0.5 < frame.height / 480 < 2


def test_calibrated_rectification_aligns_rows():
    x1, x2, K, R, t = two_view(n=100, seed=4)
    rect = calibrated_rectification(K, K, R, t)
    def to_rect(x, Rr, Kn):
        rays = np.column_stack([x, np.ones(len(x))]) @ np.linalg.inv(K).T @ Rr.T
        p = rays @ Kn.T
        return p[:, :2] / p[:, 2:]
    p1, p2 = to_rect(x1, rect.R1, rect.K1), to_rect(x2, rect.R2, rect.K2)
    assert np.max(np.abs(p1[:, 1] - p2[:, 1])) < 1e-6
    assert rect.baseline == pytest.approx(np.linalg.norm(t))


def test_eight_point_agrees_with_opencv_on_motorcycle():
    import cv2
    import skimage.data

    from mvrecon.stereo.pipeline import sift_matches

    left, right, _ = skimage.data.stereo_motorcycle()
    x1, x2 = sift_matches(left, right)
    F, inliers = ransac_fundamental(x1, x2)
    F_cv, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.0, 0.999)
    mask = mask.ravel() > 0
    assert inliers.sum() > 500
    assert np.median(sampson_distance(F, x1[inliers], x2[inliers])) < 1.0
    assert np.median(sampson_distance(F_cv, x1[inliers], x2[inliers])) < 1.0  # OpenCV's F on our inliers
    assert np.median(sampson_distance(F, x1[mask], x2[mask])) < 1.0  # our F on OpenCV's inliers


def test_eight_point_agrees_with_opencv_on_cones():
    import cv2

    from mvrecon.io.images import read_image
    from mvrecon.stereo.pipeline import sift_matches

    folder = DATA / "stereo_middlebury2003_cones_gray"
    if not folder.is_dir():
        pytest.skip(f"Cones pair not found at {folder}")
    x1, x2 = sift_matches(read_image(folder / "left.png"), read_image(folder / "right.png"))
    F, inliers = ransac_fundamental(x1, x2)
    F_cv, mask = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, 1.0, 0.999)
    assert inliers.sum() > 200
    assert np.median(sampson_distance(F_cv, x1[inliers], x2[inliers])) < 1.0
    assert np.median(sampson_distance(F, x1[mask.ravel() > 0], x2[mask.ravel() > 0])) < 1.0
