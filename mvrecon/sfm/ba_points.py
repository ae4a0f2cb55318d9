"""The points a bundle adjustment during growth optimises: a well-spread subset, as TheiaSfM selects tracks.

Poses and intrinsics are pinned as well by a few hundred good points per image as by thousands, while a GTSAM
iteration costs in proportion to the observations. Each image's frame is cut into a 16 x 16 grid; its points
are taken round by round (the best point of every cell, then the second best of every cell, ...), best meaning
the longest track, then the lowest reprojection error, until the image has `per_image` of them. An image with
fewer points keeps them all, so sparse scenes are optimised in full. The points left out are re-fitted to the
new poses afterwards (`triangulate.refine_existing_points`); the final BAs of a model use every point, except
in a large model (MapperConfig.final_ba_subset_min_images). The global mapper's BAs further keep only the
points that three images or more see (`long_points`), as GLOMAP's do.
"""

import numpy as np

from .model import Reconstruction

GRID = 16


def select_points(model: Reconstruction, images: np.ndarray | list[int], per_image: int) -> np.ndarray:
    """Point ids: up to `per_image` well-spread, long, accurate points of each of `images` (their union)."""
    obs = model.observations_of_images(images)
    if len(obs) == 0:
        return np.zeros(0, np.int64)
    img, pid = model.obs_image.data[obs], model.obs_point.data[obs]
    cams = sorted(model.cameras)
    size = np.array([(model.cameras[c].width, model.cameras[c].height) for c in cams], float)
    xy = model.keypoints_at(img, model.obs_kp.data[obs])
    wh = size[np.searchsorted(cams, model.camera_of[img])]
    gx = np.clip((xy[:, 0] * GRID / wh[:, 0]).astype(np.int64), 0, GRID - 1)
    gy = np.clip((xy[:, 1] * GRID / wh[:, 1]).astype(np.int64), 0, GRID - 1)
    cell = (img * GRID + gy) * GRID + gx
    by_error = np.argsort(model.reprojection_errors(obs)[0], kind="stable")
    length = model.point_num_observations()[pid]
    shorter = int(length.max()) - length  # 0 = the longest track, below `span`
    span = int(shorter.max()) + 1

    def best_first(key: np.ndarray) -> np.ndarray:
        """The order by `key` (int64), then by shortness, then by error: np.lexsort((err, shorter, key)) in
        two stable sorts, which take less time on a large model's millions of views (docs/benchmarks.md,
        "Every view projected in one compiled pass, and the BA points chosen by two sorts")."""
        return by_error[np.argsort(key[by_error] * span + shorter[by_error], kind="stable")]

    order = best_first(cell)  # by cell, best first
    rank = np.empty(len(obs), np.int64)
    rank[order] = _places(cell[order])  # 0 = best of its cell
    order = best_first(img * (int(rank.max()) + 1) + rank)  # by image, round by round
    return np.unique(pid[order][_places(img[order]) < per_image])


def _places(runs: np.ndarray) -> np.ndarray:
    """Each entry's place (0, 1, ...) in its run of equal values of the sorted array `runs`."""
    start = np.flatnonzero(np.r_[True, runs[1:] != runs[:-1]])
    return np.arange(len(runs)) - np.repeat(start, np.diff(np.r_[start, len(runs)]))


def held_observations(model: Reconstruction, points: np.ndarray, min_views: int) -> np.ndarray:
    """(images,) each image's observations of those of `points` seen by `min_views` images or more: what holds its
    pose beyond the baselines of its pairs (a point of the image and one other fits it anywhere along theirs)."""
    long = points[model.point_num_observations()[points] >= min_views]
    return np.bincount(model.obs_image.data[model.observations_of_points(long)], minlength=len(model.image_ids))


def long_points(model: Reconstruction, points: np.ndarray, min_views: int, enough: int) -> np.ndarray:
    """The ids of `points` seen by `min_views` images or more, and the others of each registered image that has
    fewer than `enough` observations of those (so that no pose loses its hold). A point seen twice is where a
    repeated structure's wrong match lives: nothing checks it but its own two rays, and in a bundle adjustment it
    pulls the two poses as hard as a true one (facade_small, the global mapper's rounds from pycolmap global's
    poses and camera, AUC@5 0.95: 0.88 after them with the two-view points left out, 0.81 with them)."""
    long = model.point_num_observations()[points] >= min_views
    if long.all():
        return points
    weak = model.registered & (held_observations(model, points, min_views) < enough)
    if not weak.any():
        return points[long]
    obs = model.observations_of_points(points[~long])
    rescue = np.unique(model.obs_point.data[obs][weak[model.obs_image.data[obs]]])
    return np.union1d(points[long], rescue)
