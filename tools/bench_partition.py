"""Partitioned mapping benchmark: mvrecon's mapping whole and in parts, and COLMAP's hierarchical mapper, on one
database.

    python tools/bench_partition.py --scene street_long --count 100 --sizes 30
    python tools/bench_partition.py --scene-dir SCENE --sizes 100 --whole RUN   # a rendered scene, an earlier run

The scene (a rendered catalog scene: images/ and gt/sparse/; `--scene NAME --count N` renders it into WORK,
cached) is matched once by `mvrecon reconstruct` (default front end), which also gives the unpartitioned
mapping. The same database.db is then mapped by `mvrecon map --partition-size P` (each P of --sizes; parts on
the process pool, one worker per core) and by `pycolmap.hierarchical_mapping` with leaf_max_num_images = P (its
incremental mapper in clusters merged by COLMAP; seed 0, every thread). Each mvrecon mapping runs in its own
subprocess and is timed by its report.json's mapping stage; pycolmap's call is timed in this process (its
import excluded). Per run it prints the images registered in the largest model, the models, AUC@1/5 over all
image pairs against the ground truth (`eval.metrics`) and the mapping's wall time.
"""

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models


def mvrecon(*args: str) -> None:
    subprocess.run([sys.executable, "-c", "import sys; from mvrecon.cli import main; sys.exit(main(sys.argv[1:]))",
                    "-q", *args], check=True)


def figures(models: list, gt: dict, seconds: float) -> dict:
    models = sorted(models, key=lambda r: -r.num_reg_images())
    acc = accuracy_summary([poses(r) for r in models], gt)
    largest = models[0].num_reg_images() if models else 0
    return {"registered": largest, "models": len(models), "auc@1": acc["auc@1"], "auc@5": acc["auc@5"],
            "seconds": seconds}


def mapping_seconds(ws: Path) -> float:
    return float(json.loads((ws / "report.json").read_text())["stages"]["mapping"]["wall_s"])


def hierarchical(ws: Path, images: Path, size: int, out: Path) -> tuple[list, float]:
    import pycolmap  # noqa: PLC0415 - COLMAP only for its own runs

    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    opts = pycolmap.HierarchicalPipelineOptions()
    opts.clustering_options.leaf_max_num_images = size
    opts.incremental_options.random_seed = 0
    start = time.perf_counter()
    recs = pycolmap.hierarchical_mapping(ws / "database.db", images, out, opts)
    return list(recs.values()), time.perf_counter() - start


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="street_long", help="catalog scene to render (without --scene-dir)")
    ap.add_argument("--count", type=int, default=100, help="views of --scene")
    ap.add_argument("--scene-dir", type=Path, default=None, help="an already rendered scene (read only)")
    ap.add_argument("--whole", type=Path, default=None,
                    help="an unpartitioned mvrecon run of the scene (read only): its database and model are used "
                         "instead of running `mvrecon reconstruct`")
    ap.add_argument("--sizes", default="30", help="partition sizes P, comma-separated")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_partition"))
    ap.add_argument("--no-colmap", action="store_true", help="skip pycolmap.hierarchical_mapping")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    scene = args.scene_dir or args.work / f"{args.scene}-{args.count}"
    if args.scene_dir is None:
        mvrecon("scene", "make", args.scene, "-o", str(scene), "--count", str(args.count))
    name = scene.name
    images, gt = scene / "images", load_ground_truth(scene / "gt" / "sparse")
    whole = args.whole or args.work / f"{name}-whole"
    if not (whole / "report.json").is_file():
        mvrecon("reconstruct", str(images), "-o", str(whole))
    database = args.work / f"{name}-database"  # a copy: pycolmap opens it for writing
    database.mkdir(parents=True, exist_ok=True)
    shutil.copy2(whole / "database.db", database / "database.db")
    rows = {"whole": figures(sparse_models(whole / "sparse"), gt, mapping_seconds(whole))}
    for size in sizes:
        parted = args.work / f"{name}-parts-{size}"
        shutil.rmtree(parted, ignore_errors=True)
        parted.mkdir(parents=True)
        for f in ("database.db", "report.json"):
            shutil.copy2(whole / f, parted / f)
        shutil.copytree(whole / ".stages", parted / ".stages")
        mvrecon("map", "-o", str(parted), "--partition-size", str(size), "--overwrite", "--image-dir", str(images))
        rows[f"parts P={size}"] = figures(sparse_models(parted / "sparse"), gt, mapping_seconds(parted))
        if not args.no_colmap:
            recs, seconds = hierarchical(database, images, size, args.work / f"{name}-colmap-{size}")
            rows[f"COLMAP hierarchical P={size}"] = figures(recs, gt, seconds)
    print(f"{name}: {len(gt)} images")
    print(f"{'run':32s} {'registered':>10s} {'models':>6s} {'AUC@1':>6s} {'AUC@5':>6s} {'mapping s':>9s}")
    for label, r in rows.items():
        print(f"{label:32s} {r['registered']:10d} {r['models']:6d} {r['auc@1']:6.3f} {r['auc@5']:6.3f} "
              f"{r['seconds']:9.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
