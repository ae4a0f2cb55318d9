"""Guided matching: once a pair's geometry is known, matching again among the keypoints it admits finds more
true matches, every one of them within the threshold of that geometry."""

import cv2
import numpy as np
import pytest
import skimage.data

from mvrecon.features.sift import extract_sift
from mvrecon.geometry.fundamental import sampson_distance
from mvrecon.matching.guided import guided_inliers
from mvrecon.matching.matcher import match_descriptors
from mvrecon.matching.verify import TwoViewResult


@pytest.fixture(scope="module")
def warped_pair():
    """The camera photo and a view of it rotated by 40 deg, scaled by 0.8 and tilted: SIFT of both and the
    true homography in COLMAP pixels."""
    image = skimage.data.camera()
    h, w = image.shape
    H = np.vstack([cv2.getRotationMatrix2D((w / 2, h / 2), 40, 0.8), [0.0006, 0, 1]])
    to_colmap = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    k1, d1 = extract_sift(image)
    k2, d2 = extract_sift(cv2.warpPerspective(image, H, (w, h)))
    return k1, d1, k2, d2, to_colmap @ H @ np.linalg.inv(to_colmap)


def _transfer_error(k1, k2, m, H):
    p = np.column_stack([k1[m[:, 0], :2], np.ones(len(m))]) @ H.T
    return np.linalg.norm(p[:, :2] / p[:, 2:] - k2[m[:, 1], :2], axis=1)


def test_guided_by_a_homography_finds_more_true_matches(warped_pair):
    k1, d1, k2, d2, H = warped_pair
    plain = match_descriptors(d1, d2)
    guided = guided_inliers(k1, d1, k2, d2, TwoViewResult(config="PLANAR", inliers=plain, H=H), 4.0)
    plain_err, guided_err = _transfer_error(k1, k2, plain, H), _transfer_error(k1, k2, guided, H)
    assert guided_err.max() <= 4.0
    assert (guided_err < 1.5).sum() >= 1.05 * (plain_err < 1.5).sum()
    assert (guided_err < 1.5).mean() > 0.9


def test_guided_by_a_fundamental_matrix_keeps_to_its_epipolar_band(warped_pair):
    """An F the plane's true matches satisfy (an epipole at (100, 50) and the homography): the guided matches all
    lie within 4 px of it (Sampson distance) and hold more true matches than the plain ones."""
    k1, d1, k2, d2, H = warped_pair
    ex, ey = 100.0, 50.0
    F = np.array([[0, -1, ey], [1, 0, -ex], [-ey, ex, 0]]) @ H
    plain = match_descriptors(d1, d2)
    guided = guided_inliers(k1, d1, k2, d2, TwoViewResult(config="UNCALIBRATED", inliers=plain, F=F), 4.0)
    assert sampson_distance(F, k1[guided[:, 0], :2], k2[guided[:, 1], :2]).max() <= 4.0 + 1e-9
    assert (_transfer_error(k1, k2, guided, H) < 1.5).sum() > (_transfer_error(k1, k2, plain, H) < 1.5).sum()


def test_a_pair_without_its_geometry_keeps_its_inliers(warped_pair):
    k1, d1, k2, d2, _ = warped_pair
    inliers = np.array([[0, 1], [2, 3]])
    assert guided_inliers(k1, d1, k2, d2, TwoViewResult(config="UNCALIBRATED", inliers=inliers), 4.0) is inliers
