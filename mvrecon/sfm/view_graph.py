"""The view graph of the global mapper: its verified pairs, and the focal lengths behind them.

`calibrate_focals` first sets each guessed focal length (not trusted, 1.2 * max(w, h)) from the pairs'
fundamental matrices, as GLOMAP calibrates its view graph: an essential matrix E = K2^T F K1 has two equal
singular values, so the focal that makes (s1 - s2) / (s1 + s2) smallest over the camera's pairs (the
`_CALIBRATION_PAIRS` with the most matches: the estimate needs no more, and its cost then does not grow with the
set) is the one the pairs support (one scale per camera, searched over 0.25-3x the guess, cameras in turn;
herzjesu: 2776 px for the true 2760, from 3686). Where the cost has no clear minimum inside that range (under
0.65 of the cost at both ends: a street's or a facade's minimum is at 0.53-0.62, an orbit's at 0.76-1) the guess
stays: when the optical axes meet (an orbit around an object) the pairs do
not observe the focal, and the smallest focal tried wins (object_orbit_small: 384 px for the true 560); the
global mapper then finds it with coarse models (global_mapper.py). pair_poses.py then estimates each pair's
relative pose at the calibration found.
"""

import logging
from collections.abc import Iterable

import cv2
import numpy as np

from ..database import PairGeometry
from ..geometry import camera as cammodel
from .model import Camera, Reconstruction

log = logging.getLogger("mvrecon.sfm")

SAMPLE = 1000  # matches a pair's fundamental matrix or relative pose is estimated from (as the initial pair's)
_SCALES = np.geomspace(0.25, 3.0, 161)  # of a guessed focal, tried by the calibration (steps of 1.6%)
_EDGE = 6  # a minimum this close to either end of the range is no estimate
_SHARPNESS = 0.65  # the minimum's cost must be under this share of the cost at both ends of the range
_CALIBRATION_SWEEPS = 3
MIN_RELATIVE_INLIERS = 15  # a pair's matches fitting its relative pose (COLMAP's min_num_inliers)
_CALIBRATION_PAIRS = 300  # a camera's pairs (those with the most matches) its focal is calibrated from


def oriented_pairs(image_ids: np.ndarray, pairs: Iterable[PairGeometry]) -> dict:
    """(a, b) internal indices with a < b -> (N,2) inlier keypoint indices of a and b, for verified pairs."""
    index_of = {int(i): k for k, i in enumerate(np.asarray(image_ids).tolist())}
    out = {}
    for p in pairs:
        a, b = index_of.get(p.image_id1), index_of.get(p.image_id2)
        if a is None or b is None or len(p.inliers) == 0 or a == b:
            continue
        out[(a, b) if a < b else (b, a)] = p.inliers if a < b else p.inliers[:, ::-1]
    return out


def sample_matches(matches: np.ndarray, seed: int, size: int = SAMPLE) -> np.ndarray:
    """At most `size` of `matches` (rows), drawn at `seed` and kept in their order; all of them when fewer."""
    if len(matches) <= size:
        return matches
    return matches[np.sort(np.random.default_rng(seed).choice(len(matches), size, replace=False))]


def _fundamental(model, a, b, matches):
    u1, u2 = model.keypoints[a][matches[:, 0]], model.keypoints[b][matches[:, 1]]
    if len(u1) < 8:
        return None
    F, _ = cv2.findFundamentalMat(u1, u2, cv2.FM_8POINT)
    return F if F is not None and F.shape == (3, 3) else None


def _essential_costs(F, K1s, K2s) -> np.ndarray:
    """(s1 - s2) / (s1 + s2) of E = K2^T F K1 for stacks of calibrations."""
    E = np.einsum("nji,jk,nkl->nil", K2s, F, K1s)
    s = np.linalg.svd(E, compute_uv=False)
    return (s[:, 0] - s[:, 1]) / np.maximum(s[:, 0] + s[:, 1], 1e-300)


def calibratable_cameras(cameras: dict, camera_of: np.ndarray, single: bool = False) -> set[int]:
    """The cameras (id -> Camera; `camera_of` each image's id) whose focal `calibrate_focals` sets: guessed (not
    trusted) and shared by two images or more (with `single`, also those of a single image). A camera of a single
    image keeps its guess by default: its focal meets only other unknown focals in its pairs, and the bundle
    adjustments find it from the points (imc_reichstag, a camera per photo, incremental AUC@5 0.711 -> 0.635
    calibrated so; visitor_photos_small, the global mapper 0.702 with two images misplaced -> 0.976); the global
    mapper also maps such a set with them calibrated and keeps the better mapping (global_mapper.py). Neutral or
    better on every set where it fires (docs/benchmarks.md, "Mapper rules")."""
    users = np.bincount(camera_of, minlength=max(cameras, default=0) + 1)
    return {c for c, cam in cameras.items() if not cam.prior_trusted and (single or users[c] >= 2)}


