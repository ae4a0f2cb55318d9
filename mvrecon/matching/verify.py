"""Geometric verification of putative matches: F, E and H with OpenCV's USAC/MAGSAC++, COLMAP's classification.

Each pair gets a fundamental matrix (always), an essential matrix (when both cameras have a trusted focal prior,
estimated on undistorted normalised coordinates through the camera model) and a homography. The inlier counts
then decide the pair's configuration the way COLMAP's `EstimateCalibratedTwoViewGeometry` does:

- CALIBRATED: E explains at least `min_E_F_inlier_ratio` of F's inliers (so the focal prior fits);
- UNCALIBRATED: F explains the pair, E was not tried or did not fit;
- PLANAR_OR_PANORAMIC: H explains more than `max_H_inlier_ratio` of the E (or F) inliers: a plane, or no baseline.
  With calibrated cameras it is split by decomposing the homography in normalised coordinates,
  Hn = K2^-1 H K1 ~ R + t n^T / d: a rotation-only pair (singular values of Hn equal within
  `panoramic_max_translation`, i.e. |t|/d below it) is PANORAMIC, anything else PLANAR;
- DEGENERATE: fewer than `min_num_inliers` inliers, or an inlier ratio under `min_inlier_ratio`.

Coordinates are COLMAP pixels (as stored in the database), so the F and H written back are in COLMAP's convention.
"""

from dataclasses import dataclass, field

import numpy as np

from ..config import bounded
from ..database import CameraInfo
from ..geometry import camera as camera_model
from ..geometry.two_view import homography_translation


@dataclass(frozen=True)
class VerifyConfig:
    # pixels; RANSAC inlier threshold for F and H, divided by the focal length for E
    max_error: float = bounded(4.0, 0.0, low_open=True)
    confidence: float = bounded(0.999, 0.0, 1.0, low_open=True)
    max_iterations: int = bounded(5000, 1)  # RANSAC cap per model; MAGSAC++ stops far earlier on clean pairs
    min_num_inliers: int = bounded(15, 0)  # COLMAP's two-view minimum
    min_inlier_ratio: float = bounded(0.25, 0.0, 1.0)  # inliers / putative matches
    min_E_F_inlier_ratio: float = bounded(0.95, 0.0, 1.0)  # E must explain this share of F's inliers for CALIBRATED
    max_H_inlier_ratio: float = bounded(0.8, 0.0)  # H inliers / E (or F) inliers above this: planar or panoramic
    panoramic_max_translation: float = bounded(0.01, 0.0)  # |t| / plane distance below this: rotation only (PANORAMIC)


@dataclass(kw_only=True)
class TwoViewResult:
    config: str  # a COLMAP two-view configuration name (mvrecon.database)
    inliers: np.ndarray  # (K,2) keypoint indices, a subset of the putative matches
    F: np.ndarray | None = None
    E: np.ndarray | None = None
    H: np.ndarray | None = None
    num_inliers: dict = field(default_factory=dict)  # per model: {"F": .., "E": .., "H": ..}


def f_iterations(num_matches: int, config: VerifyConfig) -> int:
    """F's RANSAC cap for a pair of `num_matches`: twice the iterations that find an all-inlier 7-point sample
    with `confidence` when the pair holds just the inliers it needs to pass (max(min_num_inliers,
    min_inlier_ratio x matches)); a pair with more inliers is found sooner, one with fewer fails whatever the
    search. Most pairs of an exhaustive run do not overlap and hold 15-30 chance matches, on which the full
    cap spent 2 ms each (templeSparseRing: 68 of its 120 pairs); 20 matches now get 100 iterations. The margin:
    with the textbook count itself (noisy all-inlier samples do not always give an F that keeps all of them
    within the threshold) the room scene lost 2 of its 262 verified pairs, both at exactly 15 inliers of 34-36
    matches; with twice that count all 13 test databases keep every pair, inliers included. At least 100
    iterations (0.05 ms) whatever the count."""
    w = max(config.min_num_inliers, config.min_inlier_ratio * num_matches) / max(num_matches, 1)
    need = np.log(1.0 - config.confidence) / np.log1p(-(w ** 7)) if w < 1.0 else 1.0
    return int(min(config.max_iterations, max(100, 2 * np.ceil(need))))


