"""Next-best-view selection and image registration by robust absolute pose.

The next image is the one whose keypoints see the most triangulated points, spread over the image: COLMAP's
visibility score counts occupied cells of a multi-resolution grid (2x2 up to 64x64), finer levels weighing
more, so 200 points spread over the frame beat 400 in one corner. Registration runs P3P in RANSAC on the
2D-3D matches; when the focal length is only a guess and no registered image shares the camera, a few focal
hypotheses are scored and the best pose is refined together with the focal length.

Repeated structure can make a second pose fit nearly as many matches as the best one: a wide lens looking at a
tiled ground matches the ground of views across the scene one tile off, and the pose with the most inliers is then
a choice, not a measurement. So when a rival pose (found by RANSAC on the best pose's outliers) fits a fifth as
many matches, the pose the image's best-connected registered views support wins: an inlier counts the tracks the
image shares with the registered views observing its point, over the most it shares with any image (a true
neighbour shares several times the tracks of a view that only sees the same texture). When no registered view
shares three quarters of that most, the views that could decide are not registered yet, and the image waits: the
mapper registers the others first, and registers a waiting image with its best-supported pose only once nothing
else can be registered (`IncrementalMapper._grow`), so waiting reorders registration but never keeps an image
out of the model. Measured on the shared sets, the catalog and degraded temples (docs/benchmarks.md, "Mapper
rules"): essential on the 184 deg fisheye orbit (AUC@5 0.99, 0.51 without), within +-0.02 AUC@1 elsewhere.
"""

import logging
from collections.abc import Collection, Iterable
from dataclasses import dataclass

import numpy as np

from ..geometry.absolute_pose import pnp_ransac, refine_pose_and_focal, reprojection_errors, rival_poses
from .config import MapperConfig
from .model import Reconstruction
from .tracks import Tracks

log = logging.getLogger("mvrecon.sfm")
_PYRAMID_LEVELS = 6
_FOCAL_HYPOTHESES = (1.0, 0.7, 1.4, 0.5, 2.0)
_RIVAL_SHARE = 0.2  # a second pose fitting this share of the best pose's inliers makes the pose ambiguous
_WEAK_LINK = 0.75  # below this share of the image's strongest link, its registered views cannot decide


def visibility_score(xy: np.ndarray, width: int, height: int, levels: int = _PYRAMID_LEVELS) -> int:
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


def correspondences_2d3d(model: Reconstruction, tracks: Tracks, image: int) -> tuple[np.ndarray, np.ndarray]:
    """(keypoint indices, point ids) of image's keypoints whose track already has a 3D point."""
    t = tracks.track_of[image]
    kps = np.flatnonzero(t >= 0)
    pids = model.point_of_track[t[kps]]
    keep = pids >= 0
    return kps[keep], pids[keep]


def rank_candidates(model: Reconstruction, tracks: Tracks,
                    images: Iterable[int]) -> list[tuple[int, int, int]]:
    """(score, number of 2D-3D matches, image) for the given unregistered images, best first."""
    return sorted((_candidate_score(model, tracks, i) for i in images), key=lambda s: (-s[0], s[2]))


def _candidate_score(model, tracks, i: int) -> tuple[int, int, int]:
    kps, _ = correspondences_2d3d(model, tracks, i)
    cam = model.camera(i)
    model.scanned += len(tracks.track_of[i])
    return visibility_score(model.keypoints[i][kps], cam.width, cam.height), len(kps), int(i)


class CandidateRanking:
    """`rank_candidates` of a growing model, each image's score kept until a track of the image gains or loses its
    point (`Reconstruction.changed_tracks`): a registration changes the points of its neighbours' tracks only, so
    re-scoring every unregistered image after each one cost in proportion to the images left (0.1 s a
    registration at 300 images), for the same ranking."""

    def __init__(self, tracks: Tracks):
        self.tracks, self.model, self.scores = tracks, None, {}

    def rank(self, model: Reconstruction, images: Collection[int]) -> list[tuple[int, int, int]]:
        if model is not self.model:
            self.model, self.scores = model, {}
            model.changed_tracks.clear()
        elif model.changed_tracks:
            for i in self._images_of(np.concatenate(model.changed_tracks)).tolist():
                self.scores.pop(i, None)
            model.changed_tracks.clear()
        for i in images:
            if i not in self.scores:
                self.scores[i] = _candidate_score(model, self.tracks, i)
        return sorted((self.scores[i] for i in images), key=lambda s: (-s[0], s[2]))

    def _images_of(self, track_ids) -> np.ndarray:
        t = np.unique(track_ids)
        ptr = self.tracks.ptr
        lengths = ptr[t + 1] - ptr[t]
        first = np.repeat(ptr[t] - np.cumsum(lengths) + lengths, lengths)
        self.model.scanned += int(lengths.sum())
        return np.unique(self.tracks.image[first + np.arange(int(lengths.sum()))])


