"""Six keypoint detectors behind one interface, and the measures of the seed paper's Table 1 and beyond.

`detect(name, image)` returns a `Detection` (keypoints (N,4): x, y, scale, angle in radians with pixel centres at
integers; descriptors or None; seconds). SIFT is the front end's (`features.sift`), SURF ours when OpenCV lacks it
(`features.surf`), FAST/ORB/AKAZE/BRISK are OpenCV's with their default settings; FAST has no descriptor of its own
and is described with ORB's (rotated BRIEF) at its corners so that it can be matched too.

Repeatability (Mikolajczyk & Schmid): warp the image by a known homography, detect in both, and count the
keypoints of the region both images see that reappear within `eps` px (the smaller of the two directions' counts),
divided by the smaller keypoint count of that region. Dense detectors (thousands of corners) get some help from
chance neighbours at 2.5 px; compare detectors with similar counts, or lower eps.

`measure` gives one image's figures for one detector as a JSON-able dict, which the `detectors` command keeps (as
it keeps each pair's `verified_inliers`) for a rerun; `CODE` names the modules these figures are computed by, so
that a rerun after an edit of one of them computes them again.
"""

import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..geometry.fundamental import RansacConfig, ransac_fundamental
from ..io.images import to_gray
from ..matching.matcher import MatcherConfig, match_descriptors
from .sift import SiftConfig, extract_sift
from .surf import SurfConfig, extract_surf

DETECTORS = ("SIFT", "SURF", "FAST", "ORB", "AKAZE", "BRISK")
BINARY = {"FAST", "ORB", "BRISK", "AKAZE"}  # Hamming-distance descriptors
CODE = ("mvrecon.features.detectors", "mvrecon.features.sift", "mvrecon.features.surf", "mvrecon.io.images",
        "mvrecon.matching.matcher", "mvrecon.matching.int_product", "mvrecon.geometry.fundamental")


@dataclass(frozen=True)
class Detection:
    keypoints: np.ndarray
    descriptors: np.ndarray | None
    seconds: float
    implementation: str


def _gray(image) -> np.ndarray:
    return to_gray(image)


def _from_cv(kps) -> np.ndarray:
    return np.array([(k.pt[0], k.pt[1], k.size / 2.0, np.radians(k.angle)) for k in kps],
                    dtype=np.float64).reshape(-1, 4)


def _opencv_factory(name: str):
    """OpenCV 5 moved AKAZE and BRISK to the contrib module `xfeatures2d`; OpenCV 4 has them in `cv2`."""
    return getattr(cv2, name, None) or getattr(cv2.xfeatures2d, name)


def detect(name: str, image: np.ndarray, max_features: int = 8192) -> Detection:
    """Keypoints and descriptors of one detector on an 8-bit (or any `read_image`) image."""
    name = name.upper()
    gray = _gray(image)
    t0 = time.perf_counter()
    if name == "SIFT":
        kps, desc = extract_sift(gray, SiftConfig(max_num_features=max_features))
        kps = np.asarray(kps, dtype=np.float64).copy()
        kps[:, :2] -= 0.5  # COLMAP's pixel convention back to array indices
        impl = "opencv (front end)"
    elif name == "SURF":
        kps, desc, impl = extract_surf(gray, SurfConfig(max_features=max_features))
    elif name in ("FAST", "ORB", "AKAZE", "BRISK"):
        detector = {"FAST": lambda: cv2.FastFeatureDetector_create(),
                    "ORB": lambda: cv2.ORB_create(nfeatures=max_features),
                    "AKAZE": lambda: _opencv_factory("AKAZE_create")(),
                    "BRISK": lambda: _opencv_factory("BRISK_create")()}[name]()
        if name == "FAST":
            cv_kps = detector.detect(gray, None)
            cv_kps = sorted(cv_kps, key=lambda k: -k.response)[:max_features]
            for k in cv_kps:
                k.size = 31.0  # ORB's patch size, so the descriptor has room; FAST itself has no scale
            cv_kps, desc = cv2.ORB_create(edgeThreshold=31).compute(gray, cv_kps)
        else:
            cv_kps, desc = detector.detectAndCompute(gray, None)
            cv_kps, desc = cv_kps[:max_features], (desc[:max_features] if desc is not None else None)
        kps, impl = _from_cv(cv_kps), "opencv"
    else:
        raise ValueError(f"unknown detector {name!r}; expected one of {', '.join(DETECTORS)}")
    return Detection(np.asarray(kps, dtype=np.float64).reshape(-1, 4), desc, time.perf_counter() - t0, impl)


def _apply_h(H, pts) -> np.ndarray:
    p = np.column_stack([pts[:, :2], np.ones(len(pts))]) @ np.asarray(H).T
    return p[:, :2] / p[:, 2:3]