def _usac(kind: str, p1: np.ndarray, p2: np.ndarray, threshold: float, config: VerifyConfig, K=None):
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    method = cv2.USAC_MAGSAC
    try:
        if kind == "F":
            M, mask = cv2.findFundamentalMat(p1, p2, method, threshold, config.confidence,
                                             f_iterations(len(p1), config))
        elif kind == "H":
            M, mask = cv2.findHomography(p1, p2, method, threshold, maxIters=config.max_iterations,
                                         confidence=config.confidence)
        else:
            M, mask = cv2.findEssentialMat(p1, p2, K, method, config.confidence, threshold,
                                           config.max_iterations)
    except cv2.error:  # degenerate samples (all points collinear, duplicates) make OpenCV throw
        return None, np.zeros(len(p1), bool)
    if M is None or mask is None or M.shape[0] < 3:
        return None, np.zeros(len(p1), bool)
    return np.asarray(M[:3], dtype=float), mask.ravel().astype(bool)


def verify_pair(points1: np.ndarray, points2: np.ndarray, matches: np.ndarray, camera1: CameraInfo,
                camera2: CameraInfo, config: VerifyConfig = VerifyConfig()) -> TwoViewResult:
    """Classify one pair. `points*` are (N,2+) keypoints in COLMAP pixels, `matches` (M,2) putative indices."""
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    empty = TwoViewResult(config="DEGENERATE", inliers=np.zeros((0, 2), np.int64))
    if len(matches) < max(config.min_num_inliers, 8):
        return empty
    p1 = np.ascontiguousarray(points1[matches[:, 0], :2], dtype=np.float64)
    p2 = np.ascontiguousarray(points2[matches[:, 1], :2], dtype=np.float64)
    F, f_mask = _usac("F", p1, p2, config.max_error, config)
    if F is None or f_mask.sum() < config.min_num_inliers or f_mask.mean() < config.min_inlier_ratio:
        # F has the most freedom (a plane or a pure rotation fits an F too): where F fails, E and H fail as well,
        # and skipping them halves the cost of the many non-overlapping pairs of an exhaustive run.
        return TwoViewResult(config="DEGENERATE", inliers=empty.inliers, num_inliers={"F": int(f_mask.sum())})
    H, h_mask = _usac("H", p1, p2, config.max_error, config)
    E, e_mask = None, np.zeros(len(p1), bool)
    calibrated = camera1.prior_trusted and camera2.prior_trusted
    if calibrated:
        # Undistorted coordinates scaled back to pixels by a shared focal f: E is the same matrix as on
        # normalised coordinates, and the threshold stays in pixels (MAGSAC++ misjudges ~1e-3 thresholds).
        focal = 0.5 * (camera_model.focal_length(camera1.model, camera1.params)
                       + camera_model.focal_length(camera2.model, camera2.params))
        n1 = focal * camera_model.pixels_to_normalized(camera1.model, camera1.params, p1)
        n2 = focal * camera_model.pixels_to_normalized(camera2.model, camera2.params, p2)
        E, e_mask = _usac("E", n1, n2, config.max_error, config, np.diag([focal, focal, 1.0]))
    nF, nE, nH = int(f_mask.sum()), int(e_mask.sum()), int(h_mask.sum())
    counts = {"F": nF, "E": nE, "H": nH}
    m = config.min_num_inliers
    if calibrated and E is not None and nE >= m and nF > 0 and nE / nF > config.min_E_F_inlier_ratio:
        mask = e_mask if nE >= nF else f_mask
        kind = "PLANAR_OR_PANORAMIC" if nH / max(nE, 1) > config.max_H_inlier_ratio else "CALIBRATED"
    elif F is not None and nF >= m:
        mask = f_mask
        kind = "PLANAR_OR_PANORAMIC" if nH / max(nF, 1) > config.max_H_inlier_ratio else "UNCALIBRATED"
    elif H is not None and nH >= m:
        mask, kind = h_mask, "PLANAR_OR_PANORAMIC"
    else:
        return TwoViewResult(config="DEGENERATE", inliers=empty.inliers, num_inliers=counts)
    if kind == "PLANAR_OR_PANORAMIC" and nH > mask.sum():
        mask = h_mask
    if mask.sum() < m or mask.sum() / len(matches) < config.min_inlier_ratio:
        return TwoViewResult(config="DEGENERATE", inliers=empty.inliers, num_inliers=counts)
    if kind == "PLANAR_OR_PANORAMIC" and calibrated and H is not None:
        K1 = camera_model.calibration_matrix(camera1.model, camera1.params)
        K2 = camera_model.calibration_matrix(camera2.model, camera2.params)
        kind = "PANORAMIC" if homography_translation(H, K1, K2) < config.panoramic_max_translation else "PLANAR"
    return TwoViewResult(config=kind, inliers=matches[mask], F=F, E=E if calibrated else None, H=H,
                         num_inliers=counts)
