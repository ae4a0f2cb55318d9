"""The initial pair: two views with many verified matches and a wide enough baseline to triangulate well.

Candidates are tried in order of inlier count (COLMAP also favours images with many correspondences), then,
when none of the first init_max_pairs starts a model, as many more in COLMAP's image-first order; for each
the relative pose comes from the essential matrix (with the camera's focal prior when it is not known) and is
accepted when enough points triangulate with a median angle above the threshold. Each pair is estimated once
(from at most 1000 of its matches); the mapper then triangulates all the tracks the two images share.
Thresholds are relaxed in turn (16 deg, then 8, 4, 2) so scenes without a wide baseline still start, as COLMAP
relaxes its own. A pair that a homography explains and that is a rotation about the camera centre for a focal
length the camera may have (`_rotation_fit`) is rejected first: with a guessed focal, the essential matrix of a
camera turning in place fits a baseline to the focal error, and a model with cameras metres apart would come
out of a panorama (as COLMAP's pipeline builds one). Other planar-with-no-baseline pairs fail the angle check.
It refuses panorama_small and changes no model where else it fires (templeSparseRing, toy_object_small).
When no pair is accepted, `initial_pair_rejections` says what each pair missed (the mapper gives the nearest
miss as the reason of the images that stay unregistered).
"""

from dataclasses import dataclass

import cv2
import numpy as np

from ..database import PairGeometry
from ..geometry.triangulation import refine_points, residuals, triangulation_angle_deg, two_view_midpoints
from ..geometry.two_view import focal_from_fundamental, homography_translation, relative_pose
from .config import MapperConfig
from .model import Reconstruction


@dataclass
class InitialPair:
    image1: int  # internal indices
    image2: int
    R: np.ndarray  # cam2_from_cam1 (image1 is the world frame)
    t: np.ndarray
    median_angle_deg: float
    focals: dict  # camera id -> the focal length the pose was estimated with


@dataclass
class PairRejection:
    """Why a pair did not become the initial pair. `text` completes "the pair (A / B) has ...";
    `closeness` orders rejections, the nearest miss largest: how far the pair got (the stages below), then how
    close it came at that stage."""

    image1: int  # internal indices
    image2: int
    closeness: tuple
    text: str


# how far a rejected pair got, from the least to the most promising
_FEW_MATCHES, _NOT_TRIED, _ROTATION, _NO_POSE, _FEW_POSE_INLIERS, _FEW_POINTS, _SMALL_ANGLE, _DISCARDED = range(8)


_DECISION_MATCHES = 1000  # a pose and a median angle from this many matches decide as well as from all


