"""Triangulation of tracks and continuation of existing points, vectorised over tracks.

A track gets a 3D point once two or more of its images are registered: multi-view DLT over all its registered
views, Gauss-Newton refinement, then the checks (positive depth, reprojection <= 4 px, largest triangulation
angle >= 1.5 deg). When an outlier view spoils the joint solution, two-view hypotheses are tried (a small
RANSAC over view pairs) and the best is refined on its inliers. Existing points are continued into registered
views of their tracks that reproject within the threshold.

Loop closure: a model drifts as it grows around a loop, and the image that closes it sees the first points
several pixels off, so the 4 px gate keeps those views out and the drift stays in the model (wide_orbit: 1.5-2
deg at the closure). Before the final refinement, views are therefore continued once through a loose angular
gate (2 deg, COLMAP's continue_max_angle_error); the bundle adjustment that follows pulls the loop together,
and the filters after it remove the views it cannot bring within 4 px. The loose gate during growth instead
measured slower (outliers cost bundle adjustment iterations) and no more accurate.
"""

import numpy as np

from ..geometry.absolute_pose import pnp_ransac
from ..geometry.triangulation import reaches_triangulation_angle, refine_points, triangulate_dlt
from .config import MapperConfig
from .model import Reconstruction, padded_slices
from .tracks import Tracks

_PAIR_HYPOTHESES = 8


def _registered_elements(model, tracks, track_ids):
    """Padded (n,k) image / keypoint / mask arrays of the registered views of each track."""
    lengths = tracks.lengths()[track_ids]
    starts = tracks.ptr[track_ids]
    kmax = int(lengths.max()) if len(lengths) else 0
    idx = starts[:, None] + np.arange(kmax)[None, :]
    inside = np.arange(kmax)[None, :] < lengths[:, None]
    idx = np.where(inside, idx, 0)
    images = tracks.image[idx]
    kps = tracks.keypoint[idx]
    mask = inside & model.registered[images]
    # compact the registered views to the left so k shrinks to the largest registered count
    order = np.argsort(~mask, axis=1, kind="stable")
    images = np.take_along_axis(images, order, 1)
    kps = np.take_along_axis(kps, order, 1)
    mask = np.take_along_axis(mask, order, 1)
    k = int(mask.sum(axis=1).max()) if len(mask) else 0
    return images[:, :k], kps[:, :k], mask[:, :k]


def _normalized(model, images, kps, mask):
    """Normalised coordinates of the views, and the mask less the views whose keypoint has no ray."""
    x = np.zeros((*images.shape, 2))
    x[mask] = model.normalized_at(images[mask], kps[mask])
    valid = np.isfinite(x).all(axis=-1)
    return np.where(valid[..., None], x, 0.0), mask & valid


