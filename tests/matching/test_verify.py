"""Descriptor matching and geometric verification against known geometry."""

import numpy as np
import pytest

from mvrecon.database import CameraInfo
from mvrecon.features.sift import extract_sift
from mvrecon.geometry import camera as camera_model
from mvrecon.geometry.fundamental import sampson_distance
from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.matching.matcher import MatcherConfig, match_descriptors
from mvrecon.matching.verify import VerifyConfig, f_iterations, verify_pair

K = [800.0, 320.0, 240.0, 0.0]
CAM = CameraInfo(model="SIMPLE_RADIAL", width=640, height=480, params=np.array(K), prior_trusted=True)


def test_matcher_recovers_a_permutation_and_applies_ratio_and_mutual_checks():
    rng = np.random.default_rng(0)
    d1 = rng.integers(0, 120, size=(500, 128)).astype(np.uint8)
    perm = rng.permutation(500)
    d2 = np.clip(d1[perm].astype(int) + rng.integers(-3, 4, size=(500, 128)), 0, 255).astype(np.uint8)
    m = match_descriptors(d1, d2)
    assert len(m) == 500 and np.array_equal(perm[m[:, 1]], m[:, 0])
    # An exact duplicate in image 2 makes the best and second-best equal: the ratio test must drop that point.
    d2_dup = np.vstack([d2, d2[:1]])
    m = match_descriptors(d1, d2_dup)
    assert perm[0] not in m[:, 0] and len(m) == 499
    # Mutual check: two points of image 1 whose nearest neighbour is the same point of image 2 keep one match.
    one = match_descriptors(np.vstack([d1[:1], d1[:1] // 2 + 1]), d1[:1], MatcherConfig(max_ratio=1.01))
    assert len(one) == 1


def test_blocked_matcher_equals_a_whole_matrix_reference():
    """3000 x 2500 float descriptors span four row blocks; the matches equal those of one whole score matrix."""
    rng = np.random.default_rng(3)
    d2 = rng.integers(0, 120, size=(2500, 128)).astype(np.uint8)
    src = rng.integers(0, 2500, size=3000)
    d1 = np.clip(d2[src].astype(int) + rng.integers(-40, 41, size=(3000, 128)), 0, 255).astype(np.uint8)
    u1, u2 = (d / np.linalg.norm(d, axis=1, keepdims=True) for d in (d1.astype(float), d2.astype(float)))
    d1, d2 = u1.astype(np.float32), u2.astype(np.float32)  # the float product; integers are tested below
    S = u1 @ u2.T
    order = np.argsort(-S, axis=1)
    best, second = order[:, 0], order[:, 1]
    rows = np.arange(len(S))
    a1, a2 = np.arccos(np.clip(S[rows, best], -1, 1)), np.arccos(np.clip(S[rows, second], -1, 1))
    keep = (a1 <= 0.7) & (a1 < 0.8 * a2) & (S.argmax(axis=0)[best] == rows)
    expected = np.stack([rows[keep], best[keep]], axis=1)
    got = match_descriptors(d1, d2)
    assert 500 < len(got) < 3000 and np.array_equal(got, expected)


def test_integer_product_matches_as_the_float_product_on_sift():
    """uint8 SIFT descriptors are matched by 7-bit integer products: on a real pair nearly every match is the one
    the float32 product of the unit descriptors gives, and the exact integer product is exact."""
    from mvrecon.matching.int_product import int_product
    from mvrecon.matching.matcher import normalize_descriptors

    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 128, (70, 128), dtype=np.uint8), rng.integers(0, 128, (128, 90)).astype(np.int8)
    assert np.array_equal(int_product(a, b), a.astype(np.int64) @ b.astype(np.int64))
    skimage_data = pytest.importorskip("skimage.data")
    try:
        left, right, _ = skimage_data.stereo_motorcycle()
    except Exception as exc:  # the data may need a download on machines without the cache
        pytest.skip(f"skimage stereo_motorcycle not available: {exc}")
    (_, d1), (_, d2) = extract_sift(left), extract_sift(right)
    integer = {tuple(m) for m in match_descriptors(d1, d2)}
    floating = {tuple(m) for m in match_descriptors(normalize_descriptors(d1), normalize_descriptors(d2))}
    assert len(floating) > 500
    assert len(integer & floating) >= 0.97 * len(floating) and abs(len(integer) / len(floating) - 1) < 0.01


def two_view(points, R, t, cam=CAM, noise=0.3, seed=1):
    rng = np.random.default_rng(seed)
    uv1 = camera_model.project(cam.model, cam.params, points)
    uv2 = camera_model.project(cam.model, cam.params, points @ R.T + t)
    return uv1 + rng.normal(scale=noise, size=uv1.shape), uv2 + rng.normal(scale=noise, size=uv2.shape)


def add_outliers(uv1, uv2, fraction=0.3, seed=2):
    rng = np.random.default_rng(seed)
    n = int(len(uv1) * fraction)
    uv2 = uv2.copy()
    uv2[:n] = rng.uniform([0, 0], [640, 480], size=(n, 2))
    return uv1, uv2, n


@pytest.mark.parametrize("scene,expected", [("general", "CALIBRATED"), ("plane", "PLANAR"),
                                            ("rotation", "PANORAMIC"), ("uncalibrated", "UNCALIBRATED"),
                                            ("random", "DEGENERATE")])
def test_pairs_are_classified_like_colmap(scene, expected):
    rng = np.random.default_rng(3)
    n = 300
    R = angle_axis_to_rotmat([0.02, 0.15, 0.01])
    t = np.array([-0.6, 0.05, 0.1])
    if scene == "plane":
        X = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), np.full(n, 5.0)])
    else:
        X = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 8, n)])
    if scene == "rotation":
        t = np.zeros(3)
    uv1, uv2 = two_view(X, R, t)
    uv1, uv2, n_out = add_outliers(uv1, uv2)
    if scene == "random":
        uv2 = np.random.default_rng(4).uniform([0, 0], [640, 480], size=uv2.shape)
    cam = CAM if scene != "uncalibrated" else CameraInfo(model="SIMPLE_RADIAL", width=640, height=480,
                                                           params=np.array(K), prior_trusted=False)
    matches = np.column_stack([np.arange(n), np.arange(n)])
    result = verify_pair(uv1, uv2, matches, cam, cam)
    assert result.config == expected, result.num_inliers
    if expected != "DEGENERATE":
        inlier_rows = set(result.inliers[:, 0])
        accepted_outliers = len(inlier_rows & set(range(n_out)))
        assert accepted_outliers <= 0.1 * n_out  # only the chance agreement of random points with the model
        assert len(inlier_rows) >= 0.9 * (n - n_out)
        assert (result.E is not None) == (cam.prior_trusted and expected != "UNCALIBRATED")
    else:
        assert len(result.inliers) == 0


