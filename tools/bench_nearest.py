"""Descriptor nearest neighbours for one image pair: mvrecon's integer product through onnxruntime against
faiss-cpu (exact flat index, and approximate HNSW and IVF indexes), in the same process, taken in turn.

Each method returns the matches of `matching.matcher.match_descriptors` (2 nearest neighbours, Lowe's ratio test,
maximum angle, mutual check) on one core, as the matching stage's pool runs one pair per core. Reports the median
seconds per pair and the share of the float32 exact matches each method finds.

    python tools/bench_nearest.py WORKSPACE [--pairs 4] [--rounds 3] [--size 8192]

WORKSPACE: a features workspace (database.db), e.g. of strecha_fountain_P11 (about 5,000 features an image).
Each side of a pair stacks the descriptors of every other image (k, k+2, ...; k+1, k+3, ...) up to --size rows.
faiss-cpu is needed only here: `pip install faiss-cpu`.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from mvrecon import database as dbmod
from mvrecon.executor import blas_threads
from mvrecon.matching.matcher import MatcherConfig, match_descriptors, normalize_descriptors, prepare_descriptors


def matches_from_neighbours(best_j, best_s, second_s, col_best_i, config: MatcherConfig) -> np.ndarray:
    """(N,2) matches from 2-NN cosines of a->b and each b's nearest a, with the tests of match_descriptors."""
    angle1 = np.arccos(np.clip(best_s, -1.0, 1.0))
    angle2 = np.arccos(np.clip(second_s, -1.0, 1.0))
    keep = (angle1 <= config.max_distance) & (angle1 < config.max_ratio * angle2) & (best_j >= 0)
    keep &= col_best_i[np.maximum(best_j, 0)] == np.arange(len(best_j))
    idx = np.nonzero(keep)[0]
    return np.stack([idx, best_j[idx]], axis=1)


def faiss_matcher(kind: str):
    import faiss

    faiss.omp_set_num_threads(1)

    def index_of(x: np.ndarray):
        if kind == "flat":
            index = faiss.IndexFlatIP(x.shape[1])
        elif kind == "hnsw":
            index = faiss.IndexHNSWFlat(x.shape[1], 32, faiss.METRIC_INNER_PRODUCT)
            index.hnsw.efSearch = 64
        else:  # ivf: 64 lists, 8 probed
            index = faiss.IndexIVFFlat(faiss.IndexFlatIP(x.shape[1]), x.shape[1], 64, faiss.METRIC_INNER_PRODUCT)
            index.train(x)
            index.nprobe = 8
        index.add(x)
        return index

    def match(d1, d2, config=MatcherConfig()):
        a, b = normalize_descriptors(d1), normalize_descriptors(d2)
        s_ab, j_ab = index_of(b).search(a, 2)
        _, i_ba = index_of(a).search(b, 1)
        return matches_from_neighbours(j_ab[:, 0], s_ab[:, 0], s_ab[:, 1], i_ba[:, 0], config)

    return match


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--size", type=int, default=8192, help="descriptors on each side of a pair")
    args = parser.parse_args(argv)
    with dbmod.open_database(args.workspace / "database.db") as db:
        ids = sorted(dbmod.read_images(db))
        desc = {i: dbmod.read_descriptors(db, i) for i in ids}
    sides = {k: np.concatenate([desc[i] for i in ids[k::2]])[:args.size] for k in range(len(ids))}
    desc = sides
    pairs = [(k, k + 1) for k in range(min(args.pairs, len(ids) - 1))]
    rows = np.mean([len(desc[k]) for k in desc])
    print(f"{len(pairs)} pairs of {rows:.0f} x {args.size} descriptors, one thread")

    def onnx_int(d1, d2):  # what the matching stage does: prepared once per image, here once per call
        return match_descriptors(prepare_descriptors(d1), prepare_descriptors(d2))

    def float_exact(d1, d2):
        return match_descriptors(normalize_descriptors(d1), normalize_descriptors(d2))

    methods = {"onnx int8 product (mvrecon)": onnx_int, "numpy float32 product": float_exact}
    try:
        for kind in ("flat", "hnsw", "ivf"):
            methods[f"faiss {kind}"] = faiss_matcher(kind)
    except ImportError:
        print("faiss-cpu is not installed: only mvrecon's own products are measured", file=sys.stderr)
    reference = {p: {tuple(m) for m in float_exact(desc[p[0]], desc[p[1]])} for p in pairs}
    times = {name: [] for name in methods}
    found = {name: [] for name in methods}
    with blas_threads(1):
        for _ in range(args.rounds):
            for name, method in methods.items():  # in turn, so that a drift of the machine's speed hits all
                start = time.perf_counter()
                out = [method(desc[p[0]], desc[p[1]]) for p in pairs]
                times[name].append((time.perf_counter() - start) / len(pairs))
                found[name] = [len({tuple(m) for m in o} & reference[p]) / max(len(reference[p]), 1)
                               for o, p in zip(out, pairs)]
    base = statistics.median(times["onnx int8 product (mvrecon)"])
    print(f"{'method':30s} {'median s/pair':>14s} {'vs onnx':>8s} {'exact matches found':>20s}")
    for name in methods:
        t = statistics.median(times[name])
        print(f"{name:30s} {t:14.3f} {t / base:8.2f} {np.mean(found[name]):20.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
