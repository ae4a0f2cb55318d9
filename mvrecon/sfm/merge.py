"""The models of a partitioned mapping's parts merged into one frame, and finished as one model.

1. Links: for two part models, a similarity transform taking one into the other, estimated robustly
   (`geometry.sim3.ransac_umeyama`) on the camera centres of their shared registered images together with
   their shared 3D points (points of one full track in both: the same feature seen by both parts). A link
   needs SHARED_IMAGES_LEAST shared images, with the rotation it implies agreeing with every shared image's two
   orientations (median within MAX_ROTATION_DEG), and LINK_INLIERS_LEAST inliers; its strength is its inliers.
2. Merge order: the maximum spanning forest of the links (strongest overlaps first), each tree rooted at its
   largest part model; every part model is carried into the root's frame along its tree path.
3. One model per tree on the whole set's images and tracks: each image at its pose from the part model that
   observes it most, each camera with the parameters of the part model holding most of its images, and one
   point per full track, placed where the part model observing it most put it, with the observations of every
   part model that saw it (tracks cut by the partition join here). Then the incremental mapper's finish
   (`IncrementalMapper.finish`: loops closed, global bundle adjustment with intrinsics, retriangulation,
   filters), so the merged model is refined exactly as an unpartitioned one.
Trees that do not join become separate models; each image of a part model that could not be attached gets the
reason in its status.
"""

import logging
from dataclasses import dataclass, replace

import numpy as np

from ..database import Correspondences
from ..geometry.rotation import rotation_error_deg
from ..geometry.sim3 import Sim3, ransac_umeyama
from . import filtering
from .config import MapperConfig
from .incremental import IncrementalMapper, MappingResult
from .model import Reconstruction, image_status
from .parts import PartModel, PartResult

log = logging.getLogger("mvrecon.sfm")
SHARED_IMAGES_LEAST = 2  # registered images two part models must share to be linked
LINK_INLIERS_LEAST = 6  # centres and points fitting the link's transform
MAX_ROTATION_DEG = 5.0  # median disagreement of the shared images' orientations under the link
INLIER_SHARE = 0.05  # of the target's spread (median distance to the median), the transform's inlier threshold
MERGE_GATE_PX = 16.0  # observations of the assembled model farther than this are dropped before its refinement


@dataclass
class Link:
    """`T` takes part model `b`'s frame into `a`'s; `inliers`: centres and points fitting it."""

    T: Sim3
    inliers: int
    shared_images: int


def merge_parts(corr: Correspondences, config: MapperConfig, results: list[PartResult]) -> MappingResult:
    """One model (or more, when the parts do not all join) of the whole set `corr` from the parts' models
    (see the module docstring), with each image's status as the mappers give it."""
    mapper = IncrementalMapper(corr, config)
    index_of = {int(i): k for k, i in enumerate(mapper.image_ids.tolist())}
    pieces = [pm for r in results for pm in r.models if len(pm.image_ids) >= 2]
    keyed = [_observed(pm, mapper, index_of) for pm in pieces]
    links, failures = {}, {}
    for a in range(len(pieces)):
        for b in range(a + 1, len(pieces)):
            link = _link(pieces[a], pieces[b], keyed[a], keyed[b], config.seed)
            if isinstance(link, Link):
                links[(a, b)] = link
            elif link is not None:
                failures[(a, b)] = link
    trees = _spanning_forest(len(pieces), links, [len(pm.image_ids) for pm in pieces])
    reasons: dict[int, str] = {}
    for tree in trees[1:]:
        why = _detached_reason(tree, trees[0], failures)
        for p in tree:
            for i in pieces[p].image_ids.tolist():
                reasons.setdefault(index_of[i], why)
    taken = np.zeros(len(mapper.image_ids), bool)  # images of the models already made (larger trees)
    for tree in trees:
        frames = _frames(tree, links)
        m = _assemble(mapper, [pieces[p] for p in tree], [keyed[p] for p in tree], [frames[p] for p in tree],
                      index_of, taken)
        taken |= m.registered
        if m.registered.sum() < 2:
            continue
        log.info("merged %d part model(s) into a model of %d images, %d points", len(tree),
                 int(m.registered.sum()), len(m.alive_points()))
        mapper.finish(m)
    models = sorted(mapper.finished, key=lambda m: -int(m.registered.sum()))
    part_reason = _part_reasons(results, mapper.names)

    def reason(i: int) -> str:
        return mapper.reasons.get(i) or reasons.get(i) or part_reason.get(i, "registered in no part's model")

    status = image_status(mapper.names, mapper.keypoints, mapper.pairs, models, reason)
    for i, why in reasons.items():  # the images of a separate model say why it stayed apart
        entry = status[mapper.names[i]]
        if entry["status"] == "registered" and entry["model"] != 0:
            entry["note"] = f"in a separate model: {why}"
    return MappingResult(models, status, {"parts": len(results), "part_models": len(pieces),
                                          "links": len(links), "merged_models": len(trees),
                                          "ba_calls": mapper.ba_calls, "ba_seconds": mapper.ba_seconds})


