"""Relative pose of two calibrated views from normalised correspondences (five-point essential matrix in
RANSAC), and the rotation of a camera turning in place (two-point RANSAC).

OpenCV's estimator is used with the identity camera matrix on normalised coordinates, so its pixel threshold
is given in normalised units (pixels divided by the focal length).
"""

import numpy as np

from .triangulation import two_view_midpoints


def relative_pose(x1: np.ndarray, x2: np.ndarray, threshold: float, seed: int = 0,
                  confidence: float = 0.9999) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(R, t, inlier mask) with x2 ~ R x1 + t and |t| = 1, or None when no essential matrix is found.

    x1, x2: (N,2) undistorted normalised coordinates. The returned mask keeps only the inliers in front of
    both cameras (cheirality check of the chosen decomposition).
    """
    x1, x2 = np.asarray(x1, float).reshape(-1, 2), np.asarray(x2, float).reshape(-1, 2)
    found = essential_matrix(x1, x2, threshold, seed, confidence)
    return None if found is None else pose_from_essential(found[0], x1, x2, found[1])


def essential_matrix(x1: np.ndarray, x2: np.ndarray, threshold: float, seed: int = 0,
                     confidence: float = 0.9999) -> tuple[np.ndarray, np.ndarray] | None:
    """(E, inlier mask) of the five-point RANSAC on normalised coordinates (inliers within `threshold` of their
    epipolar line, before any cheirality check), or None when none is found."""
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    x1 = np.ascontiguousarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.ascontiguousarray(x2, dtype=np.float64).reshape(-1, 2)
    if len(x1) < 5:
        return None
    cv2.setRNGSeed(int(seed))
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.RANSAC, prob=confidence, threshold=threshold,
                                   maxIters=10000)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    return E, mask.ravel() > 0


_FAR = 50.0  # points farther than this many baselines decide nothing about cheirality (OpenCV's choice too)


def pose_from_essential(E: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                        candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(R, t, inliers) of the decomposition of E that puts most `candidates` in front of both cameras (and
    nearer than 50 baselines), or None when fewer than 5 are. The four hypotheses are tested on the rays'
    closed-form midpoints: with OpenCV's recoverPose (a DLT per point and hypothesis) `relative_pose` took
    2.4 ms per templeRing pair, 1.3 ms with this, for the same poses."""
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    R1, R2, t = cv2.decomposeEssentialMat(E)
    t = t.ravel()
    a, b = x1[candidates], x2[candidates]
    best = None
    for R, tt in ((R1, t), (R2, t), (R1, -t), (R2, -t)):
        X = two_view_midpoints(R, tt, a, b)
        z1, z2 = X[:, 2], X @ R[2] + tt[2]
        with np.errstate(invalid="ignore"):
            good = (z1 > 0) & (z2 > 0) & (z1 < _FAR) & (z2 < _FAR)
        if best is None or good.sum() > best[2].sum():
            best = (R, tt, good)
    R, tt, good = best
    if good.sum() < 5:
        return None
    inliers = np.zeros(len(x1), bool)
    inliers[np.flatnonzero(candidates)[good]] = True
    return R, tt / np.linalg.norm(tt), inliers


def focal_from_fundamental(F: np.ndarray, principal_point1: np.ndarray,
                           principal_point2: np.ndarray) -> tuple[float, float]:
    """Focal lengths (f1, f2) of two views from F with known principal points (Bougnoux 1998).

    Each is NaN when the formula gives a negative f^2 (noise, or a degenerate configuration such as optical
    axes meeting in a point); callers fall back to their prior then.
    """
    F = np.asarray(F, dtype=float)
    p1 = np.r_[np.asarray(principal_point1, float), 1.0]
    p2 = np.r_[np.asarray(principal_point2, float), 1.0]
    Ib = np.diag([1.0, 1.0, 0.0])

    def one(F, pa, pb):
        # focal of the view whose point is pa, with epipole eb in the other view (F^T eb = 0)
        U, _, Vt = np.linalg.svd(F)
        eb = U[:, 2]
        ex = np.array([[0, -eb[2], eb[1]], [eb[2], 0, -eb[0]], [-eb[1], eb[0], 0]])
        num = -(pb @ ex @ Ib @ F @ pa) * (pa @ F.T @ pb)
        den = pb @ ex @ Ib @ F @ Ib @ F.T @ pb
        f2 = num / den if abs(den) > 1e-300 else np.nan
        return float(np.sqrt(f2)) if f2 > 0 else float("nan")

    return one(F, p1, p2), one(F.T, p2, p1)