def calibrate_focals(model: Reconstruction, pairs: dict, seed: int = 0, single: bool = False) -> dict:
    """Set the focal of every camera of `calibratable_cameras` (`single` passed on) to the one its pairs'
    fundamental matrices support best (see the module docstring), logged; returns camera id -> (guess,
    calibrated focal) of those it changed."""
    guessed = calibratable_cameras(model.cameras, model.camera_of, single)
    if not guessed:
        return {}
    Fs, used = [], dict.fromkeys(guessed, 0)
    for (a, b), matches in sorted(pairs.items(), key=lambda kv: -len(kv[1])):
        ca, cb = int(model.camera_of[a]), int(model.camera_of[b])
        mine = [c for c in (ca, cb) if c in guessed and used[c] < _CALIBRATION_PAIRS]
        if mine and len(matches) >= 4 * MIN_RELATIVE_INLIERS:
            for c in set(mine):
                used[c] += 1
            F = _fundamental(model, a, b, sample_matches(matches, seed))
            if F is not None:
                Fs.append((ca, cb, F / np.linalg.norm(F)))
    changed = {}
    base = {c: model.cameras[c].focal() for c in guessed}
    for _ in range(_CALIBRATION_SWEEPS):
        moved = False
        for c in sorted(guessed):
            mine = [(ca, cb, F) for ca, cb, F in Fs if c in (ca, cb)]
            if not mine:
                continue
            cost = np.zeros(len(_SCALES))
            for ca, cb, F in mine:
                Ks = []
                for other in (ca, cb):
                    K = np.broadcast_to(model.cameras[other].K(), (len(_SCALES), 3, 3)).copy()
                    if other == c:
                        K[:, :2, :2] *= (base[c] * _SCALES / model.cameras[c].focal())[:, None, None]
                    Ks.append(K)
                cost += np.minimum(_essential_costs(F, Ks[0], Ks[1]), 0.5)
            best = int(np.argmin(cost))
            if not _EDGE <= best < len(_SCALES) - _EDGE or cost[best] > _SHARPNESS * min(cost[0], cost[-1]):
                continue  # no clear minimum inside the range: the pairs do not observe the focal (an orbit)
            focal = float(base[c] * _SCALES[best])
            if abs(focal / model.cameras[c].focal() - 1) > 1e-3:
                model.cameras[c].set_focal(focal)
                changed[c] = (base[c], focal)
                moved = True
        if not moved:
            break
    for c, (guess, focal) in changed.items():
        log.info("camera %d: focal %.1f px from the view graph (guessed %.1f)", c, focal, guess)
    return changed


def calibration_shift_px(before: Camera, after: Camera, grid: int = 9) -> float:
    """The largest distance (pixels) between where `before` and `after` project the rays that `before` sees at a
    grid of points over the image: how far a change of calibration moves the matches a pair's pose is fit to."""
    u, v = np.meshgrid(np.linspace(0, before.width, grid), np.linspace(0, before.height, grid))
    uv = np.c_[u.ravel(), v.ravel()]
    xy = cammodel.pixels_to_normalized(before.model, before.params, uv)
    moved = cammodel.project(after.model, after.params, np.c_[xy, np.ones(len(xy))])
    shift = np.linalg.norm(moved - uv, axis=1)
    return float(np.nanmax(shift)) if np.isfinite(shift).any() else float("inf")


def matches_per_image(pairs: dict, n: int) -> np.ndarray:
    """(n,) verified matches of each image over all its pairs."""
    total = np.zeros(n)
    for (a, b), matches in pairs.items():
        total[a] += len(matches)
        total[b] += len(matches)
    return total


def dense_subset(pairs: dict, n: int, size: int, seeds: Iterable[int] = ()) -> np.ndarray:
    """(n,) mask of a well-connected set of about `size` images per seed: from the image with the most verified
    matches (or each of `seeds`), the image outside with the most matches into the set is added, in turn. The
    coarse models that calibrate a guessed focal are built on it, so that their cost does not grow with the
    images (a 300-image survey calibrates from 60 of them, as well as a 60-image set from all)."""
    neighbours = [[] for _ in range(n)]
    for (a, b), matches in pairs.items():
        neighbours[a].append((b, len(matches)))
        neighbours[b].append((a, len(matches)))
    total = matches_per_image(pairs, n)
    inside = np.zeros(n, bool)
    for seed in list(seeds) or [int(np.argmax(total))]:
        score = np.full(n, -1.0)
        score[seed] = 0.0
        for _ in range(size):
            score[inside] = -1.0
            best = int(np.argmax(score))
            if score[best] < 0:
                break
            inside[best] = True
            for other, count in neighbours[best]:
                if not inside[other]:
                    score[other] = max(score[other], 0.0) + count
    return inside
