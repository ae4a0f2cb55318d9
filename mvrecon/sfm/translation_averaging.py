"""Translation averaging of the global mapper: camera centres from the directions between them.

Input: the world-frame direction from camera i to camera j of each edge (the pair's translation direction turned
by the averaged rotations). Outlier directions are removed with `gtsam.MFAS` (1DSfM: each projection direction
orders the cameras along a line, the edges that disagree with the order get weight; an edge whose mean weight
over the projections exceeds a threshold is an outlier). The centres then come from `gtsam.TranslationRecovery`
on the kept directions, started from a linear estimate (the centres that make every baseline most parallel to
its direction, scale fixed by the sum of squares): the nonlinear problem started from random centres stalled in
poor minima on orbits.
"""

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import eigsh

from .rotation_averaging import components

_PROJECTIONS = 48
_REFITS = 2
_MIN_GATE_DEG = 1.0  # the refits drop directions over 4x the median error, at least this and at most the maximum
_MFAS_MAX_WEIGHT = 0.1  # 1DSfM's threshold on an edge's mean outlier weight


@dataclass
class PositionResult:
    centers: np.ndarray  # (n,3) camera centres, NaN for images outside `solved`
    solved: np.ndarray  # (n,) bool: the largest component of the kept directions
    inliers: np.ndarray  # (m,) bool: the directions kept


def mfas_inliers(ij: np.ndarray, directions: np.ndarray, seed: int = 0) -> np.ndarray:
    """Edges whose direction MFAS does not mark as an outlier: mean outlier weight over `_PROJECTIONS`
    projection directions (sampled among the edges' own directions, as 1DSfM does) under `_MFAS_MAX_WEIGHT`."""
    if len(ij) < 3:
        return np.ones(len(ij), bool)
    rng = np.random.default_rng(seed)
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    measurements = [gtsam.BinaryMeasurementUnit3(int(a), int(b), gtsam.Unit3(d), noise)
                    for (a, b), d in zip(ij.tolist(), directions)]
    picks = rng.choice(len(ij), min(_PROJECTIONS, len(ij)), replace=False)
    total = np.zeros(len(ij))
    index = {(int(a), int(b)): k for k, (a, b) in enumerate(ij.tolist())}
    for k in picks.tolist():
        weights = gtsam.MFAS(measurements, gtsam.Unit3(directions[k])).computeOutlierWeights()
        for key, w in weights.items():
            total[index[key]] += w
    return total / len(picks) < _MFAS_MAX_WEIGHT


def linear_centers(n: int, ij: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Centres minimising sum |(I - d d^T)(C_j - C_i)|^2 with sum C = 0 and sum |C|^2 = 1: the eigenvector of the
    smallest eigenvalue past the three of the common translation. Connected nodes only; a start, not a result."""
    m = len(ij)
    P = np.eye(3)[None] - np.einsum("mi,mj->mij", directions, directions)
    a, b = 3 * ij[:, 0], 3 * ij[:, 1]
    rows, cols, data = [], [], []
    for (r0, c0, sign) in ((a, a, 1.0), (b, b, 1.0), (a, b, -1.0), (b, a, -1.0)):
        for p in range(3):
            for q in range(3):
                rows.append(r0 + p)
                cols.append(c0 + q)
                data.append(sign * P[:, p, q])
    L = coo_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, 3 * n))
    L = L.tocsr()
    # the translations span the null space: push them up so that the smallest eigenvector is a real solution
    T = np.tile(np.eye(3), (n, 1)) / np.sqrt(n)
    if 3 * n <= 600:
        dense = L.toarray() + 10.0 * m * T @ T.T
        return np.linalg.eigh(dense)[1][:, 0].reshape(n, 3)
    shifted = L + coo_matrix(10.0 * m * T @ T.T)
    return eigsh(shifted, k=1, sigma=-1e-6, which="LM")[1][:, 0].reshape(n, 3)


def recover_centers(n: int, ij: np.ndarray, directions: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """`gtsam.TranslationRecovery` of centres from the unit directions (i -> j, world frame), from `initial`."""
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(0.1),
                                           gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    measurements = [gtsam.BinaryMeasurementUnit3(int(a), int(b), gtsam.Unit3(d), noise)
                    for (a, b), d in zip(ij.tolist(), directions)]
    values = gtsam.Values()
    for i in range(n):
        values.insert(i, gtsam.Point3(*initial[i]))
    scale = float(np.linalg.norm(initial[ij[0, 1]] - initial[ij[0, 0]]))
    result = gtsam.TranslationRecovery().run(measurements, scale, [], values)
    return np.array([result.atPoint3(i) for i in range(n)])


def average_translations(n: int, ij: np.ndarray, directions: np.ndarray, max_error_deg: float = 10.0,
                         seed: int = 0) -> PositionResult:
    """Centres of the largest component the MFAS-kept directions connect (edges ij (m,2); `directions` (m,3):
    unit world-frame direction from camera i to camera j). After the first solution, directions more than
    4x the median error off their baseline (between 1 deg and `max_error_deg`) are dropped and the centres solved
    again (up to `_REFITS` times)."""
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    directions = np.asarray(directions, dtype=float).reshape(-1, 3)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    centers = np.full((n, 3), np.nan)
    if len(ij) == 0:
        return PositionResult(centers, np.zeros(n, bool), np.zeros(0, bool))
    inliers = mfas_inliers(ij, directions, seed)
    labels = components(n, ij[inliers])
    used = np.unique(ij[inliers])
    main = int(np.argmax(np.bincount(labels[used]))) if len(used) else -1
    solved = labels == main
    inliers &= solved[ij[:, 0]]
    nodes = np.flatnonzero(solved)
    if len(nodes) < 2:
        return PositionResult(centers, np.zeros(n, bool), inliers)
    local = np.full(n, -1)
    local[nodes] = np.arange(len(nodes))
    sub, d = local[ij[inliers]], directions[inliers]
    start = linear_centers(len(nodes), sub, d)
    if np.mean(np.einsum("mi,mi->m", start[sub[:, 1]] - start[sub[:, 0]], d)) < 0:
        start = -start  # the eigenvector's sign is arbitrary: most baselines must point along their directions
    found = recover_centers(len(nodes), sub, d, start)
    for _ in range(_REFITS):  # directions the centres disagree with are outliers MFAS's projections missed
        err = direction_errors_deg(found, sub, d)
        good = err < min(max_error_deg, max(_MIN_GATE_DEG, 4 * float(np.median(err))))
        if good.all() or len(np.unique(sub[good])) < len(nodes) or components(len(nodes), sub[good]).max() > 0:
            break
        kept = np.flatnonzero(inliers)
        inliers[kept[~good]] = False
        sub, d = sub[good], d[good]
        found = recover_centers(len(nodes), sub, d, found)
    centers[nodes] = found
    return PositionResult(centers, solved, inliers)


def direction_errors_deg(centers: np.ndarray, ij: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Angle (deg) between each edge's baseline C_j - C_i and its measured direction."""
    base = centers[ij[:, 1]] - centers[ij[:, 0]]
    cos = np.einsum("mi,mi->m", base, directions) / np.maximum(np.linalg.norm(base, axis=1), 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
