"""Relative pose of two calibrated views from normalised correspondences (five-point essential matrix in
RANSAC), and the rotation of a camera turning in place (two-point RANSAC).

OpenCV's estimator is used with the identity camera matrix on normalised coordinates, so its pixel threshold
is given in normalised units (pixels divided by the focal length).
"""

import numpy as np
from numba import njit


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
    a = np.ascontiguousarray(x1[candidates], dtype=np.float64)
    b = np.ascontiguousarray(x2[candidates], dtype=np.float64)
    best, good = None, np.empty(len(a), bool)
    for R, tt in ((R1, t), (R2, t), (R1, -t), (R2, -t)):
        R, tt = np.ascontiguousarray(R, dtype=np.float64), np.ascontiguousarray(tt, dtype=np.float64)
        count = _in_front(R, tt, a, b, _FAR, good)
        if best is None or count > best[3]:
            best = (R, tt, good.copy(), count)
    R, tt, good, count = best
    if count < 5:
        return None
    inliers = np.zeros(len(x1), bool)
    inliers[np.flatnonzero(candidates)[good]] = True
    return R, tt / np.linalg.norm(tt), inliers


@njit(cache=True, nogil=True)
def _in_front(R, t, x1, x2, far, out):
    """Fills `out` with whether the midpoint of each match's rays (triangulation.two_view_midpoints, camera [I|0]
    and [R|t]) lies in front of both cameras and nearer than `far` baselines; returns how many do. Compiled: the
    view graph tests four decompositions for each of thousands of pairs."""
    c0 = -(R[0, 0] * t[0] + R[1, 0] * t[1] + R[2, 0] * t[2])  # the second centre, -R^T t
    c1 = -(R[0, 1] * t[0] + R[1, 1] * t[1] + R[2, 1] * t[2])
    c2 = -(R[0, 2] * t[0] + R[1, 2] * t[1] + R[2, 2] * t[2])
    count = 0
    for n in range(x1.shape[0]):
        u, v = x1[n, 0], x1[n, 1]  # the first ray (u, v, 1); the second, R^T (x2, 1), in the first frame:
        e0 = x2[n, 0] * R[0, 0] + x2[n, 1] * R[1, 0] + R[2, 0]
        e1 = x2[n, 0] * R[0, 1] + x2[n, 1] * R[1, 1] + R[2, 1]
        e2 = x2[n, 0] * R[0, 2] + x2[n, 1] * R[1, 2] + R[2, 2]
        a, b, c = u * u + v * v + 1.0, u * e0 + v * e1 + e2, e0 * e0 + e1 * e1 + e2 * e2
        p, q = u * c0 + v * c1 + c2, e0 * c0 + e1 * c1 + e2 * c2
        det = b * b - a * c
        ok = False
        if abs(det) > 1e-12 * a * c:
            s1, s2 = (b * q - c * p) / det, (a * q - b * p) / det
            X0, X1, X2 = 0.5 * (s1 * u + c0 + s2 * e0), 0.5 * (s1 * v + c1 + s2 * e1), 0.5 * (s1 + c2 + s2 * e2)
            z2 = X0 * R[2, 0] + X1 * R[2, 1] + X2 * R[2, 2] + t[2]
            ok = 0 < X2 < far and 0 < z2 < far
        out[n] = ok
        count += ok
    return count


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


