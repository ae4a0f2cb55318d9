"""Epipolar rectification: homographies that make epipolar lines horizontal and aligned between two images.

Uncalibrated (Hartley 1999, "Theory and practice of projective rectification"): from F alone. The right image is
sent to a frame where its epipole lies at infinity on the x axis (translate, rotate, projective G); the left
homography is the matched transform H2 M, M = [e2]_x F + e2 v^T, followed by the x-affine map that minimises the
horizontal distance of the matches (rows are aligned by construction, so only x is free).

Calibrated: from intrinsics and the relative pose, rotate both cameras to a common orientation whose x axis is the
baseline (Fusiello et al. 2000) and give them one intrinsic matrix; this is what a stereo calibration makes possible.
"""

from dataclasses import dataclass

import numpy as np

from .fundamental import epipoles


def _skew(v) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,2) pixels mapped through a 3x3 homography."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    h = np.hstack([p, np.ones((len(p), 1))]) @ np.asarray(H).T
    return h[:, :2] / h[:, 2:3]


def _epipole_to_infinity(e, width: float, height: float) -> np.ndarray:
    """H2 = G R T: image centre to the origin, epipole rotated onto the nearer half of the x axis, then sent to
    infinity by G = [[1,0,0],[0,1,0],[-w/f,0,1]]. The nearer half keeps the image upright (no 180 deg turn)."""
    T = np.array([[1.0, 0, -width / 2], [0, 1, -height / 2], [0, 0, 1]])
    et = T @ e
    angle = np.arctan2(et[1], et[0])
    if et[0] < 0:  # rotate onto the negative x axis instead of turning the image upside down
        angle -= np.pi if angle > 0 else -np.pi
    c, s = np.cos(-angle), np.sin(-angle)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    er = R @ et
    G = np.eye(3)
    if abs(er[0]) > 1e-12:
        G[2, 0] = -er[2] / er[0]
    return G @ R @ T


def hartley_rectification(F: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                          size2: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Rectifying homographies (H1, H2) for the left and right images from F (x2^T F x1 = 0) and its inlier
    matches x1, x2 (N,2). size2 = (width, height) of the right image. After warping, matches share a row.
    """
    x1, x2 = np.asarray(x1, dtype=float), np.asarray(x2, dtype=float)
    _, e2 = epipoles(F)
    H2 = _epipole_to_infinity(e2, *size2)
    M = None
    for v in (np.ones(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])):
        candidate = _skew(e2) @ F + np.outer(e2, v)
        if abs(np.linalg.det(candidate)) > 1e-9 * np.linalg.norm(candidate) ** 3:
            M = candidate
            break
    if M is None:
        raise ValueError("degenerate fundamental matrix: cannot build the matched rectifying homography")
    H0 = H2 @ M
    p1 = apply_homography(H0, x1)
    p2 = apply_homography(H2, x2)
    A = np.column_stack([p1[:, 0], p1[:, 1], np.ones(len(p1))])
    abc, *_ = np.linalg.lstsq(A, p2[:, 0], rcond=None)
    HA = np.array([[abc[0], abc[1], abc[2]], [0, 1, 0], [0, 0, 1.0]])
    return HA @ H0, H2


@dataclass(frozen=True)
class RectifiedFrame:
    """Homographies into a common canvas of width x height pixels (d = x_left - x_right stays positive)."""

    H1: np.ndarray
    H2: np.ndarray
    width: int
    height: int


def fit_to_canvas(H1: np.ndarray, H2: np.ndarray, size1: tuple[int, int], x1: np.ndarray, x2: np.ndarray,
                  margin: int = 8) -> RectifiedFrame:
    """Scale and shift rectifying homographies so the left image fills a canvas of about its original size.

    Both images get the same vertical map (rows must stay aligned) and the same scale; the right image is shifted
    horizontally so the 1st percentile of the match disparities becomes `margin` px, which keeps disparities
    positive (the shift plays the role of Middlebury's doffs).
    """
    w, h = size1
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=float)
    c1 = apply_homography(H1, corners)
    span = c1.max(axis=0) - c1.min(axis=0)
    s = float(np.sqrt(w * h / max(span[0] * span[1], 1e-9)))
    S = np.array([[s, 0, -s * c1[:, 0].min()], [0, s, -s * c1[:, 1].min()], [0, 0, 1.0]])
    H1n, H2n = S @ H1, S @ H2
    d = apply_homography(H1n, x1)[:, 0] - apply_homography(H2n, x2)[:, 0]
    shift = (np.percentile(d, 1) if len(d) else 0.0) - margin
    H2n = np.array([[1, 0, shift], [0, 1, 0], [0, 0, 1.0]]) @ H2n
    return RectifiedFrame(H1n, H2n, int(np.ceil(s * span[0])), int(np.ceil(s * span[1])))


@dataclass(frozen=True)
class CalibratedRectification:
    """Rotations taking each camera frame to the rectified frame, the shared intrinsics, and the baseline.

    Rectified pixels: x = K_new R_i X_cam_i. Depth Z = f * baseline / (d + doffs) with doffs = cx_right - cx_left.
    """

    R1: np.ndarray
    R2: np.ndarray
    K1: np.ndarray
    K2: np.ndarray
    baseline: float


def calibrated_rectification(K1: np.ndarray, K2: np.ndarray, R: np.ndarray,
                             t: np.ndarray) -> CalibratedRectification:
    """Fusiello-style rectification for cameras with x_cam2 = R x_cam1 + t (OpenCV stereoCalibrate's R, T).

    The new x axis is the baseline (camera 1 -> camera 2), y is orthogonal to it and to camera 1's optical axis;
    both cameras share fy and cy so rows align, and keep their own cx (recorded as doffs).
    """
    K1, K2, R, t = (np.asarray(a, dtype=float) for a in (K1, K2, R, t))
    c2 = -R.T @ t.ravel()  # centre of camera 2 in camera 1's frame
    x = c2 / np.linalg.norm(c2)
    y = np.cross(np.array([0.0, 0.0, 1.0]), x)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    Rrect = np.vstack([x, y, z])
    f = float((K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1]) / 4)
    cy = float((K1[1, 2] + K2[1, 2]) / 2)
    Kn1 = np.array([[f, 0, K1[0, 2]], [0, f, cy], [0, 0, 1.0]])
    Kn2 = np.array([[f, 0, K2[0, 2]], [0, f, cy], [0, 0, 1.0]])
    return CalibratedRectification(Rrect, Rrect @ R.T, Kn1, Kn2, float(np.linalg.norm(c2)))
