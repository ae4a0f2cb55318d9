"""The fundamental matrix: Hartley's normalised eight-point algorithm, Sampson distance, RANSAC, epipoles.

Convention: x2^T F x1 = 0 for a point x1 in the first (left) image and x2 in the second (right) image, both in
pixels. The eight-point steps follow the seed paper (section 3.7): build the n x 9 system A f = 0, take the right
singular vector of the smallest singular value, then force rank 2 by zeroing F's smallest singular value. Hartley's
normalisation (centroid at the origin, mean distance sqrt(2)) is what makes the linear solve well conditioned.
"""

from dataclasses import dataclass

import numpy as np


def _homogeneous(points) -> np.ndarray:
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    return np.hstack([p, np.ones((len(p), 1))])


def hartley_normalization(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normalised points (N,2), 3x3 T) with T moving the centroid to 0 and the mean distance to sqrt(2)."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    centroid = p.mean(axis=0)
    mean_dist = np.linalg.norm(p - centroid, axis=1).mean()
    s = np.sqrt(2.0) / mean_dist if mean_dist > 1e-12 else 1.0
    T = np.array([[s, 0, -s * centroid[0]], [0, s, -s * centroid[1]], [0, 0, 1.0]])
    return (p - centroid) * s, T


def enforce_rank2(F: np.ndarray) -> np.ndarray:
    """Closest rank-2 matrix in Frobenius norm: zero the smallest singular value (paper steps 2-4)."""
    U, D, Vt = np.linalg.svd(np.asarray(F, dtype=float))
    D[2] = 0.0
    return U @ np.diag(D) @ Vt


def eight_point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """F from n >= 8 correspondences (N,2) by the normalised eight-point algorithm; unit Frobenius norm.

    With more than eight points this is the linear least-squares solution (smallest singular vector of A).
    """
    x1, x2 = np.asarray(x1, dtype=float).reshape(-1, 2), np.asarray(x2, dtype=float).reshape(-1, 2)
    if len(x1) != len(x2) or len(x1) < 8:
        raise ValueError(f"eight_point needs >= 8 correspondences in two equal-length arrays, got {len(x1)} and "
                         f"{len(x2)}")
    p1, T1 = hartley_normalization(x1)
    p2, T2 = hartley_normalization(x2)
    u1, v1, u2, v2 = p1[:, 0], p1[:, 1], p2[:, 0], p2[:, 1]
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=1)  # n x 9
    # thin SVD is much cheaper for many points, but with exactly 8 rows only the full V holds the null vector
    _, _, Vt = np.linalg.svd(A, full_matrices=len(A) < 9)
    F = enforce_rank2(Vt[-1].reshape(3, 3))
    F = T2.T @ F @ T1
    norm = np.linalg.norm(F)
    F = F / norm
    return F if F[2, 2] >= 0 else -F


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric distance (pixels) of each correspondence to the epipolar geometry F."""
    h1, h2 = _homogeneous(x1), _homogeneous(x2)
    Fx1 = h1 @ np.asarray(F).T
    Ftx2 = h2 @ np.asarray(F)
    num = np.sum(h2 * Fx1, axis=1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


def epipolar_lines(F: np.ndarray, points: np.ndarray, which: int) -> np.ndarray:
    """Lines (a, b, c) with a x + b y + c = 0, normalised so a^2 + b^2 = 1.

    which=2: lines in image 2 of points of image 1 (F x1); which=1: lines in image 1 of points of image 2 (F^T x2).
    """
    h = _homogeneous(points)
    lines = h @ (np.asarray(F).T if which == 2 else np.asarray(F))
    return lines / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)


def epipoles(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous epipoles (e1, e2), unit norm: F e1 = 0 (in image 1) and F^T e2 = 0 (in image 2).

    Divide by the third coordinate for pixels; a third coordinate near 0 means the epipole is at infinity
    (rectified or nearly parallel cameras).
    """
    U, _, Vt = np.linalg.svd(np.asarray(F, dtype=float))
    return Vt[-1], U[:, -1]


@dataclass(frozen=True)
class RansacConfig:
    """RANSAC for F. threshold: Sampson distance (px) for an inlier; confidence sets the adaptive stop."""

    threshold: float = 1.0
    confidence: float = 0.999
    max_iterations: int = 5000
    min_iterations: int = 50
    seed: int = 0


def ransac_fundamental(x1: np.ndarray, x2: np.ndarray,
                       config: RansacConfig = RansacConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Robust F: eight-point minimal samples scored by Sampson distance, adaptive iteration count, then a
    least-squares eight-point refit on the inliers (repeated while the inlier set grows).

    Returns (F, inlier mask). Raises ValueError with fewer than 8 correspondences or no consensus.
    """
    x1, x2 = np.asarray(x1, dtype=float).reshape(-1, 2), np.asarray(x2, dtype=float).reshape(-1, 2)
    n = len(x1)
    if n < 8:
        raise ValueError(f"need at least 8 matches for the fundamental matrix, got {n}")
    rng = np.random.default_rng(config.seed)
    best_mask, best_score = None, -1.0
    iterations, i = config.max_iterations, 0
    while i < max(iterations, config.min_iterations) and i < config.max_iterations:
        i += 1
        idx = rng.choice(n, 8, replace=False)
        try:
            F = eight_point(x1[idx], x2[idx])
        except np.linalg.LinAlgError:
            continue
        d = sampson_distance(F, x1, x2)
        mask = d < config.threshold
        score = mask.sum() - np.minimum(d, config.threshold).sum() / config.threshold * 1e-3  # MSAC-like tie break
        if score > best_score:
            best_score, best_mask = score, mask
            w = mask.mean()
            if w > 0:
                p_fail = 1.0 - w ** 8
                iterations = (int(np.ceil(np.log(1 - config.confidence) / np.log(p_fail)))
                              if 0 < p_fail < 1 else config.min_iterations)
    if best_mask is None or best_mask.sum() < 8:
        raise ValueError(f"no fundamental matrix found: fewer than 8 of {n} matches agree within "
                         f"{config.threshold} px")
    mask = best_mask
    F = eight_point(x1[mask], x2[mask])
    for _ in range(5):
        new_mask = sampson_distance(F, x1, x2) < config.threshold
        if new_mask.sum() < 8 or np.array_equal(new_mask, mask):
            break
        mask = new_mask
        F = eight_point(x1[mask], x2[mask])
    return F, sampson_distance(F, x1, x2) < config.threshold
