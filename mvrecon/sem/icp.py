"""Rigid ICP for merging the point sets of different image pairs: KD-tree and brute-force neighbour search.

The seed paper compares a KD-tree ICP with a brute-force one in time and iterations. Here both run the same
loop and the same rigid fit (`umeyama(with_scale=False)`); only the nearest-neighbour search differs, so on the
same data they take the same steps and reach the same transform, and the timing difference is the search alone:
brute force compares every source point with every target point, O(N*M) per iteration, while a KD-tree query
costs O(log M) per point, O(N log M) per iteration (plus O(M log M) once to build the tree).
Open3D's own point-to-point and point-to-plane ICP (`registration_icp`) are offered next to them.
"""

import time
from dataclasses import dataclass

import numpy as np

from ..geometry.sim3 import umeyama
from ..interrupts import import_open3d

METHODS = ("kdtree", "brute", "open3d-point", "open3d-plane")


@dataclass(frozen=True)
class IcpConfig:
    """max_iterations: cap on rigid-fit steps. tolerance: stop when the RMS changes by less than this fraction
    (or is at rounding level, 1e-12 of the target's extent: an exact fit).
    max_distance: pairs farther apart than this (point units) are ignored, which keeps non-overlapping parts of
    two point sets from pulling the fit (inf: use all). chunk_elements: brute-force distance block size
    (query rows x target points): 8 bytes per element, small enough to stay in cache."""

    max_iterations: int = 100
    tolerance: float = 1e-10
    max_distance: float = np.inf
    chunk_elements: int = 2_000_000


@dataclass(frozen=True)
class IcpResult:
    """matrix: 4x4 rigid transform taking the source onto the target. rms: over the pairs used, last step."""

    matrix: np.ndarray
    iterations: int
    rms: float
    pairs: int
    seconds: float
    method: str

    def apply(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=float) @ self.matrix[:3, :3].T + self.matrix[:3, 3]


def nearest_brute_force(queries: np.ndarray, targets: np.ndarray,
                        chunk_elements: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
    """(index, distance) of each query's nearest target by exhaustive comparison: O(N*M), float64.

    |q - t|^2 = |q|^2 - 2 q.t + |t|^2, and |q|^2 does not change a row's argmin, so one matrix product of
    [q, 1] (N,4) with [-2 t, |t|^2] (4,M) gives every comparison in one pass. Blocks of about `chunk_elements`
    distances (16 MB) stay near the cache: with the one-pass product, measured 6x faster than the earlier 64 MB
    blocks of separate products, with the same neighbours.
    """
    queries, targets = np.asarray(queries, dtype=float), np.asarray(targets, dtype=float)
    lifted = np.ascontiguousarray(np.vstack([-2.0 * targets.T, np.einsum("ij,ij->i", targets, targets)]))
    rows = max(1, chunk_elements // max(1, len(targets)))
    index = np.empty(len(queries), dtype=np.int64)
    for s in range(0, len(queries), rows):
        q = queries[s:s + rows]
        index[s:s + rows] = np.argmin(np.hstack([q, np.ones((len(q), 1))]) @ lifted, axis=1)
    return index, np.linalg.norm(targets[index] - queries, axis=1)


class KDTreeSearch:
    """Open3D's KD-tree (nanoflann) over the target points, built once and queried every iteration."""

    def __init__(self, targets: np.ndarray):
        o3d = import_open3d()

        self._o3d = o3d
        self._nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(targets, dtype=float)))
        self._nns.knn_index()

    def __call__(self, queries) -> tuple[np.ndarray, np.ndarray]:
        idx, d2 = self._nns.knn_search(self._o3d.core.Tensor(np.ascontiguousarray(queries, dtype=float)), 1)
        return idx.numpy()[:, 0].astype(np.int64), np.sqrt(d2.numpy()[:, 0])


def icp(source: np.ndarray, target: np.ndarray, method: str = "kdtree", config: IcpConfig = IcpConfig(),
        init: np.ndarray | None = None) -> IcpResult:
    """Rigid transform taking `source` (N,3) onto `target` (M,3) by iterated closest points."""
    if method not in METHODS:
        raise ValueError(f"unknown ICP method {method!r}; expected one of {', '.join(METHODS)}")
    source, target = np.asarray(source, dtype=float), np.asarray(target, dtype=float)
    if len(source) < 3 or len(target) < 3:
        raise ValueError(f"ICP needs at least 3 points in each set, got {len(source)} and {len(target)}")
    start = time.perf_counter()
    M0 = np.eye(4) if init is None else np.asarray(init, dtype=float)
    if method.startswith("open3d"):
        matrix, iterations, rms, pairs = _open3d_icp(source, target, method, config, M0)
        return IcpResult(matrix, iterations, rms, pairs, time.perf_counter() - start, method)
    search = KDTreeSearch(target) if method == "kdtree" else (
        lambda q: nearest_brute_force(q, target, config.chunk_elements))
    M, prev_rms, rms, pairs, it = M0.copy(), np.inf, np.inf, 0, 0
    exact = 1e-12 * float(np.linalg.norm(np.ptp(target, axis=0)))  # an exact fit: relative changes are just noise
    for it in range(1, config.max_iterations + 1):
        moved = source @ M[:3, :3].T + M[:3, 3]
        index, dist = search(moved)
        near = dist <= config.max_distance
        pairs = int(near.sum())
        if pairs < 3:
            raise ValueError(f"ICP lost overlap: {pairs} point pairs within {config.max_distance}")
        rms = float(np.sqrt(np.mean(dist[near] ** 2)))
        step = umeyama(moved[near], target[index[near]], with_scale=False)
        M = step.matrix() @ M
        if abs(prev_rms - rms) <= config.tolerance * max(rms, 1e-300) or rms <= exact:
            break
        prev_rms = rms
    return IcpResult(M, it, rms, pairs, time.perf_counter() - start, method)


def _open3d_icp(source, target, method, config: IcpConfig, init):
    o3d = import_open3d()

    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    extent = float(np.linalg.norm(np.ptp(target, axis=0)))
    max_distance = config.max_distance if np.isfinite(config.max_distance) else extent
    if method == "open3d-plane":
        spacing = np.mean(np.asarray(dst.compute_nearest_neighbor_distance()))
        dst.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=10 * spacing, max_nn=30))
        estimation = reg.TransformationEstimationPointToPlane()
    else:
        estimation = reg.TransformationEstimationPointToPoint()
    criteria = reg.ICPConvergenceCriteria(relative_fitness=config.tolerance, relative_rmse=config.tolerance,
                                          max_iteration=config.max_iterations)
    result = reg.registration_icp(src, dst, max_distance, init, estimation, criteria)
    # Open3D does not report its iteration count: -1 marks it as unknown
    return np.asarray(result.transformation), -1, float(result.inlier_rmse), len(result.correspondence_set)
