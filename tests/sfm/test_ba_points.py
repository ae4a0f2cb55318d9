"""The points a bundle adjustment during growth optimises: each image's best per grid cell, round by round."""

import numpy as np

from mvrecon import database
from mvrecon.sfm.ba_points import GRID, select_points
from mvrecon.sfm.config import MapperConfig
from mvrecon.sfm.incremental import map_correspondences
from tests.sfm.test_mapper import synthetic_database


def rounds_by_hand(m, images, per_image):
    """The rule of ba_points' docstring, one image and one cell at a time: in each cell its points best first
    (longest track, then lowest reprojection error, then the observation's order); then the image's points
    round by round (every cell's best, every cell's second best, ...), within a round best first."""
    chosen = set()
    lengths = m.point_num_observations()
    for i in images:
        obs = m.observations_of_images([i])
        cam = m.cameras[int(m.camera_of[i])]
        xy = m.keypoints_at(np.full(len(obs), i), m.obs_kp.data[obs])
        err = m.reprojection_errors(obs)[0]
        cells: dict = {}
        for k, (x, y) in enumerate(xy):
            cell = (min(int(y * GRID / cam.height), GRID - 1), min(int(x * GRID / cam.width), GRID - 1))
            cells.setdefault(cell, []).append(k)
        views = []
        for members in cells.values():
            members.sort(key=lambda k: (-lengths[m.obs_point.data[obs[k]]], err[k], k))
            views += [(rank, -lengths[m.obs_point.data[obs[k]]], err[k], k) for rank, k in enumerate(members)]
        views.sort()
        chosen |= {int(m.obs_point.data[obs[k]]) for *_, k in views[:per_image]}
    return np.array(sorted(chosen), dtype=np.int64)


def test_each_image_gives_its_best_point_of_every_cell_round_by_round(tmp_path):
    """A mapped synthetic scene (8 images, 600 points) with a third of its views taken out, so that its tracks
    are two to eight views long: the points chosen for 10 and 40 per image are those the rule gives done by
    hand, image by image; at as many as an image has, every point is taken."""
    synthetic_database(tmp_path / "database.db")
    m = map_correspondences(database.read_correspondences(tmp_path / "database.db"), MapperConfig(seed=0)).models[0]
    obs = m.alive_observations()
    m.remove_observations(obs[np.random.default_rng(0).random(len(obs)) < 1 / 3])
    images = m.registered_images()
    lengths = m.point_num_observations()[m.alive_points()]
    assert len(images) == 8 and lengths.min() == 2 and lengths.max() == 8
    for per_image in (10, 40):
        chosen = select_points(m, images, per_image)
        assert len(chosen) < len(m.alive_points())
        assert np.array_equal(chosen, rounds_by_hand(m, images, per_image))
        assert np.array_equal(select_points(m, images[:3], per_image), rounds_by_hand(m, images[:3], per_image))
    most = int(m.image_num_observations().max())
    assert np.array_equal(select_points(m, images, most), m.alive_points())
