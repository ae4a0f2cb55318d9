"""The relative pose of each verified pair of the global mapper's view graph, at the cameras' current calibration.

`relative_poses` estimates each pair's relative pose from its matches in normalised coordinates (five-point
RANSAC, then Levenberg-Marquardt on the inliers' Sampson distances), with the median triangulation angle of its
inliers; a pair where a rotation about the camera centre explains `_ROTATION_SHARE` as many of its matches as its
essential matrix does (a camera turning in place; the share is COLMAP's max_H_inlier_ratio, since an epipolar
distance is one-dimensional and a rotation's two) gives that rotation and no translation direction.
"""

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..executor import WorkerPool
from ..geometry.triangulation import triangulation_angle_deg, two_view_midpoints
from ..geometry.two_view import essential_matrix, pose_from_essential, rotation_between_views
from .config import MapperConfig
from .model import Reconstruction
from .view_graph import MIN_RELATIVE_INLIERS, SAMPLE, sample_matches

COARSE_SAMPLE = 300  # matches of a pair of the coarse models that calibrate a focal
_ROTATION_SHARE = 0.8  # a pair is a rotation where one explains this share of its essential matrix's inliers
_PARALLEL_PAIRS = 200  # pairs from which `relative_poses` hands them to worker processes


@dataclass
class ViewEdge:
    """A pair's relative pose: x2 = R x1 + t in camera coordinates (|t| = 1), from `inliers` matches."""

    R: np.ndarray
    t: np.ndarray
    inliers: int
    angle_deg: float  # median triangulation angle of the inliers (0: a rotation); below the minimum `t` is not used


@dataclass
class ViewGraph:
    edges: dict  # (a, b) internal image indices, a < b -> ViewEdge
    rejected: dict  # (a, b) -> why the pair gave no edge


