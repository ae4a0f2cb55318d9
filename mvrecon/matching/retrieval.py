"""Image retrieval for pair selection (`--pairs retrieval:K`): each image with the K images that look most like it.

An unordered set of N photos has N(N-1)/2 pairs (500 images: 124,750), most of them views that share nothing.
Each image gets one global descriptor built from the SIFT descriptors already in the database, and only the K
nearest images by cosine similarity are matched: the union of the N lists of K, each pair once.

The descriptor is VLAD (Jégou et al. 2010, normalised as in Arandjelović & Zisserman 2013): 64 centres learned
by k-means on a sample of the set's own (RootSIFT) descriptors; each descriptor adds its residual to its nearest
centre; the 64 x 128 sums are square-rooted (a repeated facade element must not drown the rest) and L2-normalised
per centre, then as a whole. It was measured against tf-idf bags of 1,024-10,000 words (flat, or a two-level
tree as COLMAP's vocabulary tree) on the exhaustive runs of opensfm_lund, imc_reichstag, strecha_fountain_P11
and middlebury_templeRing. On lund, the set with the most pairs that share little, VLAD ranked the pairs with
>= 100 inliers first (mean average precision 0.83-0.85 over three k-means seeds, bags of words 0.65-0.76), and
its 10 nearest per image kept 46-48 of those 48 pairs in 164-166 selected (bags of words 41-46 in 193-210). The
other sets were ties but imc_reichstag, where the tree ranked better (0.93 against 0.75) but all 10 images
overlap anyway. 64 centres are also cheap to assign (a flat vocabulary of 4,096 words costs 64x more per
descriptor). Before ranking, each vector is averaged with its 2 nearest (query expansion): on lund that kept 79
of the 82 pairs with >= 50 inliers instead of 71-72.

No network and no pretrained file; deterministic: a fixed seed, images in name order, ties to the first name.
Descriptors are read twice per image (once for the sample, once to encode) and never all held: 500 images of
8,192 features would be 2 GB as float32.
"""

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..executor import blas_threads
from .matcher import normalize_descriptors

log = logging.getLogger(__name__)

CENTRES = 64  # VLAD vocabulary size
SAMPLE = 100_000  # descriptors the vocabulary is learned on, drawn evenly from the images
ITERATIONS = 10  # of k-means (Lloyd)
SEED = 0
EXPANSION = 2  # neighbours averaged into each image's vector before ranking (`expand_queries`)
_BLOCK = 65_536  # rows per product in `assign`: 16 MB of scores for 64 centres