def two_view_points(R: np.ndarray, t: np.ndarray, x1: np.ndarray,
                    x2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate normalised matches for cam1 = [I|0], cam2 = [R|t]; returns points, depths (n,2), errors
    (n,2)."""
    n = len(x1)
    Rs = np.stack([np.broadcast_to(np.eye(3), (n, 3, 3)), np.broadcast_to(R, (n, 3, 3))], axis=1)
    ts = np.stack([np.zeros((n, 3)), np.broadcast_to(t, (n, 3))], axis=1)
    xs = np.stack([x1, x2], axis=1)
    mask = np.ones((n, 2), bool)
    X0 = two_view_midpoints(R, t, x1, x2)
    X0[~np.isfinite(X0).all(axis=1)] = 0.0  # parallel rays: no point (the checks reject it)
    X = refine_points(X0, Rs, ts, xs, mask, iterations=3)
    r, z = residuals(X, Rs, ts, xs, mask)
    return X, z, np.linalg.norm(r, axis=-1)


def evaluate_pair(model: Reconstruction, pair: PairGeometry, i1: int, i2: int, config: MapperConfig,
                  focal_from_pair: bool = True) -> InitialPair | None:
    """Relative pose and median triangulation angle of one candidate pair (on a seeded subset of at most
    1000 of its matches), or None when it fails the criteria that do not depend on the angle threshold.
    With `focal_from_pair` a guessed focal is first replaced by the pair's estimate (below); without, the
    cameras' current focal lengths are used."""
    found = assess_pair(model, pair, i1, i2, config, focal_from_pair)
    return found if isinstance(found, InitialPair) else None


def assess_pair(model: Reconstruction, pair: PairGeometry, i1: int, i2: int, config: MapperConfig,
                focal_from_pair: bool = True) -> InitialPair | PairRejection:
    """`evaluate_pair`, with a PairRejection saying which criterion failed instead of None."""
    rotation = _rotation_fit(model, pair, i1, i2)
    limit = np.radians(config.min_tri_angle_deg)
    if rotation is not None and rotation[0] < limit:
        spread, focal = rotation
        return PairRejection(i1, i2, (_ROTATION, spread),
                             f"no baseline: a rotation about the camera centre explains its matches (homography "
                             f"|t|/d {spread:.3f} < {limit:.3f} at a focal of {focal:.0f} px): a camera turning in "
                             f"place (a panorama), or the same view twice")
    k1, k2 = pair.inliers[:, 0], pair.inliers[:, 1]
    if len(k1) > _DECISION_MATCHES:
        pick = np.sort(np.random.default_rng(config.seed).choice(len(k1), _DECISION_MATCHES, replace=False))
        k1, k2 = k1[pick], k2[pick]
    if focal_from_pair:
        _focal_from_pair(model, i1, i2, k1, k2)
    x1 = model.normalized_keypoints(i1)[k1]
    x2 = model.normalized_keypoints(i2)[k2]
    has_ray = np.isfinite(x1).all(axis=1) & np.isfinite(x2).all(axis=1)
    x1, x2 = x1[has_ray], x2[has_ray]
    f = 0.5 * (model.camera(i1).focal() + model.camera(i2).focal())
    est = relative_pose(x1, x2, config.two_view_max_error_px / f, seed=config.seed)
    if est is None:
        return PairRejection(i1, i2, (_NO_POSE, 0.0), "no relative pose: its essential matrix puts too few "
                                                      "matches in front of both views")
    R, t, inl = est
    if inl.sum() < config.init_min_inliers:
        return PairRejection(i1, i2, (_FEW_POSE_INLIERS, float(inl.sum())),
                             f"{int(inl.sum())} of {len(x1)} matches fitting its relative pose in front of "
                             f"both views, < init_min_inliers {config.init_min_inliers}")
    X, z, err = two_view_points(R, t, x1[inl], x2[inl])
    angle = triangulation_angle_deg(np.zeros(3), -R.T @ t, X)
    good = (z > 0).all(axis=1) & (err.max(axis=1) * f < config.max_reproj_error_px)
    good &= np.isfinite(X).all(axis=1)
    good &= angle >= config.min_tri_angle_deg
    if good.sum() < config.init_min_inliers:
        return PairRejection(i1, i2, (_FEW_POINTS, float(good.sum())),
                             f"{int(good.sum())} points triangulated at {config.min_tri_angle_deg:g} deg or "
                             f"more, < init_min_inliers {config.init_min_inliers}")
    focals = {int(model.camera_of[i]): model.camera(i).focal() for i in (i1, i2)}
    return InitialPair(i1, i2, R, t, float(np.median(angle[good])), focals)


_FOCAL_RANGE = (0.5, 2.0)
_H_DOMINANT = ("PLANAR_OR_PANORAMIC", "PANORAMIC", "PLANAR")  # pairs a homography explains (matching/verify.py)


def _rotation_fit(model, pair, i1: int, i2: int) -> tuple[float, float] | None:
    """(|t|/d, focal of image1) where the pair's homography is closest to a rotation about the camera centre,
    over the focal lengths the cameras may have: a trusted one as it is, a guessed one from 0.5 to 2 times its
    prior (the range `_focal_from_pair` accepts). None when no homography explains the pair. The homography is
    in distorted pixels: guessed cameras have no distortion yet, and a trusted lens that bends lines enough to
    matter leaves no pair that a homography explains."""
    if pair.config not in _H_DOMINANT or pair.H is None:
        return None
    scales = np.geomspace(*_FOCAL_RANGE, 241)  # steps of 0.6%
    Ks = []
    for cam in (model.camera(i1), model.camera(i2)):
        K = np.broadcast_to(cam.K(), (len(scales), 3, 3)).copy()
        if not cam.prior_trusted:
            K[:, :2, :2] *= (cam.prior_focal / cam.focal() * scales)[:, None, None]
        Ks.append(K)
    spread = homography_translation(pair.H, Ks[0], Ks[1])
    best = int(np.argmin(spread))
    return float(spread[best]), float(np.mean(np.diag(Ks[0][best])[:2]))


def _focal_from_pair(model, i1: int, i2: int, k1, k2) -> None:
    """Replace guessed focal lengths (not trusted, from 1.2 * max(w, h)) by the ones the pair's fundamental
    matrix implies, when that estimate is plausible; a wrong focal prior skews the whole initial model.

    Bougnoux's formula degenerates when the optical axes nearly meet (orbits around an object); then the
    estimate is NaN or implausible and the prior stays.
    """
    c1, c2 = model.camera(i1), model.camera(i2)
    if c1.focal_kept and c2.focal_kept:
        return
    for cam in (c1, c2):
        if not cam.focal_kept:
            cam.set_focal(cam.prior_focal)
    u1, u2 = model.keypoints[i1][k1], model.keypoints[i2][k2]
    F, mask = cv2.findFundamentalMat(u1, u2, cv2.FM_RANSAC, 1.0, 0.999, 5000)
    if F is None or F.shape != (3, 3):
        return
    f1, f2 = focal_from_fundamental(F, c1.K()[:2, 2], c2.K()[:2, 2])
    if c1 is c2:
        good = [f for f in (f1, f2) if np.isfinite(f)]
        estimates = {id(c1): float(np.exp(np.mean(np.log(good)))) if good else np.nan}
    else:
        estimates = {id(c1): f1, id(c2): f2}
    for cam in (c1, c2):
        f = estimates[id(cam)]
        plausible = np.isfinite(f) and _FOCAL_RANGE[0] < f / cam.prior_focal < _FOCAL_RANGE[1]
        if not cam.focal_kept and plausible:
            cam.set_focal(f)


def find_initial_pair(model: Reconstruction, pairs_by_index: dict[tuple[int, int], PairGeometry],
                      excluded: set[int], config: MapperConfig, tried: set,
                      evaluated: dict) -> InitialPair | None:
    """First pair meeting the criteria; `pairs_by_index` maps (i1, i2) internal indices -> PairGeometry.

    excluded: images already in another model; tried: (pair, angle threshold) that failed before (updated in
    place); evaluated: pair -> `assess_pair` result, so relaxing the angle does not estimate a pair again.
    """
    candidates = _candidates(pairs_by_index, excluded, config)
    for keys in ([key for _, key in candidates[:config.init_max_pairs]], _image_first(candidates, config)):
        for min_angle in config.init_min_tri_angles_deg:
            for key in keys:
                if (key, min_angle) in tried:
                    continue
                tried.add((key, min_angle))
                if key not in evaluated:
                    evaluated[key] = assess_pair(model, pairs_by_index[key], key[0], key[1], config)
                found = evaluated[key]
                if isinstance(found, InitialPair) and found.median_angle_deg >= min_angle:
                    for cid, focal in found.focals.items():  # later candidates may have moved a guessed focal
                        model.cameras[cid].set_focal(focal)
                    return found
    return None


def _image_first(candidates: list, config: MapperConfig) -> list:
    """The next init_max_pairs candidates in COLMAP's order, past the init_max_pairs with the most inliers:
    the images with the most inliers first, each with all its partners, most inliers first. Tried when none of
    the pairs with the most inliers starts a model: in a dense sequence (1,000 frames of an orbit) those are all
    neighbouring frames with no baseline, while each image's farther partners have one."""
    first = {key for _, key in candidates[:config.init_max_pairs]}
    weight: dict[int, int] = {}
    for n, (i, j) in candidates:
        weight[i] = weight.get(i, 0) + n
        weight[j] = weight.get(j, 0) + n
    partners: dict[int, list] = {}
    for n, key in candidates:  # most inliers first
        for i in key:
            partners.setdefault(i, []).append(key)
    out, seen = [], set(first)
    for i in sorted(weight, key=lambda i: (-weight[i], i)):
        for key in partners[i]:
            if key not in seen:
                seen.add(key)
                out.append(key)
                if len(out) == config.init_max_pairs:
                    return out
    return out


def rejected_for_few_inliers(found: InitialPair | PairRejection) -> bool:
    """Whether a pair's `assess_pair` result or rejection is one that a lower init_min_inliers could turn
    round."""
    return isinstance(found, PairRejection) and found.closeness[0] in (_FEW_MATCHES, _FEW_POSE_INLIERS, _FEW_POINTS)


def _candidates(pairs_by_index, excluded, config: MapperConfig) -> list:
    """(inliers, pair) of the pairs between images not in `excluded` with enough inliers, most inliers
    first."""
    return sorted(((len(p.inliers), key) for key, p in pairs_by_index.items()
                   if key[0] not in excluded and key[1] not in excluded
                   and len(p.inliers) >= config.init_min_inliers),
                  key=lambda c: (-c[0], c[1]))


def initial_pair_rejections(model: Reconstruction, pairs_by_index: dict[tuple[int, int], PairGeometry],
                            excluded: set[int], config: MapperConfig, evaluated: dict,
                            started: frozenset[int] = frozenset()) -> dict:
    """pair -> PairRejection for every pair between images not in `excluded`, after `find_initial_pair`
    accepted none of them: what each missed. A candidate not evaluated yet (the mapper resumed from a
    snapshot, or a camera's calibration changed since) is evaluated now, into `evaluated`. A pair whose angle
    passes a threshold was accepted before: it is in `started` (pairs whose model was discarded), or it was
    tried at every threshold before the calibration changed."""
    out = {}
    thresholds = config.init_min_tri_angles_deg
    loosest = min(thresholds) if thresholds else np.inf
    for rank, (n, key) in enumerate(_candidates(pairs_by_index, excluded, config)):
        if rank >= config.init_max_pairs and key not in evaluated:
            out[key] = PairRejection(*key, (_NOT_TRIED, float(n)),
                                     f"{n} inliers, but is not among the init_max_pairs "
                                     f"{config.init_max_pairs} pairs with the most, nor among those of the "
                                     f"images with the most, which are the ones tried")
            continue
        if key not in evaluated:
            evaluated[key] = assess_pair(model, pairs_by_index[key], key[0], key[1], config)
        found = evaluated[key]
        if isinstance(found, PairRejection):
            out[key] = found
        elif key in started:
            out[key] = PairRejection(*key, (_DISCARDED, found.median_angle_deg),
                                     "been the initial pair of a model that was discarded")
        elif found.median_angle_deg >= loosest:
            out[key] = PairRejection(*key, (_DISCARDED, found.median_angle_deg),
                                     f"a median triangulation angle of {found.median_angle_deg:.1f} deg, but "
                                     f"was tried at every threshold before a finished model calibrated its "
                                     f"camera")
        else:
            angle = _below(found.median_angle_deg, loosest)
            out[key] = PairRejection(*key, (_SMALL_ANGLE, found.median_angle_deg),
                                     f"a median triangulation angle of {angle} deg < {loosest:g} deg")
    for key, p in pairs_by_index.items():
        if key not in out and key[0] not in excluded and key[1] not in excluded:
            out[key] = PairRejection(*key, (_FEW_MATCHES, float(len(p.inliers))),
                                     f"{len(p.inliers)} inliers < init_min_inliers {config.init_min_inliers}")
    return out


def _below(value: float, limit: float) -> str:
    """`value` (< `limit`) to one decimal, or to as many as it takes not to print it as `limit` (1.97 < 2)."""
    for digits in (1, 2, 3):
        text = f"{value:.{digits}f}"
        if float(text) < limit:
            return text
    return f"{value:g}"