def rotation_between_views(x1: np.ndarray, x2: np.ndarray, threshold: float, seed: int = 0, min_inliers: int = 3,
                           confidence: float = 0.999,
                           max_iterations: int = 200) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, inlier mask) of the rotation about the camera centre that best explains x2 ~ R x1 (normalised
    coordinates; inliers within `threshold` of their match in view 2), or None with fewer than 3 matches.

    Two-point RANSAC on the viewing rays, then least squares (`rotation.nearest_rotation` of the rays' correlation)
    on the inliers. RANSAC draws the samples that find, at `confidence`, a rotation of `min_inliers` inliers where
    one exists (fewer as better ones turn up): a caller asking whether a rotation explains most of a pair's matches
    pays for few samples. A camera turning in place has no essential matrix (any baseline fits its matches), and its
    homography is fitted with 8 degrees of freedom where 3 suffice; a pair of a few dozen matches is told apart by
    the rotation's own count."""
    x1 = np.ascontiguousarray(x1, dtype=np.float64).reshape(-1, 2)
    x2 = np.ascontiguousarray(x2, dtype=np.float64).reshape(-1, 2)
    n = len(x1)
    if n < 3:
        return None
    r1, r2 = _rays(x1), _rays(x2)
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
        best = _best_sample(r1, r2, x2, threshold2, samples, best, inliers, found)
        drawn += _CHUNK
    return _refit(r1, r2, x2, threshold2, inliers, found)


_CHUNK = 25  # samples of `rotation_between_views` drawn before its stopping rule is looked at again


@njit(cache=True, nogil=True)
def _rays(x):
    """Unit viewing rays (n,3) of normalised image points (n,2)."""
    out = np.empty((x.shape[0], 3))
    for k in range(x.shape[0]):
        norm = np.sqrt(x[k, 0] ** 2 + x[k, 1] ** 2 + 1.0)
        out[k, 0], out[k, 1], out[k, 2] = x[k, 0] / norm, x[k, 1] / norm, 1.0 / norm
    return out


@njit(cache=True, nogil=True)
def _rotation_inliers(R, r1, x2, threshold2, out):
    """Fills `out` with whether R turns each ray of r1 to within the threshold of its match x2, in front of the
    camera; returns how many do."""
    count = 0
    for k in range(r1.shape[0]):
        p0 = R[0, 0] * r1[k, 0] + R[0, 1] * r1[k, 1] + R[0, 2] * r1[k, 2]
        p1 = R[1, 0] * r1[k, 0] + R[1, 1] * r1[k, 1] + R[1, 2] * r1[k, 2]
        z = R[2, 0] * r1[k, 0] + R[2, 1] * r1[k, 1] + R[2, 2] * r1[k, 2]
        d2 = (p0 - x2[k, 0] * z) ** 2 + (p1 - x2[k, 1] * z) ** 2
        ok = z > 0 and d2 < threshold2 * z * z
        out[k] = ok
        count += ok
    return count


@njit(cache=True, nogil=True)
def _kabsch(M):
    """rotation.nearest_rotation of one 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    if np.linalg.det(U @ Vt) < 0:
        U[:, 2] = -U[:, 2]
    return U @ Vt


@njit(cache=True, nogil=True)
def _best_sample(r1, r2, x2, threshold2, samples, best, inliers, found):
    """The rotation of each sample (a pair of matches) scored by its inliers; where one has more than `best`,
    `inliers` becomes the first such sample's. Returns the best count. Compiled, as the view graph asks every
    pair."""
    for s in range(samples.shape[0]):
        a, b = samples[s, 0], samples[s, 1]
        M = np.outer(r2[a], r1[a]) + np.outer(r2[b], r1[b])
        count = _rotation_inliers(_kabsch(M), r1, x2, threshold2, found)
        if count > best:
            best = count
            inliers[:] = found
    return best


@njit(cache=True, nogil=True)
def _refit(r1, r2, x2, threshold2, inliers, found):
    """(R, inliers): the least-squares rotation of the inliers, refitted on its own inliers up to three times."""
    R = np.eye(3)
    for _ in range(3):
        if inliers.sum() < 2:
            break
        M = np.zeros((3, 3))
        for k in range(r1.shape[0]):
            if inliers[k]:
                M += np.outer(r2[k], r1[k])
        R = _kabsch(M)
        _rotation_inliers(R, r1, x2, threshold2, found)
        if np.array_equal(found, inliers):
            break
        inliers[:] = found
    return R, inliers
