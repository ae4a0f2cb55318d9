"""The view graph split into overlapping parts of at most P images, for mapping each part on its own.

The graph: images as nodes, verified pairs as edges weighted by their inlier counts (`view_graph.oriented_pairs`).
Each connected component is cut in two by spectral bisection (the Fiedler vector of the normalised Laplacian,
cut where the normalised cut is smallest among the splits that leave the fewest cores possible), and the halves
are cut again until every *core* has at most P - O images. Each core then grows into its *part* of up to P
images (so by O images or more) with outside images taken in turn from each neighbouring core, each time that
core's image with the most inliers with it.

The overlap rule, O = max(MIN_OVERLAP, ceil(OVERLAP_SHARE * P)): merging two parts needs a similarity transform,
and that needs shared images registered in both (camera centres, and their rotations as a check) with the
points they share. The images most strongly matched to a core are the ones its part's mapper registers with the
most 2D-3D matches, and they are the boundary images of the neighbouring cores, which those parts register too;
taking them in turn from every neighbouring core gives each boundary shared images from both sides, the weak
boundaries too (a street's corners: where the spectral cut falls, and where a link is hardest to find; taking
the strongest images whatever their core left such a boundary one shared image and the parts unmerged).
"""

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..database import PairGeometry
from .config import MIN_PARTITION_SIZE
from .view_graph import oriented_pairs

MIN_OVERLAP = 4  # images a core grows by at least
OVERLAP_SHARE = 0.3  # of P, the images a core grows by
_BALANCE = 1 / 3  # each side of a bisection keeps at least this share of the images


@dataclass
class Partition:
    """`cores`: disjoint image index arrays covering every image of the graph; `parts[k]`: cores[k] with its
    overlap, at most `size` images. Indices are positions in the `image_ids` the partition was made from."""

    size: int
    cores: list[np.ndarray]
    parts: list[np.ndarray]


def overlap_for(size: int) -> int:
    """O, the images a core grows by for parts of at most `size` images (the module docstring's rule)."""
    return max(MIN_OVERLAP, math.ceil(OVERLAP_SHARE * size))


def pair_weights(image_ids: np.ndarray, pairs: Iterable[PairGeometry]) -> np.ndarray:
    """The view graph as a dense (n, n) symmetric matrix of inlier counts (0: no verified pair)."""
    n = len(image_ids)
    W = np.zeros((n, n))
    for (a, b), inliers in oriented_pairs(image_ids, pairs).items():
        W[a, b] = W[b, a] = len(inliers)
    return W


def partition_view_graph(W: np.ndarray, size: int) -> Partition:
    """Overlapping parts of at most `size` images of the view graph `W` (`pair_weights`; see the module
    docstring). A graph of at most `size` images is one part. Raises ValueError for `size` under
    MIN_PARTITION_SIZE."""
    if size < MIN_PARTITION_SIZE:
        raise ValueError(f"a partition size under {MIN_PARTITION_SIZE} leaves parts too small to map, got {size}")
    n = len(W)
    if n <= size:
        everything = np.arange(n)
        return Partition(size, [everything], [everything])
    overlap = overlap_for(size)
    core_size = size - overlap
    _, label = connected_components(coo_matrix(W > 0), directed=False)
    cores = []
    for c in range(int(label.max()) + 1 if n else 0):
        cores.extend(_bisect(W, np.flatnonzero(label == c), core_size))
    cores.sort(key=lambda core: int(core.min()))
    parts = [_grow(W, core, cores, size) for core in cores]
    return Partition(size, cores, parts)


def _bisect(W: np.ndarray, nodes: np.ndarray, most: int) -> list[np.ndarray]:
    """`nodes` cut recursively in two by their normalised-cut sweep until each piece has at most `most`: a cut
    leaves the two sides room for ceil(n / most) pieces between them (the fewest there can be), half each."""
    n = len(nodes)
    if n <= most:
        return [np.sort(nodes)]
    pieces = math.ceil(n / most)
    left_pieces = pieces // 2
    low = max(1, n - (pieces - left_pieces) * most, math.ceil(_BALANCE * n) if pieces == 2 else 1)
    high = min(n - 1, left_pieces * most)
    sub = W[np.ix_(nodes, nodes)]
    order = _spectral_order(sub)
    cut = _best_cut(sub, order, min(low, high), high)
    left, right = nodes[order[:cut]], nodes[order[cut:]]
    return _bisect(W, left, most) + _bisect(W, right, most)


def _spectral_order(W: np.ndarray) -> np.ndarray:
    """The nodes ordered by the Fiedler vector of the normalised Laplacian (D^-1/2-scaled, Shi and Malik's
    relaxed normalised cut); isolated nodes (no edge inside) go last."""
    d = W.sum(axis=1)
    inv = np.where(d > 0, 1 / np.sqrt(np.maximum(d, 1e-300)), 0.0)
    L = np.eye(len(W)) - inv[:, None] * W * inv[None, :]
    _, vectors = np.linalg.eigh(L)
    fiedler = vectors[:, 1] * inv
    fiedler[d == 0] = np.inf
    return np.argsort(fiedler, kind="stable")


def _best_cut(W: np.ndarray, order: np.ndarray, low: int, high: int) -> int:
    """The split position k in [low, high] of `order` whose normalised cut cut/vol(A) + cut/vol(B) is least."""
    Wo = W[np.ix_(order, order)]
    degree = Wo.sum(axis=1)
    volume = degree.sum()
    best, best_k = np.inf, (low + high) // 2
    for k in range(low, high + 1):
        cut = Wo[:k, k:].sum()
        va = degree[:k].sum()
        vb = volume - va
        score = cut / max(va, 1e-12) + cut / max(vb, 1e-12)
        if score < best:
            best, best_k = score, k
    return best_k


def _grow(W: np.ndarray, core: np.ndarray, cores: list[np.ndarray], size: int) -> np.ndarray:
    """`core` with up to `size - len(core)` outside images, taken in turn from each neighbouring core (strongest
    first), each time that core's image with the most inliers with `core`: every boundary gets its share of the
    overlap, the weak ones too (a weak boundary is where a link is hardest to find)."""
    strength = W[:, core].sum(axis=1)
    strength[core] = 0.0
    queues = []
    for other in cores:
        near = other[strength[other] > 0]
        if len(near):
            queues.append((float(strength[near].sum()), list(near[np.argsort(-strength[near], kind="stable")])))
    queues = [q for _, q in sorted(queues, key=lambda q: -q[0])]
    chosen: list[int] = []
    room = size - len(core)
    while room > 0 and any(queues):
        for q in queues:
            if q and room > 0:
                chosen.append(int(q.pop(0)))
                room -= 1
    return np.sort(np.r_[core, chosen]).astype(np.int64)
