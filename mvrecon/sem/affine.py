"""The affine fundamental matrix: match verification for parallel-projection views.

Under parallel projection the epipolar lines are parallel and F has the form [[0,0,a],[0,0,b],[c,d,e]], i.e. the
single linear constraint a u2 + b v2 + c u1 + d v1 + e = 0. The perspective eight-point F (and E) is
ill-conditioned on such views: the rays are nearly parallel and the epipoles sit at infinity. Hartley and
Zisserman's Gold Standard estimate (algorithm 14.1) is linear: the constraint is a hyperplane in the joint
4D space (u2, v2, u1, v1), and the orthogonal regression plane through the centroid (smallest singular vector)
minimises the true geometric (reprojection) error. A point's distance to that plane is its reprojection error,
which is what RANSAC thresholds.
Convention: x2^T F x1 = 0, as in `mvrecon.geometry.fundamental`.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AffineRansacConfig:
    """RANSAC for the affine F. threshold_px: geometric error (px) counted as inlier (SIFT on SEM images is
    good to well under a pixel; 2 px keeps matches on low-contrast regions). min_inliers: fewer verified matches
    than this and the pair counts as unmatched."""

    threshold_px: float = 2.0
    iterations: int = 1000
    confidence: float = 0.9999
    min_inliers: int = 12
    seed: int = 0


def _as_matrix(normal: np.ndarray, offset: float) -> np.ndarray:
    a, b, c, d = normal
    return np.array([[0.0, 0.0, a], [0.0, 0.0, b], [c, d, offset]])


def affine_fundamental(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Gold Standard affine F (H&Z alg. 14.1) from >= 4 correspondences; F is scaled so (a,b,c,d) is a unit vector."""
    x1, x2 = np.asarray(x1, dtype=float), np.asarray(x2, dtype=float)
    if len(x1) < 4 or x1.shape != x2.shape:
        raise ValueError(f"the affine fundamental matrix needs >= 4 correspondences, got {len(x1)}")
    X = np.hstack([x2, x1])
    mean = X.mean(axis=0)
    _, _, Vt = np.linalg.svd(X - mean, full_matrices=False)
    normal = Vt[-1]
    return _as_matrix(normal, -float(normal @ mean))


def affine_epipolar_error(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Geometric (reprojection) error in pixels of each correspondence: its distance to the 4D constraint plane."""
    normal = np.array([F[0, 2], F[1, 2], F[2, 0], F[2, 1]])
    X = np.hstack([np.asarray(x2, dtype=float), np.asarray(x1, dtype=float)])
    return np.abs(X @ normal + F[2, 2]) / np.linalg.norm(normal)


def ransac_affine_fundamental(x1: np.ndarray, x2: np.ndarray, config: AffineRansacConfig = AffineRansacConfig()
                              ) -> tuple[np.ndarray | None, np.ndarray]:
    """(F, inlier mask): minimal 4-point samples, scored by inlier count, refit by Gold Standard on the inliers.

    Returns (None, all-False mask) when fewer than `config.min_inliers` correspondences agree.
    """
    x1, x2 = np.asarray(x1, dtype=float), np.asarray(x2, dtype=float)
    n = len(x1)
    none = np.zeros(n, dtype=bool)
    if n < max(4, config.min_inliers):
        return None, none
    rng = np.random.default_rng(config.seed)
    best_mask, best_count = none, 0
    needed, i = config.iterations, 0
    while i < min(needed, config.iterations):
        i += 1
        idx = rng.choice(n, 4, replace=False)
        F = affine_fundamental(x1[idx], x2[idx])
        mask = affine_epipolar_error(F, x1, x2) < config.threshold_px
        count = int(mask.sum())
        if count > best_count:
            best_mask, best_count = mask, count
            w = count / n
            needed = np.log(1 - config.confidence) / np.log(max(1e-12, 1 - w ** 4)) if w < 1 else 1
    if best_count < config.min_inliers:
        return None, none
    for _ in range(3):  # Gold Standard refit, then re-collect inliers of the refined F
        F = affine_fundamental(x1[best_mask], x2[best_mask])
        mask = affine_epipolar_error(F, x1, x2) < config.threshold_px
        if mask.sum() < config.min_inliers or np.array_equal(mask, best_mask):
            break
        best_mask = mask
    return F, best_mask


def tilt_axis_from_affine_fundamental(F: np.ndarray) -> float:
    """In-plane tilt axis (deg from image +x towards +y, in [0, 180)) of a pure eucentric tilt pair.

    Tilting moves points only across the axis, so the constraint reads a.x2 - a.x1 = const for the axis direction
    a: the first image's coefficients (c, d) point along the axis.
    """
    return float(np.degrees(np.arctan2(F[2, 1], F[2, 0])) % 180.0)