def _visible(pts, shape, border: float) -> np.ndarray:
    h, w = shape[:2]
    return (pts[:, 0] >= border) & (pts[:, 0] < w - border) & (pts[:, 1] >= border) & (pts[:, 1] < h - border)


def repeatability(kps1: np.ndarray, kps2: np.ndarray, H: np.ndarray, shape1: tuple[int, ...],
                  shape2: tuple[int, ...], eps: float = 2.5, border: float = 10.0) -> float:
    """Share of keypoints seen by both images that reappear within eps px under x2 = H x1 (0..1)."""
    kps1, kps2 = np.asarray(kps1)[:, :2], np.asarray(kps2)[:, :2]
    Hinv = np.linalg.inv(H)
    in1 = _visible(kps1, shape1, border) & _visible(_apply_h(H, kps1), shape2, border)
    in2 = _visible(kps2, shape2, border) & _visible(_apply_h(Hinv, kps2), shape1, border)
    n = min(in1.sum(), in2.sum())
    if n == 0:
        return 0.0
    p1 = _apply_h(H, kps1[in1])
    p2 = kps2[in2]
    d12, _ = cKDTree(p2).query(p1, distance_upper_bound=eps)
    d21, _ = cKDTree(p1).query(p2, distance_upper_bound=eps)
    # a correspondence needs a partner in both directions; counting the smaller side keeps many-to-one
    # neighbours of dense detectors from inflating the figure
    return float(min(np.isfinite(d12).sum(), np.isfinite(d21).sum()) / n)


def match(det1: Detection, det2: Detection, name: str, ratio: float = 0.8) -> np.ndarray:
    """(M,2) index pairs: mutual nearest neighbours passing the ratio test (Hamming for binary descriptors)."""
    if det1.descriptors is None or det2.descriptors is None or len(det1.descriptors) < 2 or len(
            det2.descriptors) < 2:
        return np.zeros((0, 2), int)
    if name.upper() == "SIFT":
        return np.asarray(match_descriptors(det1.descriptors, det2.descriptors, MatcherConfig(max_ratio=ratio)),
                          dtype=int).reshape(-1, 2)
    norm = cv2.NORM_HAMMING if name.upper() in BINARY else cv2.NORM_L2
    d1 = np.ascontiguousarray(det1.descriptors)
    d2 = np.ascontiguousarray(det2.descriptors)
    if norm == cv2.NORM_L2:
        d1, d2 = d1.astype(np.float32), d2.astype(np.float32)
    matcher = cv2.BFMatcher(norm)
    back = {m.queryIdx: m.trainIdx for m in matcher.match(d2, d1)}
    pairs = [(m.queryIdx, m.trainIdx) for knn in matcher.knnMatch(d1, d2, k=2) if len(knn) == 2
             for m, n in [knn] if m.distance < ratio * n.distance and back.get(m.trainIdx) == m.queryIdx]
    return np.array(pairs, dtype=int).reshape(-1, 2)


def verified_inliers(det1: Detection, det2: Detection, name: str, threshold: float = 1.0) -> int:
    """Matches consistent with one fundamental matrix (our eight-point RANSAC); 0 below 8 matches."""
    pairs = match(det1, det2, name)
    if len(pairs) < 8:
        return 0
    try:
        _, inliers = ransac_fundamental(det1.keypoints[pairs[:, 0], :2], det2.keypoints[pairs[:, 1], :2],
                                        RansacConfig(threshold=threshold))
    except ValueError:
        return 0
    return int(inliers.sum())


def synthetic_homography(shape: tuple[int, ...], angle_deg: float = 20.0, scale: float = 0.8) -> np.ndarray:
    """Rotation about the image centre with a zoom: the known warp used for repeatability."""
    h, w = shape[:2]
    return np.vstack([cv2.getRotationMatrix2D((w / 2, h / 2), angle_deg, scale), [0, 0, 1]])


def warp_repeatability(name: str, image: np.ndarray, H: np.ndarray, eps: float = 2.5,
                       keypoints: np.ndarray | None = None) -> float:
    """Repeatability of a detector between an image and its warp by H; `keypoints`: the image's own, when they
    were detected already (the detection is then not run twice)."""
    gray = _gray(image)
    warped = cv2.warpPerspective(gray, H, (gray.shape[1], gray.shape[0]))
    k1 = detect(name, gray).keypoints if keypoints is None else keypoints
    k2 = detect(name, warped).keypoints
    return repeatability(k1, k2, H, gray.shape, warped.shape, eps)


def measure(name: str, image: np.ndarray, H: np.ndarray) -> tuple[Detection, dict]:
    """One detector on one image: its Detection (for the pairs) and the table's figures: keypoints, detect_s (the
    time of the detection alone), repeatability under the warp H (0..1) and implementation."""
    det = detect(name, image)
    return det, {"keypoints": len(det.keypoints), "detect_s": det.seconds,
                 "repeatability": warp_repeatability(name, image, H, keypoints=det.keypoints),
                 "implementation": det.implementation}
