"""Acceptance test of the front end: our features and verified matches are good enough for COLMAP's own mapper.

A ground-truth scene from `pycolmap.synthesize_dataset` is rendered to images with `pycolmap.synthesize_images`;
we extract, match and verify into our database, run `pycolmap.incremental_mapping` on it, and compare the model's
poses with the ground truth after a robust Sim3 alignment of the camera centres.
"""

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from mvrecon.eval.metrics import align_and_compare  # noqa: E402
from mvrecon.eval.models import poses  # noqa: E402
from mvrecon.stages.common import FrontendConfig  # noqa: E402
from mvrecon.stages.features import extract_features  # noqa: E402
from mvrecon.stages.matching import match  # noqa: E402


def synthetic_scene(folder, num_images=10, num_points=300):
    """10 views of 300 textured points, 640x480, f = 1000 px (points stay large enough for SIFT)."""
    options = pycolmap.SyntheticDatasetOptions(
        num_rigs=1, num_cameras_per_rig=1, num_frames_per_rig=num_images, num_points3D=num_points,
        camera_width=640, camera_height=480, camera_params=[1000.0, 320.0, 240.0, 0.0],
        num_points2D_without_point3D=0)
    truth = pycolmap.synthesize_dataset(options)
    images = folder / "images"
    images.mkdir(parents=True)
    pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), truth, str(images))
    return truth, images


def test_colmap_maps_our_matches_and_recovers_the_ground_truth_rotations(tmp_path):
    truth, images = synthetic_scene(tmp_path)
    config = FrontendConfig(workers=1)
    features = extract_features(config, images, tmp_path / "ws")
    assert features.num_images == 10 and min(features.keypoints.values()) > 300
    matches = match(config, tmp_path / "ws")
    assert matches.num_pairs == 45 and matches.num_verified >= 40

    models = pycolmap.incremental_mapping(str(tmp_path / "ws" / "database.db"), str(images),
                                          str(tmp_path / "sparse"))
    assert len(models) >= 1
    model = max(models.values(), key=lambda m: m.num_reg_images())
    assert model.num_reg_images() == 10
    alignment = align_and_compare(poses(model), poses(truth))
    assert len(alignment.inliers) == 10
    errors = np.array(list(alignment.rotation_errors_deg.values()))
    assert errors.max() < 0.5, errors
