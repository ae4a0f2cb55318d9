"""Absolute camera pose from 2D-3D matches: P3P in RANSAC (OpenCV), then refinement with or without the focal.

Image points are "ideal" pixels: distortion removed but the focal length and principal point kept, so the
RANSAC threshold stays in pixels. Poses are cam_from_world (x = K (R X + t)).
"""

import cv2
import numpy as np


def pnp_ransac(X: np.ndarray, uv: np.ndarray, K: np.ndarray, threshold_px: float, seed: int = 0,
               confidence: float = 0.9999,
               max_iterations: int = 10000) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(R, t, inlier mask) or None: P3P minimal samples in RANSAC, SQPnP on the inliers, then LM on them.

    OpenCV's RANSAC fits its final pose to the inliers with EPnP, which can fail outright on a wide field of
    view (wide_orbit_small with an OPENCV lens: 635 RANSAC inliers, 58 under EPnP's pose); SQPnP is globally
    optimal and took 0.2 ms there. Of the candidate poses (RANSAC's, SQPnP's, and SQPnP's refined by LM) the
    one with the most inliers, in front of the camera, wins.
    """
    X = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3)
    uv = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(X) < 4:
        return None
    cv2.setRNGSeed(int(seed))
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(X, uv, K, None, iterationsCount=max_iterations,
                                                 reprojectionError=float(threshold_px), confidence=confidence,
                                                 flags=cv2.SOLVEPNP_P3P)
    if not ok or inliers is None or len(inliers) < 4:
        return None
    mask = np.zeros(len(X), bool)
    mask[inliers.ravel()] = True
    candidates = [(rvec, tvec)]
    try:
        ok, rvec_s, tvec_s = cv2.solvePnP(X[mask], uv[mask], K, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:  # SQPnP asserts on inliers with (almost) no spread: keep RANSAC's pose
        ok = False
    if ok:
        candidates.append((rvec_s, tvec_s))
        candidates.append(cv2.solvePnPRefineLM(X[mask], uv[mask], K, None, rvec_s.copy(), tvec_s.copy()))
    best = None
    for rv, tv in reversed(candidates):  # the refined pose first: it wins ties
        R, t = cv2.Rodrigues(rv)[0], np.asarray(tv, dtype=float).ravel()
        inl = reprojection_errors(X, uv, K, R, t) < threshold_px
        if best is None or inl.sum() > best[2].sum():
            best = (R, t, inl)
    return best


def rival_poses(X: np.ndarray, uv: np.ndarray, K: np.ndarray, inliers: np.ndarray, threshold_px: float,
                min_inliers: float, count: int = 2,
                seed: int = 0) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Other poses that fit many of the matches the best pose leaves out (`inliers` is its mask): a list of
    (R, t, inlier mask over all matches), each from P3P RANSAC on the matches no pose before it fits; the
    search ends at the first that fits fewer than `min_inliers` of those.

    Repeated structure makes the matches of a view support a second pose one period away (a tiled floor seen
    through a wide lens: the same rotation, 6 m off, and as many inliers as the true pose), so the pose with
    the most inliers is then a choice rather than a measurement (sfm/register.py decides it).
    """
    rest = ~np.asarray(inliers, bool)
    out = []
    for _ in range(count):
        idx = np.flatnonzero(rest)
        if len(idx) < max(min_inliers, 4):
            break
        est = pnp_ransac(X[idx], uv[idx], K, threshold_px, seed=seed)
        if est is None or est[2].sum() < min_inliers:
            break
        inl = reprojection_errors(X, uv, K, est[0], est[1]) < threshold_px
        out.append((est[0], est[1], inl))
        rest &= ~inl
    return out


def reprojection_errors(X: np.ndarray, uv: np.ndarray, K: np.ndarray, R: np.ndarray,
                        t: np.ndarray) -> np.ndarray:
    """Pixel distance of each projected point to its observation; inf behind the camera."""
    Xc = np.asarray(X) @ R.T + t
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = (Xc[:, :2] / z[:, None]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    err = np.linalg.norm(proj - uv, axis=1)
    err[~(z > 0) | ~np.isfinite(err)] = np.inf
    return err


def refine_pose_and_focal(X: np.ndarray, uv: np.ndarray, K: np.ndarray, R: np.ndarray,
                          t: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares pose and focal length (one f for x and y) on inlier matches: (R, t, f).

    Used when the camera's focal length is only a guess and no registered image shares the camera yet, as
    COLMAP's estimate_focal_length does; the Huber loss keeps a few bad matches from pulling the focal.
    """
    from scipy.optimize import least_squares  # noqa: PLC0415 - slow to import; images of unknown focal only

    rvec0 = cv2.Rodrigues(np.asarray(R, dtype=float))[0].ravel()
    f0 = float(K[0, 0])
    cx, cy = K[0, 2], K[1, 2]

    def fun(p):
        Rm = cv2.Rodrigues(p[:3])[0]
        Xc = X @ Rm.T + p[3:6]
        f = f0 * np.exp(p[6])
        return ((Xc[:, :2] / Xc[:, 2:3]) * f + [cx, cy] - uv).ravel()

    res = least_squares(fun, np.r_[rvec0, t, 0.0], loss="huber", f_scale=2.0, max_nfev=100)
    return cv2.Rodrigues(res.x[:3])[0], res.x[3:6], f0 * float(np.exp(res.x[6]))
