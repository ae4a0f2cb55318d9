"""Guided matching (COLMAP's guided_matching): once a pair's two-view geometry is known, its descriptors are
matched again among the keypoint pairs that geometry admits.

The ratio test then compares a keypoint's best neighbour with the second best on its epipolar band (or at its
homography transfer), not anywhere in the other image, so that repeated or weak texture elsewhere no longer
vetoes a correct match. The result replaces the pair's inliers; every one lies within `max_error` pixels of
the geometry by construction (Sampson distance to F, or the transfer distance by H for planar and panoramic
pairs). It costs a second descriptor product for each verified pair.
"""

from collections.abc import Callable

import numpy as np

from .matcher import MatcherConfig, Prepared, match_descriptors
from .verify import TwoViewResult

_BY_HOMOGRAPHY = ("PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")


def epipolar_band(F: np.ndarray, points1: np.ndarray, points2: np.ndarray, max_error: float
                  ) -> Callable[[int, int], np.ndarray]:
    """admissible(start, stop): whether each of points1[start:stop] and each of points2 is within `max_error`
    pixels of F by the Sampson distance (geometry.fundamental.sampson_distance over all pairs)."""
    h1 = np.column_stack([points1[:, :2], np.ones(len(points1))])
    h2 = np.column_stack([points2[:, :2], np.ones(len(points2))])
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    den1 = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2
    den2 = Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    limit = max_error ** 2

    def admissible(start: int, stop: int) -> np.ndarray:
        num = (Fx1[start:stop] @ h2.T) ** 2
        return num <= limit * (den1[start:stop, None] + den2[None, :])

    return admissible


def homography_disc(H: np.ndarray, points1: np.ndarray, points2: np.ndarray, max_error: float
                    ) -> Callable[[int, int], np.ndarray]:
    """admissible(start, stop): whether each of points2 lies within `max_error` pixels of H's image of each
    of points1[start:stop]."""
    h1 = np.column_stack([points1[:, :2], np.ones(len(points1))]) @ H.T
    w = np.where(np.abs(h1[:, 2]) > 1e-12, h1[:, 2], 1e-12)
    mapped = h1[:, :2] / w[:, None]
    p2 = points2[:, :2]
    limit = max_error ** 2

    def admissible(start: int, stop: int) -> np.ndarray:
        d = mapped[start:stop, None, :] - p2[None, :, :]
        return np.einsum("ijk,ijk->ij", d, d) <= limit

    return admissible


def guided_inliers(points1: np.ndarray, desc1: np.ndarray | Prepared, points2: np.ndarray,
                   desc2: np.ndarray | Prepared, result: TwoViewResult, max_error: float,
                   config: MatcherConfig = MatcherConfig()) -> np.ndarray:
    """(K,2) index pairs: mutual nearest neighbours passing `config`'s ratio and distance tests among the
    keypoint pairs `result`'s geometry admits (H for planar and panoramic pairs, else F). A pair without that
    geometry keeps its inliers."""
    if result.config in _BY_HOMOGRAPHY and result.H is not None:
        admissible = homography_disc(result.H, points1, points2, max_error)
    elif result.F is not None:
        admissible = epipolar_band(result.F, points1, points2, max_error)
    else:
        return result.inliers
    return match_descriptors(desc1, desc2, config, admissible)
