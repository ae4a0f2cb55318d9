"""Rotation averaging of the global mapper: one rotation per image from the view graph's relative rotations.

Conventions: rotations are COLMAP's cam_from_world R_i; an edge (i, j, R_ij) says R_j = R_ij R_i. Three steps:
1. Robust initialisation: rotations chained along spanning trees of the graph (the maximum one by weight, then
   random ones), keeping the tree whose rotations agree with most edges within the threshold (a RANSAC over
   trees: one wrong edge in a tree spoils a branch, but not every tree holds one).
2. Iteratively reweighted least squares in the tangent space (Chatterjee and Govindu's L1-IRLS), then the edges
   whose residual exceeds the threshold are removed as outliers (GLOMAP's 5 degrees).
3. `gtsam.ShonanAveraging3` on the edges kept, started from step 2: the certifiably optimal chordal average (its
   local optimum where no rank is certified).
Edges are removed again by their residuals afterwards, and the images the kept edges no longer connect to the
largest component are left to other components.
"""

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.sparse.linalg import spsolve

from ..geometry.rotation import angle_axis_to_rotmat

_RANDOM_TREES = 20
_IRLS_ITERATIONS = 12


@dataclass
class RotationResult:
    R: np.ndarray  # (n,3,3) cam_from_world; identity for images outside `solved`
    solved: np.ndarray  # (n,) bool: images whose rotation was averaged (the component of `root`)
    inliers: np.ndarray  # (m,) bool: edges consistent with the rotations