def _angular_errors_deg(model, X, images, x):
    """Angle (deg) between each view's ray (normalised coordinates x) and the direction to its point X."""
    Xc = np.einsum("nij,nj->ni", model.R[images], X) + model.t[images]
    ray = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    cos = np.einsum("ni,ni->n", Xc, ray) / (np.linalg.norm(Xc, axis=1) * np.linalg.norm(ray, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), Xc[:, 2]


def _passes_gate(model, X, images, kps, config, x=None):
    """Views whose point is in front and within the gate: the reprojection error in pixels through the camera
    model, or, given the views' normalised coordinates `x`, the loose angular gate. Pixels rather than
    normalised residuals times the focal: under a strong distortion those overstate the periphery's errors
    (2.5x at the edge of the wide_orbit lens), and the filters measure in pixels too."""
    if x is not None:
        err, depth = _angular_errors_deg(model, X, images, x)
        limit = config.tri_max_angle_error_deg
    else:
        uv, depth = model.project(images, X)
        err = np.linalg.norm(uv - model.keypoints_at(images, kps), axis=1)
        limit = config.max_reproj_error_px
    return np.isfinite(err) & (depth > 0) & (err <= limit)


def _inlier_views(model, X, images, kps, mask, config):
    """The views of `mask` that pass the pixel gate (n,k)."""
    rows, cols = np.nonzero(mask)
    inl = np.zeros(mask.shape, bool)
    if len(rows):
        inl[rows, cols] = _passes_gate(model, X[rows], images[rows, cols], kps[rows, cols], config)
    return inl


def _check(model, X, images, kps, mask, config):
    """Inlier views (through the pixel gate) and whether each point is kept (two inlier views or more,
    largest triangulation angle over them above the minimum)."""
    inl = _inlier_views(model, X, images, kps, mask, config)
    centers = model.centers()[images]
    ok = (inl.sum(axis=1) >= 2) & reaches_triangulation_angle(X, centers, inl, config.min_tri_angle_deg)
    return inl, ok


def triangulate_tracks(model: Reconstruction, tracks: Tracks, track_ids: np.ndarray, config: MapperConfig,
                       seed: int = 0) -> int:
    """Create points for the given tracks that have none yet and >= 2 registered views. Returns points
    added.

    The tracks are padded to the longest, so that many at once (a global mapper's every track) are taken in
    groups of at most model.PADDED_VIEWS padded views (`padded_slices`): at once, the padded poses and rays of a
    300-image survey's tracks held 1.6 GB above the model."""
    track_ids = np.unique(np.asarray(track_ids, dtype=np.int64))
    track_ids = track_ids[model.point_of_track[track_ids] < 0]
    if len(track_ids) == 0:
        return 0
    # in the given order, so that points are numbered as in one group
    return sum(_triangulate_group(model, tracks, track_ids[part], config, seed)
               for part in padded_slices(tracks.lengths()[track_ids]))


def _triangulate_group(model, tracks, track_ids, config, seed) -> int:
    """`triangulate_tracks` on tracks without a point. They are solved in buckets of similar registered view
    counts (`_count_buckets`), each padded to its own longest track rather than the group's: padded together,
    a few long tracks make every short one as long, and in a long sequence they grow with the model
    (docs/scale.md, street_long). Each track's point is the one a single padded array gives (up to rounding): the
    two-view hypotheses are drawn in track order over the whole group, and the points are added in track order."""
    parts = []
    for pos in _count_buckets(_registered_views(model, tracks, track_ids)):
        images, kps, mask = _registered_elements(model, tracks, track_ids[pos])
        x, mask = _normalized(model, images, kps, mask)
        keep = mask.sum(axis=1) >= 2
        if keep.any():
            parts.append(_Bucket(model, pos[keep], images[keep], kps[keep], mask[keep], x[keep], config))
    if not parts:
        return 0
    # Joint solution spoiled by an outlier view: best of a few two-view hypotheses, refined on its inliers.
    retry = np.sort(np.concatenate([b.pos[b.retry] for b in parts]))
    if len(retry):
        rng = np.random.default_rng(seed)
        draws = np.array([(rng.random(len(retry)), rng.random(len(retry))) for _ in range(_PAIR_HYPOTHESES)])
        for b in parts:
            b.try_pairs(model, draws[:, :, np.searchsorted(retry, b.pos[b.retry])], config)
    for b in parts:
        b.refit_partial(model, config)
    return _add_in_track_order(model, track_ids, parts)


def _count_buckets(counts: np.ndarray) -> list[np.ndarray]:
    """Positions (ascending) of the items grouped by the power of two their count rounds up to: padded to the
    longest of its bucket, an item's row is at most half padding."""
    level = np.ceil(np.log2(np.maximum(counts, 1))).astype(np.int64)
    order = np.argsort(level, kind="stable")
    cuts = np.flatnonzero(np.diff(level[order])) + 1
    return np.split(order, cuts)


class _Bucket:
    """Tracks padded together (`pos`: their positions in the group): the DLT point refined over all registered
    views, then the checks; `retry` are the rows an outlier view may have spoilt (failed, three views or more)."""

    def __init__(self, model, pos, images, kps, mask, x, config):
        self.pos, self.images, self.kps, self.mask, self.x = pos, images, kps, mask, x
        self.R, self.t = model.R[images], model.t[images]
        self.X = refine_points(triangulate_dlt(self.R, self.t, x, mask), self.R, self.t, x, mask)
        self.inl, self.ok = _check(model, self.X, images, kps, mask, config)
        self.retry = np.flatnonzero(~self.ok & (mask.sum(axis=1) >= 3))

    def try_pairs(self, model, draws, config) -> None:
        """The best of the two-view hypotheses of the retried rows, `draws` (hypotheses, 2, rows) in [0, 1)
        choosing each hypothesis's two views, refined on its inliers."""
        retry = self.retry
        if len(retry) == 0:
            return
        nview = self.mask[retry].sum(axis=1)
        best_count = np.full(len(retry), -1)
        best_X = self.X[retry].copy()
        rr = np.arange(len(retry))
        Rr, tr, xr, mr = self.R[retry], self.t[retry], self.x[retry], self.mask[retry]
        kr, ir = self.kps[retry], self.images[retry]
        for first, second in draws:
            a = (first * nview).astype(int)
            b = (a + 1 + (second * (nview - 1)).astype(int)) % nview
            sub = np.zeros_like(mr)
            sub[rr, a] = True
            sub[rr, b] = True
            Xh = triangulate_dlt(Rr, tr, xr, sub)
            count = _inlier_views(model, Xh, ir, kr, mr, config).sum(axis=1)  # counts need no angles
            better = count > best_count
            best_count[better], best_X[better] = count[better], Xh[better]
        inl_r = _inlier_views(model, best_X, ir, kr, mr, config)
        self.X[retry] = refine_points(best_X, Rr, tr, xr, inl_r)
        self.inl[retry], self.ok[retry] = _check(model, self.X[retry], ir, kr, inl_r, config)

    def refit_partial(self, model, config) -> None:
        """Refit the kept points that some views failed on their inlier views only."""
        partial = self.ok & (self.inl.sum(axis=1) < self.mask.sum(axis=1))
        if partial.any():
            p = np.flatnonzero(partial)
            self.X[p] = refine_points(self.X[p], self.R[p], self.t[p], self.x[p], self.inl[p], iterations=3)
            self.inl[p], self.ok[p] = _check(model, self.X[p], self.images[p], self.kps[p], self.inl[p], config)


def _add_in_track_order(model, track_ids, parts) -> int:
    """Add the kept points of the buckets, numbered in the group's track order, each with its inlier views in
    track order. Returns points added."""
    pos, X, local, images, kps, offset = [], [], [], [], [], 0
    for b in parts:
        sel = np.flatnonzero(b.ok)
        row, view = np.nonzero(b.inl[sel])
        pos.append(b.pos[sel])
        X.append(b.X[sel])
        local.append(row + offset)
        images.append(b.images[sel][row, view])
        kps.append(b.kps[sel][row, view])
        offset += len(sel)
    if offset == 0:
        return 0
    pos = np.concatenate(pos)
    order = np.argsort(pos, kind="stable")
    rank = np.empty(len(pos), np.int64)
    rank[order] = np.arange(len(pos))
    local = rank[np.concatenate(local)]
    views = np.argsort(local, kind="stable")
    model.add_points(np.concatenate(X)[order], track_ids[pos[order]], local[views],
                     np.concatenate(images)[views], np.concatenate(kps)[views])
    return offset


def continue_points(model: Reconstruction, tracks: Tracks, config: MapperConfig,
                    images: np.ndarray | list[int] | None = None, loose: bool = False, seed: int = 0) -> int:
    """Add observations of existing points in registered views of their tracks (restricted to `images` when
    given) that pass the pixel gate, or with `loose` the angular one and then `_refits` or `_coherent`.
    Returns observations added."""
    e, img, kp, p = unobserved_views(model, tracks, images)
    if len(e) == 0:
        return 0
    x = None
    if loose:
        x = model.normalized_at(img, kp)
    good = _passes_gate(model, model.xyz.data[p], img, kp, config, x)
    if loose:
        good[good] = (_refits(model, p[good], img[good], kp[good], config)
                      | _coherent(model, model.xyz.data[p[good]], img[good], x[good], config, seed))
    model.add_observations(p[good], img[good], kp[good])
    return int(good.sum())


def unobserved_views(model: Reconstruction, tracks: Tracks, images: np.ndarray | list[int] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(elements, images, keypoints, points): the track elements in registered images (of `images` when given)
    whose track has a point that the keypoint does not observe."""
    e = np.arange(len(tracks.image)) if images is None else tracks.elements_of_images(images)
    model.scanned += len(e)
    img, kp = tracks.image[e], tracks.keypoint[e]
    p = model.point_of_track[tracks.element_track[e]]
    cand = (p >= 0) & model.registered[img]
    e, img, kp, p = e[cand], img[cand], kp[cand], p[cand]
    free = model.obs_of_kp_flat[model.kp_offset[img] + kp] < 0
    return e[free], img[free], kp[free], p[free]


def _refits(model, points, images, kps, config: MapperConfig) -> np.ndarray:
    """Whether each new view (images, kps) of `points` is one the point, re-fitted to its views and this one,
    reprojects within the pixel gate in all of them (COLMAP's test for merging two tracks): a view that drift or
    a poor early estimate left a few pixels off, where a wrong match that the angular gate lets in (its 2
    degrees are tens of pixels at a long focal length) cannot be fitted so. Fitted by the bundle adjustment
    that follows, such matches bent blurred and noisy models."""
    pids, obs, mask = model.padded_observations(np.unique(points))
    found = np.zeros(len(points), bool)
    if len(pids) == 0:
        return found
    row = np.minimum(np.searchsorted(pids, points), len(pids) - 1)
    found = pids[row] == points
    # the new views in slices of at most PADDED_VIEWS padded views (`padded_slices`): at once, the padded arrays
    # of a dense orbit's loop closure were its mapping's memory peak (docs/scale.md); every slice keeps the whole
    # width, so each view's verdict is unchanged
    slices = padded_slices(np.full(len(points), obs.shape[1] + 1))
    return np.concatenate([_refit_slice(model, obs[row[s]], mask[row[s]] & found[s, None], images[s], kps[s],
                                        model.xyz.data[points[s]], found[s], config) for s in slices])


def _refit_slice(model, obs, mask, images, kps, X, found, config) -> np.ndarray:
    """`_refits` of the new views (images, kps) of points X whose padded observations are `obs`, `mask`."""
    images_k = np.c_[model.obs_image.data[obs], images]
    kps_k = np.c_[model.obs_kp.data[obs], kps]
    mask_k = np.c_[mask, found]
    x, valid = _normalized(model, images_k, kps_k, mask_k)
    X = refine_points(X, model.R[images_k], model.t[images_k], x, valid, iterations=3)
    inl = _inlier_views(model, X, images_k, kps_k, valid, config)
    return found & np.isfinite(X).all(axis=1) & (inl == valid).all(axis=1)


def _coherent(model, X, images, x, config: MapperConfig, seed: int) -> np.ndarray:
    """Whether each new view (of point X, at normalised coordinates x, in `images`) is among those of its image
    that one pose of the image fits within the pixel gate, when at least abs_pose_min_inliers do (P3P in
    RANSAC). The image closing a loop sees the loop's first points displaced together by the drift: their
    points are pinned by many views and cannot be re-fitted to it (`_refits`), but one pose fits them all."""
    keep = np.zeros(len(X), bool)
    for i in np.unique(images):
        sel = np.flatnonzero(images == i)
        if len(sel) < config.abs_pose_min_inliers:
            continue
        K = model.camera(int(i)).K()
        uv = x[sel] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        est = pnp_ransac(X[sel], uv, K, config.max_reproj_error_px, seed=seed)
        if est is not None and est[2].sum() >= config.abs_pose_min_inliers:
            keep[sel[est[2]]] = True
    return keep


def tracks_of_image(model: Reconstruction, tracks: Tracks, image: int) -> np.ndarray:
    t = tracks.track_of[image]
    return np.unique(t[t >= 0])


def retriangulate(model: Reconstruction, tracks: Tracks, config: MapperConfig,
                  seed: int = 0, images: np.ndarray | list[int] | None = None) -> tuple[int, int]:
    """Continue all points into every registered view and triangulate the tracks still without a point
    (COLMAP's retriangulation after global BA, which recovers points lost to earlier poor poses). With
    `images`, only the tracks through those images: after a bundle adjustment of a subset, the tracks it could
    have changed, at a cost in proportion to the subset rather than to every track.

    A track that fails is tried again only once it has gained a registered view, or once a camera has
    changed (any parameter by more than 0.5%, relative to max(|value|, 1)) since the tracks were last all
    tried, as COLMAP bounds its retriangulation trials (re_max_trials). Most failures are tracks with a wrong
    view that no pose refinement fixes, and re-solving them after every global BA was most of the mapping's
    Python time on opensfm_lund (29 images, 1024 x 768); but tracks spoilt by a wrong focal or distortion do
    triangulate once the camera is found (wide_orbit_small's AUC@1 fell from 0.45 to 0.40 without the reset).
    """
    added_obs = continue_points(model, tracks, config, images=images)
    params = np.concatenate([model.cameras[c].params for c in sorted(model.cameras)])
    before = model.tri_failed_params
    if len(before) != len(params) or np.max(np.abs(params - before) / np.maximum(np.abs(before), 1)) > 5e-3:
        model.tri_failed_views[:] = 0
        model.tri_failed_params = params.copy()
    if images is None:
        track_ids = np.arange(len(tracks))
        registered_count = np.bincount(tracks.element_track, weights=model.registered[tracks.image],
                                       minlength=len(tracks)).astype(np.int64)
    else:
        track_ids = np.unique(tracks.element_track[tracks.elements_of_images(images)])
        registered_count = _registered_views(model, tracks, track_ids)
    open_ = ((registered_count >= 2) & (model.point_of_track[track_ids] < 0)
             & (registered_count > model.tri_failed_views[track_ids]))
    cand, registered_count = track_ids[open_], registered_count[open_]
    made = triangulate_tracks(model, tracks, cand, config, seed)
    failed = model.point_of_track[cand] < 0
    model.tri_failed_views[cand[failed]] = registered_count[failed]
    return made, added_obs


def _registered_views(model: Reconstruction, tracks: Tracks, track_ids: np.ndarray) -> np.ndarray:
    """The registered views of each of `track_ids`, visiting only their elements."""
    elements, owner = tracks.elements_of_tracks(track_ids)
    model.scanned += len(elements)
    return np.bincount(owner, weights=model.registered[tracks.image[elements]],
                       minlength=len(track_ids)).astype(np.int64)


def refine_existing_points(model: Reconstruction, point_ids: np.ndarray, iterations: int = 3) -> None:
    """Re-fit points to their observations with the poses held fixed: the points a subset bundle adjustment
    left out follow the poses it moved (their outliers go to the filters that run next). Groups of at most
    PADDED_VIEWS padded views at a time (`Reconstruction.padded_groups`), each point as the whole would be:
    at once, a pose per padded view held the peak of a 300-image survey's final refinement (85,000 points
    padded to their longest track)."""
    for p, o, mask in model.padded_groups(point_ids):
        images, kps = model.obs_image.data[o], model.obs_kp.data[o]
        x, m = _normalized(model, images, kps, mask)
        X = refine_points(model.xyz.data[p], model.R[images], model.t[images], x, m, iterations)
        ok = np.isfinite(X).all(axis=1)
        model.xyz.data[p[ok]] = X[ok]