def relative_poses(model: Reconstruction, pairs: dict, config: MapperConfig, sample: int = SAMPLE,
                   workers: int = 1) -> ViewGraph:
    """The relative pose of each pair at the model's current calibration (see the module docstring), from at
    most `sample` of its matches, in `workers` processes (executor.WorkerPool) when there are enough pairs: a
    pair costs milliseconds of CPU, and a 1,000-image survey has over 10,000 of them."""
    keys, jobs = [], []
    for (a, b), matches in sorted(pairs.items()):
        matches = sample_matches(matches, config.seed, sample)
        x1, x2 = model.normalized_keypoints(a)[matches[:, 0]], model.normalized_keypoints(b)[matches[:, 1]]
        ok = np.isfinite(x1).all(axis=1) & np.isfinite(x2).all(axis=1)
        f = 0.5 * (model.camera(a).focal() + model.camera(b).focal())
        keys.append((a, b))
        jobs.append((x1[ok], x2[ok], len(matches), config.two_view_max_error_px / f))
    if workers > 1 and len(jobs) >= _PARALLEL_PAIRS:
        step = -(-len(jobs) // (4 * workers))  # a few chunks per worker: even loads, little pickling
        chunks = [(jobs[k:k + step], config.seed) for k in range(0, len(jobs), step)]
        with WorkerPool(workers) as pool:
            found = [edge for chunk in pool.map(_pair_poses, chunks) for edge in chunk]
    else:
        found = _pair_poses((jobs, config.seed))
    edges, rejected = {}, {}
    for key, edge in zip(keys, found):
        if isinstance(edge, ViewEdge):
            edges[key] = edge
        else:
            rejected[key] = edge
    return ViewGraph(edges, rejected)


def _pair_poses(chunk: tuple[list, int]) -> list:
    """A ViewEdge, or the reason there is none, for each (x1, x2, matches, threshold) of the chunk (jobs, seed)."""
    jobs, seed = chunk
    return [_pair_pose(x1, x2, count, threshold, seed) for x1, x2, count, threshold in jobs]


def _pair_pose(x1: np.ndarray, x2: np.ndarray, count: int, threshold: float, seed: int) -> "ViewEdge | str":
    essential = essential_matrix(x1, x2, threshold, seed)
    fit = 0 if essential is None else int(essential[1].sum())  # before cheirality, which a turn leaves to chance
    share = int(np.ceil(_ROTATION_SHARE * fit))
    # the least count that decides anything below: `share` where the pair may be refused as no baseline, else a
    # rotation edge's MIN_RELATIVE_INLIERS; RANSAC's samples follow it, so a pair with a baseline, whose best
    # rotation explains few of its matches, takes one chunk of draws, not 200 (docs/benchmarks.md, "The view
    # graph: a rotation test as long as its decision needs")
    least = share if fit >= MIN_RELATIVE_INLIERS else MIN_RELATIVE_INLIERS
    turn = rotation_between_views(x1, x2, threshold, seed, min_inliers=least)
    turned = 0 if turn is None else int(turn[1].sum())
    if turned >= max(share, MIN_RELATIVE_INLIERS):
        return ViewEdge(turn[0], np.zeros(3), turned, 0.0)  # a rotation about the camera centre
    if fit >= MIN_RELATIVE_INLIERS and turned >= share:
        return (f"no baseline: a rotation about the camera centre explains {turned} of its {count} matches, "
                f"{_ROTATION_SHARE:.0%} or more of its essential matrix's {fit}, and < {MIN_RELATIVE_INLIERS}")
    est = None if essential is None else pose_from_essential(essential[0], x1, x2, essential[1])
    found = 0 if est is None else int(est[2].sum())
    if found < MIN_RELATIVE_INLIERS:
        return (f"{found} of its {count} matches fit a relative pose in front of both views, "
                f"< {MIN_RELATIVE_INLIERS}")
    R, t, inl = est
    R, t = refine_relative_pose(R, t, x1[inl], x2[inl])
    X = two_view_midpoints(R, t, x1[inl], x2[inl])  # the angle needs no refined points
    front = np.isfinite(X).all(axis=1)
    front[front] = (X[front, 2] > 0) & (X[front] @ R[2] + t[2] > 0)
    angle = float(np.median(triangulation_angle_deg(np.zeros(3), -R.T @ t, X[front]))) if front.any() else 0.0
    return ViewEdge(R, t, found, angle)


def refine_relative_pose(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                         iterations: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) refined by Levenberg-Marquardt on the Sampson distances of the inlier matches (normalised
    coordinates): the five-point RANSAC's pose comes from a minimal sample, and with a narrow field of view it
    can be degrees off (templeSparseRing, 24 deg across: pairs of 150-200 matches 10 deg off in rotation).
    Five unknowns (a rotation applied on the left, the direction turned with |t| held at 1), the Jacobian in
    closed form, compiled: the view graph refines thousands of pairs, and a pose far off in a narrow view
    follows a long narrow valley of the cost for hundreds of iterations."""
    if len(x1) < 6:
        return R, t
    R, t = _refine_pose(np.ascontiguousarray(R, np.float64), np.asarray(t, np.float64).copy(),
                        np.ascontiguousarray(x1, np.float64), np.ascontiguousarray(x2, np.float64), iterations)
    return R, t


@njit(cache=True, nogil=True)
def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@njit(cache=True, nogil=True)
def _rodrigues(w):
    theta = np.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
    if theta < 1e-12:
        return np.eye(3) + _skew(w)
    K = _skew(w / theta)
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


@njit(cache=True, nogil=True)
def _sampson_system(R, t, basis, x1, x2, jacobian):
    """Sum of squared Sampson distances under E = [t]x R and, with `jacobian`, the normal equations (J^T J, J^T r)
    of the five unknowns: rotations about x, y and z applied on the left, and moves of t along `basis`' rows."""
    E = _skew(t) @ R
    dE = np.zeros((5, 3, 3))  # E's change along each unknown
    for k in range(3 if jacobian else 0):
        axis = np.zeros(3)
        axis[k] = 1.0
        dE[k] = _skew(t) @ _skew(axis) @ R
        if k < 2:
            dE[3 + k] = _skew(basis[k]) @ R
    cost, A, g, J = 0.0, np.zeros((5, 5)), np.zeros(5), np.empty(5)
    e1, e2, d1, d2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for n in range(x1.shape[0]):
        u1, v1, u2, v2 = x1[n, 0], x1[n, 1], x2[n, 0], x2[n, 1]
        for i in range(3):
            e1[i] = E[i, 0] * u1 + E[i, 1] * v1 + E[i, 2]  # E h1
            e2[i] = E[0, i] * u2 + E[1, i] * v2 + E[2, i]  # E^T h2
        den = e1[0] ** 2 + e1[1] ** 2 + e2[0] ** 2 + e2[1] ** 2 + 1e-300
        root = np.sqrt(den)
        r = (u2 * e1[0] + v2 * e1[1] + e1[2]) / root
        cost += r * r
        if not jacobian:
            continue
        for k in range(5):
            D = dE[k]
            for i in range(3):
                d1[i] = D[i, 0] * u1 + D[i, 1] * v1 + D[i, 2]
                d2[i] = D[0, i] * u2 + D[1, i] * v2 + D[2, i]
            dnum = u2 * d1[0] + v2 * d1[1] + d1[2]
            dden = 2.0 * (e1[0] * d1[0] + e1[1] * d1[1] + e2[0] * d2[0] + e2[1] * d2[1])
            J[k] = dnum / root - 0.5 * r / den * dden
        for i in range(5):
            g[i] += J[i] * r
            for j in range(5):
                A[i, j] += J[i] * J[j]
    return cost, A, g


@njit(cache=True, nogil=True)
def _refine_pose(R, t, x1, x2, iterations):
    """`refine_relative_pose`'s iterations: Marquardt's damping of the normal equations' diagonal, each step
    taken only where it lowers the cost, until a step lowers it by under 1e-10 of itself."""
    t = t / np.linalg.norm(t)
    basis = np.zeros((2, 3))
    cost = _sampson_system(R, t, basis, x1, x2, False)[0]
    damping = 1e-3
    for _ in range(iterations):
        axis = np.zeros(3)
        axis[np.argmin(np.abs(t))] = 1.0
        basis[0] = np.cross(t, axis)
        basis[0] /= np.linalg.norm(basis[0])
        basis[1] = np.cross(t, basis[0])
        _, A, g = _sampson_system(R, t, basis, x1, x2, True)
        improved = False
        while damping < 1e8:
            step = np.linalg.solve(A + damping * np.diag(np.diag(A) + 1e-12), -g)
            Rn = _rodrigues(step[:3]) @ R
            tn = t + basis[0] * step[3] + basis[1] * step[4]
            tn /= np.linalg.norm(tn)
            new = _sampson_system(Rn, tn, basis, x1, x2, False)[0]
            if new <= cost:
                improved = True
                break
            damping *= 10.0
        if not improved:
            break  # no step lowers the cost: a minimum
        done = cost - new <= 1e-10 * cost or np.abs(step).max() < 1e-12
        R, t, cost, damping = Rn, tn, new, max(damping / 10.0, 1e-9)
        if done:
            break
    return R, t