def test_motorcycle_fundamental_matrix_is_accurate_and_epipolar_lines_are_horizontal():
    skimage_data = pytest.importorskip("skimage.data")
    try:
        left, right, _ = skimage_data.stereo_motorcycle()
    except Exception as exc:  # the data may need a download on machines without the cache
        pytest.skip(f"skimage stereo_motorcycle not available: {exc}")
    k1, d1 = extract_sift(left)
    k2, d2 = extract_sift(right)
    matches = match_descriptors(d1, d2)
    h, w = left.shape[:2]
    cam = CameraInfo(model="SIMPLE_RADIAL", width=w, height=h, params=np.array([1.2 * w, w / 2, h / 2, 0.0]))
    result = verify_pair(k1, k2, matches, cam, cam)
    assert result.config in ("UNCALIBRATED", "PLANAR_OR_PANORAMIC") and len(result.inliers) > 300
    p1, p2 = k1[result.inliers[:, 0], :2], k2[result.inliers[:, 1], :2]
    assert np.median(sampson_distance(result.F, p1[:, :2], p2[:, :2])) < 1.0
    # Rectified pair: the epipolar line of every inlier in the right image is (nearly) horizontal.
    lines = np.column_stack([p1, np.ones(len(p1))]) @ result.F.T
    slopes_deg = np.degrees(np.arctan2(np.abs(lines[:, 0]), np.abs(lines[:, 1])))
    assert np.median(slopes_deg) < 0.5 and np.percentile(slopes_deg, 95) < 2.0
    # and matched points keep their row
    assert np.median(np.abs(p1[:, 1] - p2[:, 1])) < 1.0


def test_pairs_with_just_enough_inliers_verify_under_the_shortened_f_search():
    """F's RANSAC runs only as long as a pair holding the fewest inliers that could pass needs (24 matches of
    which 15 must fit: 364 iterations, not 5000): pairs with 17 true inliers among 24 still verify, with every
    inlier found, on each of 20 random scenes, and chance matches still fail."""
    assert f_iterations(24, VerifyConfig()) < 400 and f_iterations(200, VerifyConfig()) == 5000
    R = angle_axis_to_rotmat([0.02, 0.15, 0.01])
    t = np.array([-0.6, 0.05, 0.1])
    cam = CameraInfo(model="SIMPLE_RADIAL", width=640, height=480, params=np.array(K), prior_trusted=False)
    matches = np.column_stack([np.arange(24), np.arange(24)])
    for seed in range(20):
        rng = np.random.default_rng(seed)
        X = np.column_stack([rng.uniform(-2, 2, 24), rng.uniform(-1.5, 1.5, 24), rng.uniform(4, 8, 24)])
        uv1, uv2 = two_view(X, R, t, cam, seed=seed)
        uv2[17:] = rng.uniform([0, 0], [640, 480], size=(7, 2))
        result = verify_pair(uv1, uv2, matches, cam, cam)
        assert result.config == "UNCALIBRATED" and set(range(17)) <= set(result.inliers[:, 0]), (seed, result)
        chance = verify_pair(uv1, rng.uniform([0, 0], [640, 480], size=(24, 2)), matches, cam, cam)
        assert chance.config == "DEGENERATE"


