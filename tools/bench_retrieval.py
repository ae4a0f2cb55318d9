"""How retrieval's cost grows with the images: vocabulary, VLAD vectors, similarities and ranking, for n images.

    python tools/bench_retrieval.py WORKSPACE [--sizes 100,300,1000] [--k 20]

WORKSPACE: a features workspace (database.db); its images' descriptors are read in turn, over and over, for n
images (image k reads image k mod m's, with the rows rolled by k so that no two vectors are equal): the cost of
each step, not a ranking to trust. Prints seconds per step and per image.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from mvrecon import database as dbmod
from mvrecon.matching.retrieval import global_vectors, nearest_pairs, ranking


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--sizes", default="100,300,1000")
    parser.add_argument("--k", type=int, default=20)
    args = parser.parse_args(argv)
    with dbmod.open_database(args.workspace / "database.db") as db:
        base = [dbmod.read_descriptors(db, i) for i in sorted(dbmod.read_images(db))]
    print(f"{np.mean([len(d) for d in base]):.0f} descriptors per image; retrieval:{args.k}")
    print(f"{'images':>6s} {'vectors s':>10s} {'rank s':>8s} {'ms/image':>9s} {'pairs':>7s}")
    for n in (int(s) for s in args.sizes.split(",")):
        names = [f"{k:05d}.jpg" for k in range(n)]

        def read(name: str) -> np.ndarray:
            k = int(name[:5])
            return np.roll(base[k % len(base)], k // len(base), axis=1)

        start = time.perf_counter()
        g = global_vectors(names, read)
        made = time.perf_counter()
        expanded, raw = ranking(g.vectors)
        pairs = nearest_pairs(expanded, args.k, tiebreak=raw)
        ranked = time.perf_counter()
        per_image = 1000 * (ranked - start) / n
        print(f"{n:6d} {made - start:10.1f} {ranked - made:8.2f} {per_image:9.1f} {len(pairs):7d}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