@dataclass
class _Observed:
    """A part model's observations on the whole set: internal image index, keypoint, full track (-1: none) and
    point row of each; and the full tracks it has a point on (ascending), with that point's row (the point
    with most observations of the track)."""

    images: np.ndarray
    kps: np.ndarray
    tracks: np.ndarray
    rows: np.ndarray
    track_ids: np.ndarray
    track_rows: np.ndarray


def _observed(pm: PartModel, mapper: IncrementalMapper, index_of: dict) -> _Observed:
    lookup = np.array([index_of[int(i)] for i in pm.obs_image.tolist()], np.int64).reshape(-1)
    offsets = np.r_[0, np.cumsum([len(t) for t in mapper.tracks.track_of])].astype(np.int64)
    flat = np.concatenate(mapper.tracks.track_of) if len(offsets) > 1 else np.zeros(0, np.int64)
    tracks = flat[offsets[lookup] + pm.obs_kp] if len(lookup) else np.zeros(0, np.int64)
    keep = tracks >= 0
    pairs, counts = np.unique(np.c_[tracks[keep], pm.obs_point[keep]], axis=0, return_counts=True)
    order = np.lexsort((-counts, pairs[:, 0])) if len(pairs) else np.zeros(0, np.int64)
    pairs = pairs[order]
    first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]] if len(pairs) else np.zeros(0, bool)
    return _Observed(lookup, pm.obs_kp, tracks, pm.obs_point, pairs[first, 0].reshape(-1),
                     pairs[first, 1].reshape(-1))


def _link(pa: PartModel, pb: PartModel, ka: _Observed, kb: _Observed, seed: int) -> "Link | str | None":
    """The transform taking `pb` into `pa`'s frame (module docstring, step 1), or why there is none (None when
    they share no image at all)."""
    shared, ia, ib = np.intersect1d(pa.image_ids, pb.image_ids, return_indices=True)
    if len(shared) == 0:
        return None
    if len(shared) < SHARED_IMAGES_LEAST:
        return f"{len(shared)} shared registered image(s), < {SHARED_IMAGES_LEAST}"
    tracks, ta, tb = np.intersect1d(ka.track_ids, kb.track_ids, return_indices=True)
    src = np.r_[pb.centers()[ib], pb.xyz[kb.track_rows[tb]]]
    dst = np.r_[pa.centers()[ia], pa.xyz[ka.track_rows[ta]]]
    if len(src) < 3:
        return f"{len(shared)} shared images and {len(tracks)} shared points, too few for a transform"
    spread = float(np.median(np.linalg.norm(dst - np.median(dst, axis=0), axis=1)))
    T, inliers = ransac_umeyama(src, dst, INLIER_SHARE * max(spread, 1e-12), seed=seed)
    disagreement = float(np.median([rotation_error_deg(pa.R[x].T @ pb.R[y], T.R) for x, y in zip(ia, ib)]))
    if disagreement > MAX_ROTATION_DEG:
        return (f"the transform on {len(shared)} shared images and {len(tracks)} shared points turns their "
                f"orientations {disagreement:.1f} deg apart (> {MAX_ROTATION_DEG:g})")
    if int(inliers.sum()) < LINK_INLIERS_LEAST:
        return f"{int(inliers.sum())} centres and points fit a transform, < {LINK_INLIERS_LEAST}"
    return Link(T, int(inliers.sum()), len(shared))


def _spanning_forest(n: int, links: dict, sizes: list[int]) -> list[list[int]]:
    """The trees of the maximum spanning forest (Kruskal on link strength), each as [root, ...] in the order
    the parts join it, the root its largest part model; the trees largest first."""
    parent = list(range(n))

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    used = {}
    for (a, b), link in sorted(links.items(), key=lambda kv: -kv[1].inliers):
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
            used[(a, b)] = link
    groups: dict[int, list[int]] = {}
    for p in range(n):
        groups.setdefault(find(p), []).append(p)
    trees = []
    for members in groups.values():
        root = max(members, key=lambda p: (sizes[p], -p))
        order, seen = [root], {root}
        while len(order) < len(members):  # strongest link from the joined parts to one not yet joined
            best = max(((link.inliers, a if b in seen else b) for (a, b), link in used.items()
                        if (a in seen) != (b in seen)), default=None)
            order.append(best[1])
            seen.add(best[1])
        trees.append(order)
    return sorted(trees, key=lambda t: -sum(sizes[p] for p in t))


def _frames(tree: list[int], links: dict) -> dict[int, Sim3]:
    """Each part model of `tree` -> the transform taking its frame into the root's (composed along the tree)."""
    frames = {tree[0]: Sim3(1.0, np.eye(3), np.zeros(3))}
    for p in tree[1:]:
        for (a, b), link in links.items():
            if b == p and a in frames:  # link.T: b into a
                frames[p] = _compose(frames[a], link.T)
                break
            if a == p and b in frames:
                frames[p] = _compose(frames[b], link.T.inverse())
                break
    return frames


