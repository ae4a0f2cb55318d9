"""Next-best-view selection and image registration by robust absolute pose.

The next image is the one whose keypoints see the most triangulated points, spread over the image: COLMAP's
visibility score counts occupied cells of a multi-resolution grid (2x2 up to 64x64), finer levels weighing
more, so 200 points spread over the frame beat 400 in one corner. Registration runs P3P in RANSAC on the
2D-3D matches; when the focal length is only a guess and no registered image shares the camera, a few focal
hypotheses are scored and the best pose is refined together with the focal length.
"""

from dataclasses import dataclass

import numpy as np

from ..geometry.absolute_pose import pnp_ransac, refine_pose_and_focal, reprojection_errors
from .config import MapperConfig

_PYRAMID_LEVELS = 6
_FOCAL_HYPOTHESES = (1.0, 0.7, 1.4, 0.5, 2.0)


def visibility_score(xy, width: int, height: int, levels: int = _PYRAMID_LEVELS) -> int:
    """Sum over levels l = 1..levels of (occupied cells of a 2^l grid) * 2^l."""
    if len(xy) == 0:
        return 0
    score = 0
    for level in range(1, levels + 1):
        n = 2 ** level
        cx = np.clip((xy[:, 0] / width * n).astype(int), 0, n - 1)
        cy = np.clip((xy[:, 1] / height * n).astype(int), 0, n - 1)
        score += len(np.unique(cy * n + cx)) * n
    return int(score)


def correspondences_2d3d(model, tracks, image: int):
    """(keypoint indices, point ids) of image's keypoints whose track already has a 3D point."""
    t = tracks.track_of[image]
    kps = np.flatnonzero(t >= 0)
    pids = model.point_of_track[t[kps]]
    keep = pids >= 0
    return kps[keep], pids[keep]


def rank_candidates(model, tracks, images) -> list[tuple[int, int, int]]:
    """(score, number of 2D-3D matches, image) for the given unregistered images, best first."""
    out = []
    for i in images:
        kps, _ = correspondences_2d3d(model, tracks, i)
        cam = model.camera(i)
        out.append((visibility_score(model.keypoints[i][kps], cam.width, cam.height), len(kps), int(i)))
    return sorted(out, key=lambda s: (-s[0], s[2]))


@dataclass
class Registration:
    ok: bool
    reason: str | None
    inliers: int = 0
    matches: int = 0


def register_image(model, tracks, image: int, config: MapperConfig, seed: int = 0) -> Registration:
    """Estimate image's pose from its 2D-3D matches and register it (observations are added by the caller)."""
    kps, pids = correspondences_2d3d(model, tracks, image)
    has_ray = np.isfinite(model.normalized_keypoints(image)[kps]).all(axis=1)
    kps, pids = kps[has_ray], pids[has_ray]
    if len(kps) < config.abs_pose_min_inliers:
        return Registration(False, f"too few 2D-3D matches ({len(kps)} < {config.abs_pose_min_inliers})",
                            0, len(kps))
    cam = model.camera(image)
    K = cam.K()
    X = model.xyz.data[pids]
    xn = model.normalized_keypoints(image)[kps]
    uv = xn * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]  # ideal (undistorted) pixels
    shared = np.any(model.registered & (model.camera_of == model.camera_of[image]))
    estimate_focal = not cam.prior_trusted and not shared
    best = None
    for scale in (_FOCAL_HYPOTHESES if estimate_focal else (1.0,)):
        Kh = K.copy()
        Kh[0, 0] *= scale
        Kh[1, 1] *= scale
        uvh = (uv - K[:2, 2]) * scale + K[:2, 2]  # same rays re-expressed with the hypothesised focal
        est = pnp_ransac(X, uvh, Kh, config.abs_pose_max_error_px, seed=seed)
        if est is not None and (best is None or est[2].sum() > best[3].sum()):
            best = (scale, est[0], est[1], est[2])
    if best is None:
        return Registration(False, "absolute pose (P3P RANSAC) found no solution", 0, len(kps))
    scale, R, t, inl = best
    if estimate_focal:
        Kh = K.copy()
        Kh[:2, :2] *= scale
        uvh = (uv - K[:2, 2]) * scale + K[:2, 2]
        R, t, f = refine_pose_and_focal(X[inl], uvh[inl], Kh, R, t)
        cam.set_focal(cam.focal() * f / Kh[0, 0])
        K = cam.K()
        uv = model.normalized_keypoints(image)[kps] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        inl = reprojection_errors(X, uv, K, R, t) < config.abs_pose_max_error_px
    n_inl = int(inl.sum())
    if n_inl < config.abs_pose_min_inliers or n_inl < config.abs_pose_min_inlier_ratio * len(kps):
        return Registration(False, f"absolute pose has too few inliers ({n_inl} of {len(kps)} 2D-3D matches)",
                            n_inl, len(kps))
    model.register(image, R, t)
    return Registration(True, None, n_inl, len(kps))