def homography_translation(H: np.ndarray, K1: np.ndarray, K2: np.ndarray) -> float | np.ndarray:
    """|t|/d of the calibrated homography Hn = K2^-1 H K1 ~ R + t n^T/d, from the spread of its singular values:
    a pure rotation has three equal singular values; a translation along or towards the plane (distance d)
    spreads them by about |t|/d, the parallax angle at the plane in radians. K1, K2 may be stacks (n,3,3) of
    calibrations to try: the result is then one value per calibration."""
    s = np.linalg.svd(np.linalg.inv(K2) @ np.asarray(H, float) @ K1, compute_uv=False)
    spread = (s[..., 0] - s[..., 2]) / s[..., 1]
    return float(spread) if np.ndim(spread) == 0 else spread


_CHUNK = 25  # samples of `rotation_between_views` drawn before its stopping rule is looked at again


def rotation_between_views(x1: np.ndarray, x2: np.ndarray, threshold: float, seed: int = 0, min_inliers: int = 3,
                           confidence: float = 0.999,
                           max_iterations: int = 200) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, inlier mask) of the rotation about the camera centre that best explains x2 ~ R x1 (normalised
    coordinates; inliers within `threshold` of their match in view 2), or None with fewer than 3 matches.

    Two-point RANSAC on the viewing rays, then least squares (the nearest rotation to the rays' correlation) on the
    inliers, compiled (`kernels`: the global mapper's view graph asks it of every pair). RANSAC draws the samples
    that find, at `confidence`, a rotation of `min_inliers` inliers where one exists (fewer as better ones turn
    up): a caller asking whether a rotation explains most of a pair's matches pays for few samples. A camera
    turning in place has no essential matrix (any baseline fits its matches), and its homography is fitted with 8
    degrees of freedom where 3 suffice; a pair of a few dozen matches is told apart by the rotation's own count."""
    from .kernels import best_rotation_sample, refit_rotation, unit_rays  # noqa: PLC0415 - numba, at the first call

    x1 = np.ascontiguousarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.ascontiguousarray(x2, dtype=np.float64).reshape(-1, 2)
    n = len(x1)
    if n < 3:
        return None
    r1, r2 = unit_rays(x1), unit_rays(x2)
    threshold2 = float(threshold) ** 2

    def needed(count):  # samples that find a rotation of `count` inliers at the confidence
        share = min(count / n, 1.0 - 1e-9) ** 2
        return np.log(1 - confidence) / np.log1p(-share) if share > 0 else np.inf

    rng = np.random.default_rng(seed)
    inliers, found, best, drawn = np.zeros(n, bool), np.empty(n, bool), 0, 0
    samples = np.empty((_CHUNK, 2), np.int64)
    while drawn < min(max_iterations, needed(max(min_inliers, best))):
        samples[:, 0] = rng.integers(n, size=_CHUNK)
        samples[:, 1] = (samples[:, 0] + rng.integers(1, n, size=_CHUNK)) % n  # two distinct matches each
        best = best_rotation_sample(r1, r2, x2, threshold2, samples, best, inliers, found)
        drawn += _CHUNK
    return refit_rotation(r1, r2, x2, threshold2, inliers, found)
