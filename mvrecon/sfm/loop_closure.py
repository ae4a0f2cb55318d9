"""Closing a loop that growth left open: the hinge where its two ends meet, and a similarity pose graph.

A model grown round a long loop drifts, in rotation, position and scale (a street sequence round a block). The
mapper grows from its initial pair both ways, and where the two ends meet each end's images see the other end's
points metres away, past the 4 px gate and the loose angular one of the loop-closing continuation
(`triangulate.continue_points`). So the loop stays open at one hinge that holds all the drift, and a bundle
adjustment cannot close it: nothing ties the two ends.

An image at a hinge is found by the points of its own tracks that it does not observe: where one pose (P3P RANSAC)
fits `loop_min_inliers` of them and half, and its own pose does not, the image sees the other end of the loop
(`find_hinges`). The gap is then spread over the loop as SLAM systems close loops (`close_loop`): a pose graph of
one similarity per image, with an edge between images that share points holding their relative pose and scale,
its sigmas going as the inverse square of the points they share (the gap goes where the model is held least), and one
edge per hinge image to the other end's image that sees most of its points, holding the pose found there (its
scale left free: nothing measured it). Each point moves with an image that observes it. The caller then lets the
hinge's views join their points and settles the model (`close_open_loop`); a closure after which the model holds
no more views than before is undone.

The global mapper's model can hold an open loop too: its cameras are placed in turn from the first pair both ways
round a loop, and where the two ends meet their steps have drifted apart in scale (a 1 km street loop: 0.89x the
true steps on one side, 1.18x on the other, 86 m between two neighbouring frames, 90 camera spacings). Its
rotations do not drift: rotation averaging solved them over the whole view graph at once. So there the loop is
closed only at such a gap (`min_gap`), the pose graph holds every image's rotation (`hold_rotations`) and spreads
the gap over the centres and scales alone (left free, the rotations took it up at the corners: streets turned 4-6
deg, 201 of the 1,000 frames misplaced).
"""

import logging
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from ..geometry.absolute_pose import pnp_ransac
from .config import MapperConfig
from .model import Reconstruction
from .tracks import Tracks
from .triangulate import unobserved_views

log = logging.getLogger("mvrecon.sfm")

_NEIGHBOURS = 6  # covisibility edges kept per image: its most shared partners
_LEAST_SHARED = 15  # points two images must share for an edge
_LONGEST_TRACK = 20  # points seen by more images are left out of the covisibility count (quadratic in length)
_SIGMA_ROTATION = 0.01  # rad, for an edge of _REFERENCE_SHARED points; sigmas go as 1 / shared points ** 2
_HELD_SIGMA_ROTATION = 1e-4  # rad, the same with `hold_rotations`
_SIGMA_TRANSLATION = 0.01  # of the median edge length
_SIGMA_SCALE = 0.01
_REFERENCE_SHARED = 100
_LOOSE_PRIOR = 1e4  # every image's prior on its pose: this many times an edge's sigmas
_PNP_ITERATIONS = 1000  # a hinge's points fit its other pose by half or more: few samples find it


@dataclass
class Hinge:
    """An image that sees the other end of an open loop: `R`, `t` its pose (camera from world) among that end's
    `points`, which its own pose does not fit."""
    image: int
    R: np.ndarray
    t: np.ndarray
    points: np.ndarray


