"""Pair selections compared on a scene with ground truth: pairs, matching seconds, registered images, pose AUC,
and the recall of the ground-truth overlapping pairs (`eval.overlap`).

    python tools/bench_pairs.py SCENE [SCENE ...] --specs exhaustive,retrieval:20,auto --out DIR [--recall-only]

SCENE: a catalog scene folder (images/ and gt/sparse/). Each spec is a full `mvrecon reconstruct` run into
DIR/<scene>/<spec>; with --recall-only the features are extracted once and each spec only selects pairs (no
matching or mapping), for the recall on large scenes. Prints one table row per scene and spec.
"""

import argparse
import json
import sys
from pathlib import Path

from mvrecon import database as dbmod
from mvrecon.cli import main as mvrecon_main
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models
from mvrecon.eval.overlap import overlapping_pairs, pair_recall
from mvrecon.io.gps import read_gps
from mvrecon.matching.pairs import plan_pairs


def selected(workspace: Path, images: Path, spec: str):
    """The PairPlan that `spec` makes on a workspace's features (as the matching stage makes it)."""
    with dbmod.open_database(workspace / "database.db") as db:
        ids = {i.name: i.image_id for i in dbmod.read_images(db).values()}
        return plan_pairs(spec, sorted(ids), descriptors=lambda n: dbmod.read_descriptors(db, ids[n]),
                          positions=lambda n: read_gps(images / n))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--specs", default="exhaustive,retrieval:20,auto")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--recall-only", action="store_true")
    args = parser.parse_args(argv)
    print(f"{'scene':22s} {'spec':26s} {'images':>6s} {'pairs':>6s} {'recall':>7s} {'match s':>8s} "
          f"{'registered':>10s} {'auc@5':>6s}", flush=True)
    for scene in args.scenes:
        images, gt_dir = scene / "images", scene / "gt" / "sparse"
        overlap = overlapping_pairs(gt_dir)
        gt = load_ground_truth(gt_dir)
        for spec in args.specs.split(","):
            if args.recall_only:
                ws = args.out / scene.name / "features"
                if not (ws / "database.db").exists():
                    assert mvrecon_main(["-q", "features", str(images), "-o", str(ws)]) == 0
                plan = selected(ws, images, spec)
                row = {"pairs": len(plan.pairs), "match_s": float("nan"), "registered": "", "auc": float("nan")}
            else:
                out = args.out / scene.name / spec.replace(":", "_").replace("+", "_")
                code = mvrecon_main(["-q", "reconstruct", str(images), "-o", str(out), "--pairs", spec])
                if code != 0:
                    print(f"{scene.name:22s} {spec:26s} failed with exit code {code}", flush=True)
                    continue
                report = json.loads((out / "report.json").read_text())
                plan = selected(out, images, spec)
                acc = accuracy_summary([poses(m) for m in sparse_models(out / "sparse")], gt)
                row = {"pairs": report["pairs"]["pairs"], "match_s": report["stages"]["matching"]["wall_s"],
                       "registered": f"{acc['registered']}/{len(gt)}", "auc": acc["auc@5"]}
            print(f"{scene.name:22s} {plan.spec:26s} {len(gt):6d} {row['pairs']:6d} "
                  f"{pair_recall(plan.pairs, overlap):7.1%} {row['match_s']:8.1f} {row['registered']:>10s} "
                  f"{row['auc']:6.3f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