def _compose(outer: Sim3, inner: Sim3) -> Sim3:
    """outer after inner."""
    return Sim3(outer.scale * inner.scale, outer.R @ inner.R, outer.scale * outer.R @ inner.t + outer.t)


def _assemble(mapper: IncrementalMapper, pieces: list[PartModel], keyed: list[_Observed], frames: list[Sim3],
              index_of: dict, taken: np.ndarray) -> Reconstruction:
    """The model of one tree's part models on the whole set (module docstring, step 3), without the images
    `taken` by a model made before (an image is in one model only)."""
    m = Reconstruction(mapper.image_ids, mapper.names, mapper.camera_of, mapper.cameras, mapper.keypoints,
                       len(mapper.tracks))
    counts = [pm.observations_per_image() for pm in pieces]
    best_piece: dict[int, int] = {}
    for k, pm in enumerate(pieces):
        for i in pm.image_ids.tolist():
            if i not in best_piece or counts[k].get(i, 0) > counts[best_piece[i]].get(i, 0):
                best_piece[i] = k
    for k, (pm, T) in enumerate(zip(pieces, frames)):
        for row, i in enumerate(pm.image_ids.tolist()):
            # x_cam = R X + t in the part's frame, X_root = s Rs X + ts
            if best_piece[i] == k and not taken[index_of[i]]:
                R = pm.R[row] @ T.R.T
                m.register(index_of[i], R, T.scale * pm.t[row] - R @ T.t)
    for cid in np.unique(m.camera_of[m.registered]).tolist():
        holders = [sum(int(m.camera_of[index_of[i]] == cid) for i in pm.image_ids.tolist()) for pm in pieces]
        params = pieces[int(np.argmax(holders))].cameras[cid]
        m.cameras[cid].params = np.array(params, float)
    _add_points(m, pieces, keyed, frames)
    filtering.filter_observations(m, _gated(mapper.config))
    m.deregister_empty_images()
    return m


def _add_points(m: Reconstruction, pieces: list[PartModel], keyed: list[_Observed], frames: list[Sim3]) -> None:
    """One point per full track seen by a part model, with the union of the part models' observations on it in
    the model's registered images, placed where the part model with most observations of it put it."""
    xyz, tracks, nobs, images = [], [], [], []
    for pm, ob, T in zip(pieces, keyed, frames):
        count = np.bincount(pm.obs_point, minlength=len(pm.xyz))
        xyz.append(T.apply(pm.xyz[ob.track_rows]).reshape(-1, 3))
        tracks.append(ob.track_ids)
        nobs.append(count[ob.track_rows])
        keep = (ob.tracks >= 0) & m.registered[ob.images]
        images.append(np.c_[ob.tracks[keep], ob.images[keep], ob.kps[keep]])
    xyz, tracks, nobs = np.concatenate(xyz), np.concatenate(tracks), np.concatenate(nobs)
    best = np.lexsort((-nobs, tracks))  # per track, the part model's point with most observations first
    first = np.r_[True, tracks[best][1:] != tracks[best][:-1]] if len(best) else np.zeros(0, bool)
    track_ids, where = tracks[best][first], xyz[best][first]
    views = np.unique(np.concatenate(images), axis=0)  # (track, image, keypoint), each view once
    views = views[np.r_[True, (views[1:, :2] != views[:-1, :2]).any(axis=1)]] if len(views) else views
    counted = np.bincount(views[:, 0], minlength=len(m.point_of_track)) if len(views) else np.zeros(0, int)
    seen = np.isin(track_ids, np.flatnonzero(counted >= 2))
    track_ids, where = track_ids[seen], where[seen]
    views = views[np.isin(views[:, 0], track_ids)]
    if len(track_ids):
        local = np.searchsorted(track_ids, views[:, 0])
        m.add_points(where, track_ids, local, views[:, 1], views[:, 2])


def _gated(config: MapperConfig) -> MapperConfig:
    return replace(config, filter_max_reproj_error_px=max(MERGE_GATE_PX, config.filter_max_reproj_error_px))


def _detached_reason(tree: list[int], main: list[int], failures: dict) -> str:
    """Why the part models of `tree` stayed apart from the largest tree `main`."""
    tried = [why for (a, b), why in failures.items() if (a in tree and b in main) or (b in tree and a in main)]
    if tried:
        return f"its part's model could not be attached to the largest model: {tried[0]}"
    return "its part's model shares no registered image with the largest model"


def _part_reasons(results: list[PartResult], names: list[str]) -> dict[int, str]:
    """Image index -> the reason its part's mapping gave for leaving it out (the first part that did)."""
    index = {name: k for k, name in enumerate(names)}
    out = {}
    for r in results:
        for name, s in r.status.items():
            if s["status"] != "registered" and name in index:
                out.setdefault(index[name], f"in its part of the partitioned mapping: {s['reason']}")
    return out