def test_the_feature_cap_keeps_the_coarsest_scales_as_colmap():
    """Over max_num_features, the keypoints kept are those of the coarsest DoG levels (COLMAP's rule), not
    OpenCV's strongest responses, which on large photos are mostly the finest levels' (full-size Sceaux castle
    registered 10 of 11 images with those, 11 with these)."""
    from skimage import data as skimage_data

    from mvrecon.features.sift import SiftConfig

    image = skimage_data.astronaut()
    k_all, d_all = extract_sift(image)
    k, d = extract_sift(image, SiftConfig(max_num_features=600))
    assert len(k_all) > 1000 and len(k) == 600
    rows = {(tuple(kp), desc.tobytes()) for kp, desc in zip(k_all, d_all)}
    assert all((tuple(kp), desc.tobytes()) in rows for kp, desc in zip(k, d))  # the same keypoints, described alike
    # DoG levels are 2^(1/3) apart in scale: every keypoint twice the smallest kept scale is of a coarser level
    coarse = k_all[:, 2] >= 2 * k[:, 2].min()
    assert coarse.sum() > 100 and {tuple(kp) for kp in k_all[coarse]} <= {tuple(kp) for kp in k}
    assert np.median(k[:, 2]) > 1.4 * np.median(k_all[:, 2])
    # under the cap nothing changes
    k_same, d_same = extract_sift(image, SiftConfig(max_num_features=len(k_all)))
    assert np.array_equal(k_same, k_all) and np.array_equal(d_same, d_all)


def test_runs_of_a_sorted_array_count_as_unique_does():
    """fixed_keypoints counts cells and images by the runs of sorted keys (numpy's hashing `unique` took 19 ms
    of templeSparseRing's matching stage): the values and counts are np.unique's, also for 0 and 1 values."""
    from mvrecon.matching.overlay import _runs

    rng = np.random.default_rng(1)
    for values in (np.zeros(0, np.int64), np.array([7]), np.sort(rng.integers(0, 50, 400))):
        found, expected = _runs(values), np.unique(values, return_counts=True)
        assert all(np.array_equal(a, b) for a, b in zip(found, expected))


def test_features_printed_on_three_images_of_one_size_are_fixed_and_their_still_matches_dropped():
    """matching/overlay.py: a position is fixed when half the images of one size, and at least three, have a
    keypoint there; two copies of one view (a duplicate) are not enough, and images of another size do not
    count."""
    from mvrecon.matching.overlay import drop_static, fixed_keypoints

    rng = np.random.default_rng(0)
    logo = rng.uniform(20, 620, (40, 2))  # printed on images 1-3
    pair = rng.uniform(20, 620, (40, 2))  # only in images 1 and 2: a duplicated view

    def image(*parts):
        return np.concatenate([p + rng.normal(0, 0.2, p.shape) for p in parts] + [rng.uniform(0, 640, (200, 2))])

    positions = {1: image(logo, pair), 2: image(logo, pair), 3: image(logo, rng.uniform(0, 640, (40, 2))),
                 4: image(logo, pair)}
    sizes = {1: (640, 480), 2: (640, 480), 3: (640, 480), 4: (800, 600)}
    fixed = fixed_keypoints(positions, sizes)
    assert fixed[1][:40].all() and fixed[3][:40].all()
    assert not fixed[1][40:80].any()  # the duplicated view's own features: two images, and image 4 is larger
    assert not fixed[4].any()  # the only image of its size
    assert fixed[1][80:].mean() < 0.05  # chance neighbours among 200 random points

    # images 1 and 2 matched on all their shared features and on 10 that move: only the logo's are dropped
    idx = np.arange(80)
    moving = np.c_[np.arange(80, 90), np.arange(90, 100)]
    matches = np.r_[np.c_[idx, idx], moving]
    kept = drop_static(matches, positions[1], positions[2], fixed[1], fixed[2])
    assert sorted(map(tuple, kept)) == sorted(map(tuple, matches[40:]))

    # among eight images of that size, three are not half: chance neighbours in big sets are not printed features
    positions.update({k: image() for k in range(5, 10)})
    sizes.update({k: (640, 480) for k in range(5, 10)})
    assert fixed_keypoints(positions, sizes)[1][:40].mean() < 0.2  # all 40 before; chance neighbours remain