def assign(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest centre (Euclidean) of each row: the largest x.c - |c|^2 / 2."""
    half = 0.5 * (centres * centres).sum(axis=1)
    out = np.empty(len(x), dtype=np.int64)
    for s in range(0, len(x), _BLOCK):
        out[s:s + _BLOCK] = np.argmax(x[s:s + _BLOCK] @ centres.T - half, axis=1)
    return out


def _cluster_sums(x: np.ndarray, labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-cluster sums of rows and counts, as one product with the (k, n) indicator matrix (10x faster than a
    sort and np.add.reduceat on 100,000 rows)."""
    indicator = np.zeros((k, len(x)), dtype=np.float32)
    indicator[labels, np.arange(len(x))] = 1.0
    return indicator @ x, np.bincount(labels, minlength=k)


# `rng`'s annotation is a string: evaluated, it imported numpy.random at every start-up (7 ms before the feature
# workers fork, on one core)
def kmeans(x: np.ndarray, k: int, iterations: int, rng: "np.random.Generator") -> np.ndarray:
    """Lloyd's k-means from k distinct sample rows; an empty cluster keeps its centre."""
    centres = x[rng.choice(len(x), size=k, replace=False)].astype(np.float32)
    for _ in range(iterations):
        sums, counts = _cluster_sums(x, assign(x, centres), k)
        full = counts > 0
        centres[full] = sums[full] / counts[full, None]
    return centres


def learn_vocabulary(names: list[str], read: Callable[[str], np.ndarray], k: int = CENTRES,
                     sample: int = SAMPLE, seed: int = SEED) -> np.ndarray:
    """k centres (fewer if there are fewer descriptors) from an even sample of every image's unit descriptors."""
    rng = np.random.default_rng(seed)
    per_image = max(1, sample // len(names))
    parts = []
    for name in names:
        d = normalize_descriptors(read(name))
        parts.append(d[rng.choice(len(d), size=min(per_image, len(d)), replace=False)] if len(d) else d)
    x = np.concatenate(parts)
    return kmeans(x, min(k, len(x)), ITERATIONS, rng) if len(x) else x


def vlad(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Unit VLAD vector of one image (zeros for an image without descriptors)."""
    x = normalize_descriptors(descriptors)
    if not len(x) or not len(centres):
        return np.zeros(centres.size, dtype=np.float32)
    sums, counts = _cluster_sums(x, assign(x, centres), len(centres))
    v = sums - counts[:, None] * centres
    v = np.sign(v) * np.sqrt(np.abs(v))
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    v = v.ravel()
    return (v / max(np.linalg.norm(v), 1e-12)).astype(np.float32)


def similarities(vectors: np.ndarray) -> np.ndarray:
    """Cosines of every pair of unit rows (float64); the diagonal is -inf, so that each row's own index sorts
    last in `nearest`, past the n - 1 others."""
    sim = vectors.astype(np.float64) @ vectors.T.astype(np.float64)
    np.fill_diagonal(sim, -np.inf)
    return sim


def nearest(sim: np.ndarray, k: int, tiebreak: np.ndarray | None = None) -> np.ndarray:
    """(rows, min(k, n-1)) indices of each row's k most similar other images of (rows of) an n x n `similarities`
    matrix, best first.
    Similarities equal to 6 decimals are ranked by `tiebreak` (the same images' similarities before query
    expansion), then by index."""
    k = min(k, sim.shape[1] - 1)
    if tiebreak is None:
        return np.argsort(-sim, axis=1, kind="stable")[:, :k]
    return np.lexsort((-tiebreak, -np.round(sim, 6)), axis=1)[:, :k]


def expand_queries(vectors: np.ndarray, sim: np.ndarray, n: int = EXPANSION) -> np.ndarray:
    """Each unit row replaced by the unit mean of itself and its n nearest rows by `sim` (its `similarities`;
    average query expansion, Chum et al. 2007): an image then also finds the views of its views, which a street
    walk's chain of moderately overlapping images needs."""
    out = vectors + vectors[nearest(sim, n)].sum(axis=1)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def nearest_pairs(sim: np.ndarray, k: int, tiebreak: np.ndarray | None = None) -> set[tuple[int, int]]:
    """(i, j), i < j, for every j among i's k nearest rows (`nearest`)."""
    return {(min(i, int(j)), max(i, int(j))) for i, row in enumerate(nearest(sim, k, tiebreak)) for j in row}


@dataclass(frozen=True)
class GlobalVectors:
    """One unit VLAD vector per image, rows in sorted-name order; `empty`: indices of images without
    descriptors (their rows are zeros and they rank nowhere)."""

    names: list[str]
    vectors: np.ndarray
    empty: list[int]

    @property
    def found(self) -> list[int]:
        """Indices of the images that have descriptors."""
        gone = set(self.empty)
        return [i for i in range(len(self.names)) if i not in gone]


def global_vectors(names: list[str], read: Callable[[str], np.ndarray]) -> GlobalVectors:
    """VLAD vectors of the images `names` (sorted here) on a vocabulary learned from their own descriptors.
    BLAS runs one thread here: its products are small (64 centres), and OpenBLAS's waiting threads spin, which
    made this step 4-10x slower on a busy 2-core machine."""
    names = sorted(names)
    vectors, empty = [], []
    with blas_threads(1):
        centres = learn_vocabulary(names, read)
        for i, name in enumerate(names):
            descriptors = read(name)
            vectors.append(vlad(descriptors, centres))
            if not len(descriptors):
                empty.append(i)
    dim = centres.size if len(centres) else CENTRES * 128
    return GlobalVectors(names, np.stack(vectors) if vectors else np.zeros((0, dim), np.float32), empty)


def ranking(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(expanded, raw) `similarities` of unit rows: the query-expanded ones rank, the raw ones break ties.
    One BLAS thread, as in `global_vectors`."""
    with blas_threads(1):
        raw = similarities(vectors)
        # at the two ends of a chain of views (a street, a half orbit) an image and its neighbour expand to the
        # same vector (each is among the other's nearest, and they share the third), so the third's choice
        # between them fell to float rounding (3.7e-9 apart on object_orbit_small): the raw vectors decide
        return similarities(expand_queries(vectors, raw)), raw


def retrieval_pairs(names: list[str], read: Callable[[str], np.ndarray], k: int,
                    vectors: GlobalVectors | None = None) -> list[tuple[str, str]]:
    """Pairs of names (in sorted-name order) of each image with its k nearest by VLAD; an image without
    descriptors is paired with every other image. `vectors`: the images' `global_vectors`, if already made."""
    names = sorted(names)
    n = len(names)
    start = time.perf_counter()
    g = global_vectors(names, read) if vectors is None else vectors
    found, empty = g.found, g.empty
    pairs = set()
    if len(found) > 1:
        expanded, raw = ranking(g.vectors[found])
        pairs = {(found[a], found[b]) for a, b in nearest_pairs(expanded, k, tiebreak=raw)}
    if empty:
        log.info("retrieval:%d: %d image(s) without descriptors (%s) are paired with every other image",
                 k, len(empty), ", ".join(names[i] for i in empty[:3]) + (", ..." if len(empty) > 3 else ""))
        pairs |= {(min(i, j), max(i, j)) for i in empty for j in range(n) if j != i}
    log.info("retrieval:%d: %d of the %d pairs of %d images selected in %.1f s", k, len(pairs), n * (n - 1) // 2,
             n, time.perf_counter() - start)
    return [(names[i], names[j]) for i, j in sorted(pairs)]
