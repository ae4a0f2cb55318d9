"""The global mapper's view graph: relative poses refined, rotations of a camera turning in place."""

import numpy as np
from scipy.spatial.transform import Rotation

from mvrecon import database
from mvrecon.sfm import pair_poses
from mvrecon.sfm.config import MapperConfig
from mvrecon.sfm.global_mapper import GlobalMapper
from mvrecon.sfm.model import Camera
from mvrecon.sfm.pair_poses import refine_relative_pose, relative_poses
from mvrecon.sfm.view_graph import calibration_shift_px, dense_subset
from tests.sfm.test_global_mapper import rotating_views
from tests.sfm.test_mapper import synthetic_database


def angle_deg(R):
    return float(np.degrees(Rotation.from_matrix(R).magnitude()))


def test_a_relative_pose_degrees_off_is_refined_to_its_matches():
    """A narrow field of view (0.2 rad across, as the temple's 24 deg) and a pose 3 deg off in rotation and 5 deg
    in direction: the Sampson refinement brings both back within the noise."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-0.1, 0.1, (300, 2)), np.ones(300)] * rng.uniform(4, 6, (300, 1))
    R = Rotation.from_rotvec([0.0, -0.15, 0.0]).as_matrix()
    t = np.array([0.6, 0.0, 0.1])
    t /= np.linalg.norm(t)
    x1 = X[:, :2] / X[:, 2:] + rng.normal(0, 2e-4, (300, 2))
    Y = X @ R.T + t
    x2 = Y[:, :2] / Y[:, 2:] + rng.normal(0, 2e-4, (300, 2))
    R0 = Rotation.from_rotvec([0.03, 0.02, -0.03]).as_matrix() @ R
    t0 = Rotation.from_rotvec([0.0, 0.09, 0.0]).as_matrix() @ t
    Rr, tr = refine_relative_pose(R0, t0, x1, x2)
    assert angle_deg(R0 @ R.T) > 2.5
    assert angle_deg(Rr @ R.T) < 0.3  # what the noise allows: yaw and direction trade off in a narrow view
    assert np.degrees(np.arccos(np.clip(tr @ t, -1, 1))) < 1.0


def test_a_relative_pose_far_off_in_a_narrow_view_reaches_the_exact_pose():
    """Exact matches in a 0.2 rad view and a start 10 deg off in rotation and 20 deg in direction, where yaw and
    direction trade off along a long narrow valley of the cost: the refinement follows it to the true pose."""
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(-0.1, 0.1, (200, 2)), np.ones(200)] * rng.uniform(4, 6, (200, 1))
    R = Rotation.from_rotvec([0.02, -0.12, 0.01]).as_matrix()
    t = np.array([0.7, 0.1, 0.2])
    t /= np.linalg.norm(t)
    Y = X @ R.T + t
    x1, x2 = X[:, :2] / X[:, 2:], Y[:, :2] / Y[:, 2:]
    R0 = Rotation.from_rotvec(np.radians([4.0, -8.0, 4.0])).as_matrix() @ R
    t0 = Rotation.from_rotvec(np.radians([0.0, 20.0, 0.0])).as_matrix() @ t
    Rr, tr = refine_relative_pose(R0, t0, x1, x2)
    assert angle_deg(R0 @ R.T) > 9.5
    assert angle_deg(Rr @ R.T) < 1e-4
    assert np.degrees(np.arccos(np.clip(tr @ t, -1, 1))) < 1e-4


def test_a_camera_turning_in_place_gives_rotations_without_directions():
    corr = rotating_views([0, 10, 20, 30])
    mapper = GlobalMapper(corr, MapperConfig(mapper="global"))
    graph = relative_poses(mapper._new_model(mapper.cameras), mapper.pairs, mapper.config)
    assert len(graph.edges) == 6 and not graph.rejected
    for (a, b), edge in graph.edges.items():
        yaw = np.radians(10 * (b - a))
        truth = np.array([[np.cos(yaw), 0, -np.sin(yaw)], [0, 1, 0], [np.sin(yaw), 0, np.cos(yaw)]])
        assert edge.angle_deg == 0.0 and not edge.t.any()
        assert angle_deg(edge.R @ truth.T) < 0.1


def test_a_panorama_of_few_matches_per_pair_gives_rotations_only():
    """The same camera turning in place with 43-83 matches per pair and 1 px of noise, 5 seeds: every pair a
    rotation without a direction. Its essential matrix, whose epipolar distance is one-dimensional, fits more of
    the noisy matches than a homography does, and a pair that kept it as a baseline would place cameras apart.
    With 9-25 matches a pair is a rotation or refused, never a baseline."""
    for share, low in ((0.03, 40), (0.008, 5)):
        for seed in range(5):
            corr = rotating_views([0, 10, 20, 30], seed=seed, noise_px=1.0)
            keep = np.random.default_rng(seed)
            for pair in corr.pairs:
                pair.inliers = pair.inliers[keep.random(len(pair.inliers)) < share]
            assert low < min(len(p.inliers) for p in corr.pairs) and max(len(p.inliers) for p in corr.pairs) < 100
            mapper = GlobalMapper(corr, MapperConfig(mapper="global"))
            graph = relative_poses(mapper._new_model(mapper.cameras), mapper.pairs, mapper.config)
            assert all(edge.angle_deg == 0.0 and not edge.t.any() for edge in graph.edges.values())
            assert all(why.startswith("no baseline") or why.endswith("< 15") for why in graph.rejected.values())
            assert len(graph.edges) == 6 if share == 0.03 else len(graph.edges) + len(graph.rejected) == 6


def test_the_calibration_subset_is_bounded_and_well_connected():
    """A 300-image sequence, each image paired with its 5 successors (matches falling with distance) and one
    busy stretch: the subset holds `size` consecutive images around the busiest, with every pair among them, and
    a seed grows a second set of its own."""
    pairs = {(i, j): np.zeros((100 * (6 - (j - i)) + (400 if 140 <= i < 160 else 0), 2), int)
             for i in range(300) for j in range(i + 1, min(300, i + 6))}
    inside = dense_subset(pairs, 300, 30)
    assert inside.sum() == 30
    members = np.flatnonzero(inside)
    assert np.ptp(members) == 29 and members[0] <= 140 and members[-1] >= 159  # one stretch, over the busy one
    seeded = dense_subset(pairs, 300, 30, [10])
    assert seeded.sum() == 30 and seeded[10] and np.ptp(np.flatnonzero(seeded)) == 29
    assert dense_subset(pairs, 300, 400).sum() == 300  # no more than there are


def test_relative_poses_in_worker_processes_are_those_of_one_process(tmp_path, monkeypatch):
    """pycolmap's synthetic scene (28 pairs) handed to two worker processes: every pair's pose as in-process,
    and near the true relative rotation."""
    path = tmp_path / "database.db"
    gt = synthetic_database(path)
    mapper = GlobalMapper(database.read_correspondences(path), MapperConfig(mapper="global"))
    model = mapper._new_model(mapper.cameras)
    for cam in model.cameras.values():
        cam.params = np.array([600.0, 320.0, 240.0, 0.02])  # the scene's true calibration
    monkeypatch.setattr(pair_poses, "_PARALLEL_PAIRS", 1)
    alone = relative_poses(model, mapper.pairs, mapper.config)
    shared = relative_poses(model, mapper.pairs, mapper.config, workers=2)
    assert len(alone.edges) == 28 and sorted(shared.edges) == sorted(alone.edges)
    errors = []
    for (a, b), edge in shared.edges.items():
        assert np.allclose(edge.R, alone.edges[(a, b)].R) and edge.inliers == alone.edges[(a, b)].inliers
        Ra, Rb = gt[mapper.names[a]][0], gt[mapper.names[b]][0]
        errors.append(angle_deg(edge.R @ (Rb @ Ra.T).T))
    assert np.median(errors) < 0.2 and max(errors) < 1.0  # 0.5 px of keypoint noise


def test_a_calibration_change_is_measured_by_how_far_it_moves_the_image_corners():
    """A focal 3% longer moves a 640 x 480 image's corners by 3% of their 400 px from the centre; a distortion
    k1 of -0.02 at a focal of 450 px by about 6 px; the same calibration moves nothing."""
    before = Camera("SIMPLE_RADIAL", 640, 480, np.array([450.0, 320.0, 240.0, 0.0]))
    longer = Camera("SIMPLE_RADIAL", 640, 480, np.array([463.5, 320.0, 240.0, 0.0]))
    barrel = Camera("SIMPLE_RADIAL", 640, 480, np.array([450.0, 320.0, 240.0, -0.02]))
    assert calibration_shift_px(before, before) < 1e-9
    assert abs(calibration_shift_px(before, longer) - 12.0) < 0.01
    assert 5.0 < calibration_shift_px(before, barrel) < 7.0