def edge_residuals_deg(R: np.ndarray, ij: np.ndarray, Rij: np.ndarray) -> np.ndarray:
    """Angle (deg) of R_ij R_i R_j^T per edge: 0 when the rotations agree with the edge."""
    M = np.einsum("mab,mbc,mdc->mad", Rij, R[ij[:, 0]], R[ij[:, 1]])
    c = np.clip((np.trace(M, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return np.degrees(np.arccos(c))


def components(n: int, ij: np.ndarray) -> np.ndarray:
    """Connected-component label of each of n nodes joined by the edges ij (m,2)."""
    if len(ij) == 0:
        return np.arange(n)
    g = coo_matrix((np.ones(len(ij)), (ij[:, 0], ij[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def _chain(n, ij, Rij, tree_edges, root) -> np.ndarray:
    """Rotations chained from `root` (identity) along the given edges of a spanning tree."""
    sub = ij[tree_edges]
    g = csr_matrix((np.arange(1, len(sub) + 1), (sub[:, 0], sub[:, 1])), shape=(n, n))
    order, parent = breadth_first_order(g, root, directed=False)
    lookup = {}
    for k, (a, b) in zip(tree_edges.tolist(), sub.tolist()):
        lookup[(a, b)] = (k, False)
        lookup[(b, a)] = (k, True)
    R = np.tile(np.eye(3), (n, 1, 1))
    for node in order[1:].tolist():
        p = int(parent[node])
        k, backwards = lookup[(p, node)]
        R[node] = (Rij[k].T if backwards else Rij[k]) @ R[p]  # R_j = R_ij R_i, R_i = R_ij^T R_j
    return R


def _tree(n, ij, weights) -> np.ndarray:
    """Edge indices of a maximum spanning tree (forest) for the given positive weights."""
    w = 1.0 / np.maximum(weights, 1e-9)
    g = coo_matrix((w, (ij[:, 0], ij[:, 1])), shape=(n, n)).tocsr()
    t = minimum_spanning_tree(g).tocoo()
    index = {(a, b): k for k, (a, b) in enumerate(ij.tolist())}
    return np.array([index.get((a, b), index.get((b, a))) for a, b in zip(t.row.tolist(), t.col.tolist())],
                    dtype=np.int64)


def initial_rotations(n: int, ij: np.ndarray, Rij: np.ndarray, weights: np.ndarray, root: int,
                      max_error_deg: float, seed: int = 0) -> np.ndarray:
    """Rotations of the spanning tree (maximum by weight, or one of `_RANDOM_TREES` random ones) whose chained
    rotations agree with the most edges within `max_error_deg`, weighted."""
    rng = np.random.default_rng(seed)
    best, best_score = None, -1.0
    for k in range(_RANDOM_TREES + 1):
        w = weights if k == 0 else weights * rng.uniform(0.05, 1.0, len(weights))
        R = _chain(n, ij, Rij, _tree(n, ij, w), root)
        score = float(weights[edge_residuals_deg(R, ij, Rij) < max_error_deg].sum())
        if score > best_score:
            best, best_score = R, score
    return best


def _irls(R, ij, Rij, weights, root: int, iterations: int = _IRLS_ITERATIONS) -> np.ndarray:
    """L1-IRLS refinement: each iteration solves R_ij w_i - w_j = -log(R_ij R_i R_j^T) for tangent updates
    w (R_i <- exp(w_i) R_i) in weighted least squares, each edge weighted by 1 / |its residual| (an L1 cost),
    with the root held."""
    n, m = len(R), len(ij)
    rows = np.repeat(np.arange(3 * m), 3).reshape(m, 3, 3)
    for _ in range(iterations):
        r = _log(np.einsum("mab,mbc,mdc->mad", Rij, R[ij[:, 0]], R[ij[:, 1]]))
        norm = np.linalg.norm(r, axis=1)
        w = weights / np.maximum(norm, 1e-4)
        cols_i = np.broadcast_to(3 * ij[:, 0, None, None] + np.arange(3)[None, None, :], (m, 3, 3)).ravel()
        cols_j = np.broadcast_to(3 * ij[:, 1, None, None] + np.arange(3)[None, None, :], (m, 3, 3)).ravel()
        sw = np.sqrt(w)[:, None, None]
        data = np.concatenate([(Rij * sw).ravel(), np.broadcast_to(-np.eye(3) * sw, (m, 3, 3)).ravel()])
        A = coo_matrix((data, (np.r_[rows.ravel(), rows.ravel()], np.r_[cols_i, cols_j])), shape=(3 * m, 3 * n))
        A = A.tocsc()
        keep = np.ones(3 * n, bool)
        keep[3 * root:3 * root + 3] = False
        A = A[:, np.flatnonzero(keep)]
        b = -(r * np.sqrt(w)[:, None]).ravel()
        x = np.zeros(3 * n)
        x[keep] = spsolve((A.T @ A).tocsc(), A.T @ b)
        step = x.reshape(n, 3)
        R = np.einsum("nab,nbc->nac", np.array([angle_axis_to_rotmat(s) for s in step]), R)
        if np.abs(step).max() < 1e-9:
            break
    return R


def _log(M) -> np.ndarray:
    """Rotation vectors (m,3) of rotation matrices (m,3,3)."""
    c = np.clip((np.trace(M, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(c)
    v = np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], axis=1)
    s = np.sin(angle)
    scale = np.where(s > 1e-9, angle / (2 * np.where(s > 1e-9, s, 1.0)), 0.5)
    out = v * scale[:, None]
    near_pi = angle > np.pi - 1e-3  # the skew part vanishes there: the axis from the symmetric part
    for k in np.flatnonzero(near_pi):
        B = (M[k] + np.eye(3)) / 2
        axis = B[np.argmax(np.diag(B))]
        out[k] = angle[k] * axis / np.linalg.norm(axis)
    return out


def shonan(R: np.ndarray, ij: np.ndarray, Rij: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """`gtsam.ShonanAveraging3` over `nodes` (indices into R) and the edges ij among them, started from R;
    returns R with those nodes replaced. GTSAM's measurement between world_from_camera rotations of i and j is
    R_i R_j^T = R_ij^T. Where no rank up to 6 is certified optimal, the local optimum at rank 3 is returned
    instead of GTSAM's error: along a street, each image paired with its few neighbours, pairs a degree or two
    off leave the relaxation loose, and a 100-frame street failed there with no model (docs/benchmarks.md,
    "Rotation averaging: the local optimum where Shonan certifies none")."""
    key = {int(v): k for k, v in enumerate(nodes.tolist())}
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    measurements = [gtsam.BinaryMeasurementRot3(key[int(a)], key[int(b)], gtsam.Rot3(Rij[k].T), noise)
                    for k, (a, b) in enumerate(ij.tolist())]
    params = gtsam.ShonanAveragingParameters3(gtsam.LevenbergMarquardtParams.CeresDefaults())
    params.setCertifyOptimality(True)
    averaging = gtsam.ShonanAveraging3(measurements, params)
    initial = gtsam.Values()
    for v, k in key.items():
        initial.insert(k, gtsam.Rot3(R[v].T))
    try:
        result, _ = averaging.run(initial, 3, 6)
    except RuntimeError:  # no rank up to 6 certified: the local optimum at rank 3, as without the certificate
        params.setCertifyOptimality(False)
        result, _ = gtsam.ShonanAveraging3(measurements, params).run(initial, 3, 3)
    out = R.copy()
    for v, k in key.items():
        out[v] = np.asarray(result.atRot3(k).matrix()).T
    return out


def _largest(n: int, ij) -> np.ndarray:
    """Mask of the nodes of the largest connected component (by nodes) of the edges ij."""
    labels = components(n, ij)
    return labels == int(np.argmax(np.bincount(labels[np.unique(ij)])))


def _solve(R, ij, Rij, weights, nodes, solver) -> np.ndarray:
    """R with the rotations of `nodes` (a mask) replaced by `solver(R_sub, ij_sub, Rij, weights)` run on the
    edges among them in the nodes' own numbering (so that no node without an edge makes the problem singular)."""
    local = np.full(len(R), -1)
    local[nodes] = np.arange(int(nodes.sum()))
    keep = nodes[ij[:, 0]] & nodes[ij[:, 1]]
    out = R.copy()
    out[nodes] = solver(R[nodes], local[ij[keep]], Rij[keep], weights[keep])
    return out


def average_rotations(n: int, ij: np.ndarray, Rij: np.ndarray, weights: np.ndarray,
                      max_error_deg: float = 5.0, seed: int = 0) -> RotationResult:
    """Rotations of the largest component of the view graph (n images, edges ij (m,2) with R_j = R_ij R_i and
    positive `weights`), with the outlier edges found on the way (see the module docstring)."""
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    Rij = np.asarray(Rij, dtype=float).reshape(-1, 3, 3)
    weights = np.asarray(weights, dtype=float)
    inliers = np.ones(len(ij), bool)
    R = np.tile(np.eye(3), (n, 1, 1))
    solved = np.zeros(n, bool)
    if len(ij) == 0:
        return RotationResult(R, solved, inliers)
    solved = _largest(n, ij)
    # the IRLS sees every edge of the component: its L1 cost outvotes the wrong edges a tree may hold
    R = _solve(R, ij, Rij, weights, solved, lambda r, e, sub, sw: _irls(
        initial_rotations(len(r), e, sub, sw, 0, max_error_deg, seed), e, sub, sw, 0))
    inliers = solved[ij[:, 0]] & (edge_residuals_deg(R, ij, Rij) < max_error_deg)
    if inliers.any():
        solved = _largest(n, ij[inliers])
        inliers &= solved[ij[:, 0]]
        R = _solve(R, ij[inliers], Rij[inliers], weights[inliers], solved,
                   lambda r, e, sub, sw: shonan(r, e, sub, np.arange(len(r))))
        inliers = solved[ij[:, 0]] & (edge_residuals_deg(R, ij, Rij) < max_error_deg)
        solved = _largest(n, ij[inliers]) if inliers.any() else np.zeros(n, bool)
        inliers &= solved[ij[:, 0]]
    R[~solved] = np.eye(3)
    return RotationResult(R, solved, inliers)
