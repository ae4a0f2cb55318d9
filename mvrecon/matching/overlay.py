"""Matches that stay on one pixel because the feature is printed on the images, not part of the scene.

A logo, a timestamp burnt in by the camera, a frame counter or sensor dust sits at the same pixel of every image.
Its matches between two views do not move, and a match that does not move satisfies x^T [e]x x = 0 for every
epipole e: every pure-translation fundamental matrix explains it. So verification keeps such matches, and a pair
that the scene does not connect is verified on them alone. On the catalog's object_orbit_small with a logo and a
timestamp drawn on each view, the relative-pose AUC@5 fell from 0.99 to 0.10 (COLMAP's pipeline: 0.22).

A keypoint is *fixed* when, counting its own image, half the images of its size (and at least three) have a
keypoint within about `radius` px of it; a match between two fixed keypoints that moves less than `radius` is
dropped before verification. What is printed on the images is on all of them, while chance neighbours are
not: at three images, a third of templeRing's and opensfm_lund's keypoints had some within 2 px in two other
images. Two copies of one view (a duplicate, two shots from a tripod) keep their matches, and the copy is
registered where its original is: `same_view` tells such a pair, so that the run can name it. A camera that never
moves (a time-lapse) is left with no match to verify, which is what it has to reconstruct from.
"""

import math

import numpy as np

MIN_IMAGES, MIN_SHARE = 3, 0.5  # a feature at one pixel in this many images, and this share of them, is printed
RADIUS_PX = 1.0
SAME_VIEW_PX = 0.5  # verified matches that move less than this (median) between two images: one view twice


def fixed_keypoints(positions: dict, sizes: dict, min_images: int = MIN_IMAGES, min_share: float = MIN_SHARE,
                    radius: float = RADIUS_PX) -> dict:
    """image id -> bool mask of its keypoints that are fixed (module docstring). `positions`: image id -> (N,2+)
    keypoints (x, y first); `sizes`: image id -> (width, height); only images of one size are compared.

    Cells of 2 * radius on four grids offset by half a cell: two points less than `radius` apart along each
    axis share a cell in one of them (along one axis, the boundaries of two grids are `radius` apart, so a gap
    shorter than that crosses at most one of them). Linear in the number of keypoints."""
    out = {i: np.zeros(len(p), bool) for i, p in positions.items()}
    groups = {}
    for i, size in sizes.items():
        if i in positions and len(positions[i]):
            groups.setdefault(tuple(size), []).append(i)
    for ids in groups.values():
        needed = max(min_images, math.ceil(min_share * len(ids)))
        if len(ids) < needed:
            continue
        xy = np.concatenate([np.asarray(positions[i], float)[:, :2] for i in ids])
        image = np.repeat(np.arange(len(ids)), [len(positions[i]) for i in ids])
        fixed = np.zeros(len(xy), bool)
        for offset in ((0, 0), (radius, 0), (0, radius), (radius, radius)):
            cell = np.floor((xy + offset) / (2 * radius)).astype(np.int64)
            cell -= cell.min(axis=0)
            key = cell[:, 0] * (cell[:, 1].max() + 1) + cell[:, 1]
            occupied = _runs(np.sort(key * len(ids) + image))[0] // len(ids)  # one row per (cell, image)
            cells, images_in_cell = _runs(occupied)
            fixed |= images_in_cell[np.searchsorted(cells, key)] >= needed
        for i, part in zip(ids, np.split(fixed, np.cumsum([len(positions[i]) for i in ids])[:-1])):
            out[i] = part
    return out


def _runs(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(value, count) of each run of equal values in a sorted array: `np.unique(values, return_counts=True)`
    without its sort, or its hashing (numpy 2.4 hashes integers, 2-4x slower than sorting them: fixed_keypoints
    took 19 ms of templeSparseRing's matching stage, 7 ms this way)."""
    starts = np.flatnonzero(np.r_[True, values[1:] != values[:-1]]) if len(values) else np.zeros(0, np.int64)
    return values[starts], np.diff(np.r_[starts, len(values)])


def drop_static(matches: np.ndarray, xy1: np.ndarray, xy2: np.ndarray, fixed1: np.ndarray, fixed2: np.ndarray,
                radius: float = RADIUS_PX) -> np.ndarray:
    """`matches` (N,2) without those between two fixed keypoints that move less than `radius` px."""
    if len(matches) == 0:
        return matches
    a, b = matches[:, 0], matches[:, 1]
    still = np.linalg.norm(xy1[a, :2] - xy2[b, :2], axis=1) < radius
    return matches[~(still & fixed1[a] & fixed2[b])]


def same_view(xy1: np.ndarray, xy2: np.ndarray, inliers: np.ndarray, max_shift: float = SAME_VIEW_PX) -> bool:
    """Whether two images show one view: their verified matches (`inliers`, (N,2) indices into the keypoints
    `xy1`, `xy2`) stay on their pixels, by less than `max_shift` px at the median. A copy of a photo moves them by
    0 px, the same photo saved again as JPEG by 0.04 px, and templeSparseRing's two shots from one gantry pose
    (0001 and 0011) by 0.14 px; its neighbouring views by 9 px and more."""
    if len(inliers) == 0:
        return False
    sample = inliers[:: max(1, len(inliers) // 64)]  # 64 of them tell as well as all, at a tenth of the cost
    shift = xy1[sample[:, 0], :2] - xy2[sample[:, 1], :2]
    return bool(np.median(np.hypot(shift[:, 0], shift[:, 1])) < max_shift)