def find_hinges(model: Reconstruction, tracks: Tracks, config: MapperConfig, seed: int = 0) -> list[Hinge]:
    """The registered images with loop_min_inliers or more points of their tracks unobserved, one pose fitting
    half of them or more within max_reproj_error_px while their own pose leaves those beyond it (median)."""
    least = config.loop_min_inliers
    if least <= 0:
        return []
    _, img, kp, pts = unobserved_views(model, tracks)
    order = np.argsort(img, kind="stable")
    img, kp, pts = img[order], kp[order], pts[order]
    images, start, count = np.unique(img, return_index=True, return_counts=True)
    hinges = []
    for i, a, n in zip(images.tolist(), start.tolist(), count.tolist()):
        if n < least:
            continue
        sel = slice(a, a + n)
        X = model.xyz.data[pts[sel]]
        K = model.camera(i).K()
        uv = model.normalized_at(img[sel], kp[sel]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        est = pnp_ransac(X, uv, K, config.max_reproj_error_px, seed=seed, max_iterations=_PNP_ITERATIONS)
        if est is None or est[2].sum() < max(least, 0.5 * n):
            continue
        R, t, inl = est
        views = img[sel][inl]
        now, depth = model.project(views, X[inl])
        err = np.linalg.norm(now - model.keypoints_at(views, kp[sel][inl]), axis=1)
        err[~np.isfinite(err) | (depth <= 0)] = np.inf
        if np.median(err) > config.max_reproj_error_px:
            hinges.append(Hinge(i, R, np.asarray(t, float).ravel(), pts[sel][inl]))
    return hinges


def close_open_loop(model: Reconstruction, tracks: Tracks, config: MapperConfig, settle: Callable[[], None],
                    hold_rotations: bool = False, min_gap: float = 0.0, settled_baseline: bool = False,
                    tolerance: float = 0.0) -> list[Hinge]:
    """Find the hinges of an open loop and, where one of them has its other pose `min_gap` camera spacings or more
    from its own (`gaps`), close the loop at all of them (`close_loop`), then `settle` the model (the caller lets
    the hinges' views join their points and adjusts or filters it); undone when the model then holds no more views
    than before, as a closure that bent the model would leave it (a wrong "other end" from repeated structure).
    With `settled_baseline`, "before" is the model settled without the closure (a settling that adds views of its
    own, such as triangulating the tracks again, would otherwise credit the closure with them). The closure is kept
    when the model holds more than (1 - `tolerance`) of those views. Returns the hinges of a closure kept, else []."""
    hinges = find_hinges(model, tracks, config, config.seed)
    if not hinges or (min_gap > 0 and gaps(model, hinges).max() < min_gap):
        return []
    before = model.state()
    if settled_baseline:
        settle()
    views = int(model.obs_alive.data.sum())
    if settled_baseline:
        model.restore(before)
    close_loop(model, hinges, hold_rotations)
    settle()
    after = int(model.obs_alive.data.sum())
    names = ", ".join(model.names[h.image] for h in hinges[:3]) + (", ..." if len(hinges) > 3 else "")
    if after <= (1.0 - tolerance) * views:
        model.restore(before)
        log.info("an open loop at %d images (%s) left as it was: closed, the model held %d views, not more than "
                 "%.0f", len(hinges), names, after, (1.0 - tolerance) * views)
        return []
    log.info("closed an open loop at %d images (%s): %d views in all (%d %s)", len(hinges), names, after, views,
             "without the closure" if settled_baseline else "before")
    return hinges


def gaps(model: Reconstruction, hinges: list[Hinge]) -> np.ndarray:
    """How far each hinge's other pose lies from its own: the distance between the two centres over the median
    distance from a registered camera to its nearest neighbour."""
    centers = model.centers()
    placed = centers[model.registered_images()]
    if len(placed) < 2 or not hinges:
        return np.zeros(len(hinges))
    spacing = max(float(np.median(cKDTree(placed).query(placed, k=2)[0][:, 1])), 1e-12)
    return np.array([np.linalg.norm(-h.R.T @ h.t - centers[h.image]) / spacing for h in hinges])


def close_loop(model: Reconstruction, hinges: list[Hinge], hold_rotations: bool = False) -> None:
    """Move every registered image and point by the similarity pose graph's solution (module docstring); with
    `hold_rotations` every image keeps its rotation (within `_HELD_SIGMA_ROTATION` an edge)."""
    sigma_rotation = _HELD_SIGMA_ROTATION if hold_rotations else _SIGMA_ROTATION
    images = model.registered_images()
    a, b, shared = covisibility(model)
    node = {int(i): k for k, i in enumerate(images)}
    centers = model.centers()
    old = [_similarity(model.R[i], centers[i]) for i in images.tolist()]
    lengths = np.linalg.norm(centers[a] - centers[b], axis=1)
    unit = float(np.median(lengths)) if len(lengths) else 1.0
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    loose = _noise(_REFERENCE_SHARED, unit, sigma_rotation, _SIGMA_SCALE, _LOOSE_PRIOR)
    for k, s in enumerate(old):
        values.insert(k, s)
        # a prior far looser than any edge, so that an image without edges stays where it is
        graph.add(gtsam.PriorFactorSimilarity3(k, s, loose))
    anchor = node[model.registration_order[0]]  # the gauge: the first registered image stays
    graph.add(gtsam.PriorFactorSimilarity3(anchor, old[anchor], gtsam.noiseModel.Isotropic.Sigma(7, 1e-6)))
    for i, j, n in zip(a.tolist(), b.tolist(), shared.tolist()):
        ki, kj = node[i], node[j]
        graph.add(gtsam.BetweenFactorSimilarity3(ki, kj, old[ki].inverse().compose(old[kj]),
                                                 _noise(n, unit, sigma_rotation, _SIGMA_SCALE)))
    for h in hinges:
        seen = model.obs_image.data[model.observations_of_points(h.points)]
        seen = seen[seen != h.image]
        if len(seen) == 0:
            continue
        j = int(np.bincount(seen).argmax())
        there = _similarity(h.R, -h.R.T @ h.t)
        # from j, in whose frame the pose was found: so the unknown scale between the two ends is the
        # measurement's scale alone, and its translation holds whatever that scale turns out to be
        graph.add(gtsam.BetweenFactorSimilarity3(node[j], node[h.image], old[node[j]].inverse().compose(there),
                                                 _noise(len(h.points), unit, sigma_rotation, 1.0)))
    solved = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    new = [solved.atSimilarity3(k) for k in range(len(images))]
    # every point moves with the image of its oldest observation
    obs = model.alive_observations()
    pts, first = np.unique(model.obs_point.data[obs], return_index=True)
    ref = model.obs_image.data[obs[first]]
    moves = np.stack([new[k].matrix() @ np.linalg.inv(old[k].matrix()) for k in range(len(images))])
    index = np.full(len(model.image_ids), -1, np.int64)
    index[images] = np.arange(len(images))
    on = index[ref] >= 0
    pts, M = pts[on], moves[index[ref[on]]]
    X = np.einsum("nij,nj->ni", M[:, :3, :3], model.xyz.data[pts]) + M[:, :3, 3]
    model.xyz.data[pts] = X / M[:, 3, 3:]
    for k, i in enumerate(images.tolist()):
        R = new[k].rotation().matrix().T
        model.R[i], model.t[i] = R, -R @ new[k].transformFrom(np.zeros(3))


def covisibility(model: Reconstruction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, shared): the pose graph's edges, each registered image to its _NEIGHBOURS partners sharing the most
    points (_LEAST_SHARED or more; points of at most _LONGEST_TRACK views counted), a < b."""
    nobs = model.point_num_observations()
    pids = model.alive_points()
    pids = pids[(nobs[pids] >= 2) & (nobs[pids] <= _LONGEST_TRACK)]
    n = len(model.image_ids)
    keys = []
    for _, obs, mask in model.padded_groups(pids):
        img = model.obs_image.data[obs]
        for c1 in range(img.shape[1]):
            for c2 in range(c1 + 1, img.shape[1]):
                both = mask[:, c1] & mask[:, c2]
                lo = np.minimum(img[both, c1], img[both, c2])
                hi = np.maximum(img[both, c1], img[both, c2])
                keys.append(lo * n + hi)
    if not keys:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    key, shared = np.unique(np.concatenate(keys), return_counts=True)
    keep = shared >= _LEAST_SHARED
    key, shared = key[keep], shared[keep]
    a, b = key // n, key % n
    # each image's strongest partners: an edge stays when it is among either end's best
    chosen = np.zeros(len(key), bool)
    for ends in (a, b):
        order = np.lexsort((-shared, ends))
        first = np.r_[0, np.flatnonzero(np.diff(ends[order])) + 1]
        rank = np.arange(len(order)) - np.repeat(first, np.diff(np.r_[first, len(order)]))
        chosen[order[rank < _NEIGHBOURS]] = True
    return a[chosen], b[chosen], shared[chosen]


def _similarity(R_cam_from_world: np.ndarray, center: np.ndarray) -> "gtsam.Similarity3":
    return gtsam.Similarity3(gtsam.Rot3(np.ascontiguousarray(R_cam_from_world.T)), np.asarray(center, float), 1.0)


def _noise(shared: int, unit: float, sigma_rotation: float, sigma_scale: float, times: float = 1.0):
    w = times * (_REFERENCE_SHARED / max(shared, 1)) ** 2
    return gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sigma_rotation * w),
                                                  np.full(3, _SIGMA_TRANSLATION * unit * w), sigma_scale * w])
