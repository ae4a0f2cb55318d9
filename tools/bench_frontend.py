"""Benchmark the front end against pycolmap on the same images, in the same run (not a test).

    .venv/bin/python tools/bench_frontend.py ../shared/data/middlebury_templeRing/images [--workers 2]

Copies the images to a temporary folder, then times (wall clock) our `extract_features` + `match` (exhaustive)
and pycolmap's `extract_features` + `match_exhaustive` on the CPU, each into its own database, and prints
keypoints per image, verified pairs (pairs with at least 15 inliers), mean inliers per verified pair, the times,
and our time as a ratio of pycolmap's. Both use all cores unless --workers is given.
"""

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def colmap_figures(database_path, min_inliers=15):
    from mvrecon import database as dbmod

    with dbmod.open_database(database_path) as db:
        images = dbmod.read_images(db)
        kps = [dbmod.num_keypoints(db, i) for i in images]
        pairs = [n for *_, n in dbmod.read_verified_pairs(db) if n >= min_inliers]
    return {"images": len(images), "kp": float(np.mean(kps)) if kps else 0.0, "pairs": len(pairs),
            "inliers": float(np.mean(pairs)) if pairs else 0.0}


def run_pycolmap(images: Path, work: Path, workers: int) -> tuple[float, float]:
    import pycolmap

    db = work / "colmap.db"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = workers
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = workers
    t0 = time.perf_counter()
    pycolmap.extract_features(db, images, extraction_options=extraction, device=pycolmap.Device.cpu)
    t1 = time.perf_counter()
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    return t1 - t0, time.perf_counter() - t1


def run_ours(images: Path, work: Path, workers: int) -> tuple[float, float]:
    from mvrecon.stages.common import FrontendConfig
    from mvrecon.stages.features import extract_features
    from mvrecon.stages.matching import match

    config = FrontendConfig(workers=max(workers, 0))
    t0 = time.perf_counter()
    extract_features(config, images, work / "ours")
    t1 = time.perf_counter()
    match(config, work / "ours")
    return t1 - t0, time.perf_counter() - t1


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("images", type=Path)
    parser.add_argument("--workers", type=int, default=-1, help="processes/threads for both (-1 = all cores)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        images = tmp / "images"
        shutil.copytree(args.images, images)
        ours_t = run_ours(images, tmp, args.workers)
        colmap_t = run_pycolmap(images, tmp, args.workers)
        ours = colmap_figures(tmp / "ours" / "database.db")
        theirs = colmap_figures(tmp / "colmap.db")
    print(f"\n{args.images} ({ours['images']} images)\n")
    print("| | keypoints/image | verified pairs | mean inliers/pair | features s | matching s | total s |")
    print("|---|---|---|---|---|---|---|")
    for name, f, t in (("mvrecon", ours, ours_t), ("pycolmap", theirs, colmap_t)):
        print(f"| {name} | {f['kp']:.0f} | {f['pairs']} | {f['inliers']:.0f} | {t[0]:.2f} | {t[1]:.2f} | "
              f"{sum(t):.2f} |")
    print(f"\ntime ratio mvrecon/pycolmap: features {ours_t[0] / colmap_t[0]:.2f}, matching "
          f"{ours_t[1] / colmap_t[1]:.2f}, total {sum(ours_t) / sum(colmap_t):.2f}")


if __name__ == "__main__":
    main()