@dataclass
class Registration:
    ok: bool
    reason: str | None
    inliers: int = 0
    matches: int = 0
    wait: bool = False  # not a failure of the image: its pose waits for its neighbours (`choose_pose`)


def register_image(model: Reconstruction, tracks: Tracks, image: int, config: MapperConfig, seed: int = 0,
                   decide: bool = False) -> Registration:
    """Estimate image's pose from its 2D-3D matches and register it (observations are added by the caller).

    An image whose pose is ambiguous and whose best-connected views are not registered yet is not registered
    but told to wait (`Registration.wait`); with `decide` it is registered with the pose its registered views
    support most (`choose_pose`), which the mapper asks for once no other image can be registered."""
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
        Kh, uvh = _at_focal_scale(K, uv, scale)
        est = pnp_ransac(X, uvh, Kh, config.abs_pose_max_error_px, seed=seed)
        if est is not None and (best is None or est[2].sum() > best[4].sum()):
            best = (Kh, uvh, *est)
    if best is None:
        return Registration(False, "absolute pose (P3P RANSAC) found no solution", 0, len(kps))
    Kh, uvh, R, t, inl = best
    rivals = rival_poses(X, uvh, Kh, inl, config.abs_pose_max_error_px,
                         max(config.abs_pose_min_inliers, _RIVAL_SHARE * inl.sum()), seed=seed)
    if rivals:
        (R, t, inl), undecided = choose_pose(model, tracks, image, pids, [(R, t, inl), *rivals])
        if undecided and not decide:
            return Registration(False, undecided, int(inl.sum()), len(kps), wait=True)
    if estimate_focal:
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


def _at_focal_scale(K, uv, scale: float):
    """K and the ideal pixels `uv` re-expressed with the focal length times `scale` (the same rays)."""
    Kh = K.copy()
    Kh[0, 0] *= scale
    Kh[1, 1] *= scale
    return Kh, (uv - K[:2, 2]) * scale + K[:2, 2]


def track_links(tracks: Tracks, image: int) -> np.ndarray:
    """Per image, the tracks it shares with `image` (0 for `image` itself): how strongly two views are tied,
    about the inliers of their verified pair plus the matches that reach it through third views."""
    t = tracks.track_of[image]
    elements, _ = tracks.elements_of_tracks(t[t >= 0])
    links = np.bincount(tracks.image[elements], minlength=len(tracks.track_of))
    links[image] = 0
    return links


def choose_pose(model: Reconstruction, tracks: Tracks, image: int, pids: np.ndarray,
                poses: list[tuple[np.ndarray, ...]]) -> tuple[tuple[np.ndarray, ...], str | None]:
    """Of `poses` ((R, t, inlier mask over the 2D-3D matches of points `pids`), the best RANSAC pose first),
    the one the image's registered views support most, and None, or with the reason to wait (a str) when
    none of its best-connected views is registered yet, so that they cannot vouch for either pose.

    An inlier weighs the most tracks the image shares with a registered view observing its point, over the
    most it shares with any image; ties keep the first pose."""
    links = track_links(tracks, image).astype(float)
    others = model.registered.copy()
    others[image] = False
    strongest = int(np.argmax(links))
    if links[strongest] <= 0 or not others.any():  # nothing to weigh by (matches come through tracks: never)
        return poses[0], None
    undecided = None
    if links[others].max() < _WEAK_LINK * links[strongest]:
        counts = " and ".join(str(int(inl.sum())) for _, _, inl in poses)
        undecided = (f"ambiguous pose: {len(poses)} poses fit {counts} of its {len(pids)} 2D-3D matches "
                     f"(repeated structure?), and no registered image shares {_WEAK_LINK:.0%} as many tracks "
                     f"with it as {model.names[strongest]} does")
    obs = model.observations_of_points(np.unique(pids))
    point_link = np.zeros(model.xyz.n)
    np.maximum.at(point_link, model.obs_point.data[obs], links[model.obs_image.data[obs]])
    weight = point_link[pids] / links[strongest]
    support = [float(weight[inl].sum()) for _, _, inl in poses]
    pick = int(np.argmax(support))
    if pick:
        log.debug("%s: a rival pose wins (inliers %s, supported %s)", model.names[image],
                  [int(inl.sum()) for _, _, inl in poses], [round(v) for v in support])
    return poses[pick], undecided
