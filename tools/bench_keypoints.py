"""Feature settings on every set with ground truth: keypoints, the front end's CPU, and what our mapper makes of them.

    python tools/bench_keypoints.py --tag default
    python tools/bench_keypoints.py --tag colmap-peak --features-args "--peak-threshold 0.00667"
    python tools/bench_keypoints.py --tag peak-only --features-args "--min-features 0" --only room,planar

The sets are tools/bench_mapper.py's (catalog scenes rendered into WORK/scenes, cached; the shared sets read in
place), those with ground truth; the panorama (no translation, no model) is left out. Per set: `mvrecon features`
(the scene's camera model as bench_mapper names it, plus --features-args) and `mvrecon match` (plus --match-args)
into WORK/TAG/SET, each timed as a whole process (user + system CPU seconds of the child, and wall); then
`mvrecon map --seed S` and the relative-pose AUC@1 / AUC@5 of its models against the ground truth (bench_mapper's
scoring). Results go to WORK/TAG.json, kept: a rerun skips the sets done. Compare two tags with `--against TAG`:
a table of both, with the front-end CPU as a ratio. Times come from whole processes in one run after the other;
quote a speed only from alternated runs (the library's timing entry).
"""

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(1, str(ROOT / "tools"))

from bench_mapper import DEFAULT_MODEL, names_list, plan_sets  # noqa: E402

from mvrecon import database  # noqa: E402
from mvrecon.eval.ground_truth import load_ground_truth_for  # noqa: E402
from mvrecon.eval.metrics import accuracy_summary  # noqa: E402
from mvrecon.eval.runners import RunOptions, run_mvrecon_map  # noqa: E402
from mvrecon.io.images import list_images  # noqa: E402


def child_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def front_end(images: Path, ws: Path, camera_model: str, features_args: list[str], match_args: list[str]) -> dict:
    """Both stages as whole processes: CPU and wall seconds of each, keypoints an image, verified pairs."""
    named = [] if camera_model == DEFAULT_MODEL else ["--camera-model", camera_model]
    figures = {}
    for stage, args in (("features", [str(images), *named, *features_args]), ("match", match_args)):
        cpu, wall = child_cpu(), time.perf_counter()
        subprocess.run([sys.executable, "-m", "mvrecon.cli", stage, "-w", str(ws), "-q", *args], cwd=ROOT,
                       check=True)
        figures[f"{stage}_cpu_s"], figures[f"{stage}_wall_s"] = child_cpu() - cpu, time.perf_counter() - wall
    with database.open_database(ws / "database.db") as db:
        images = database.read_images(db)
        figures["keypoints"] = sum(database.num_keypoints(db, i) for i in images) / max(len(images), 1)
        figures["verified_pairs"] = len(database.read_verified_pairs(db))
    return figures


def measure(s, ws: Path, args) -> dict:
    figures = front_end(s.images, ws, s.camera_model, args.features_args.split(), args.match_args.split())
    run = run_mvrecon_map(ws, RunOptions(camera_model=s.camera_model, seed=args.seed), image_dir=s.images,
                          timeout=args.timeout)
    names = [Path(n).name for n in list_images(s.images)[0]]
    summary = accuracy_summary([{Path(k).name: v for k, v in p.items()} for p in run.poses],
                               load_ground_truth_for(s.gt, names))
    return {**figures, "auc@1": summary["auc@1"], "auc@5": summary["auc@5"], "models": len(run.models),
            "registered": run.models[0].num_reg_images() if run.models else 0, "images": len(names),
            "error": run.error}


def table(results: dict, against: dict | None) -> str:
    head = "| set | keypoints | AUC@1 / AUC@5 | front-end CPU s |"
    if against is not None:
        head += " against: keypoints | AUC@1 / AUC@5 | front-end CPU s | CPU ratio |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, r in results.items():
        cpu = r["features_cpu_s"] + r["match_cpu_s"]
        line = f"| {name} | {r['keypoints']:.0f} | {r['auc@1']:.3f} / {r['auc@5']:.3f} | {cpu:.1f} |"
        if against is not None and name in against:
            o = against[name]
            other = o["features_cpu_s"] + o["match_cpu_s"]
            line += (f" {o['keypoints']:.0f} | {o['auc@1']:.3f} / {o['auc@5']:.3f} | {other:.1f} |"
                     f" {cpu / other:.2f} |")
        lines.append(line)
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tag", required=True, help="the settings' name: WORK/TAG/ and WORK/TAG.json")
    parser.add_argument("--features-args", default="", help="flags for `mvrecon features`, in one string")
    parser.add_argument("--match-args", default="", help="flags for `mvrecon match`, in one string")
    parser.add_argument("--work", type=Path, default=ROOT / "out" / "bench_keypoints")
    parser.add_argument("--only", type=names_list, default=[], help="only these sets, comma-separated")
    parser.add_argument("--skip", type=names_list, default=[], help="leave these sets out, comma-separated")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--against", default=None, help="another tag of WORK, shown beside this one")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds per mapper run")
    args = parser.parse_args(argv)
    sets, skipped = plan_sets(args.work, lambda n: (not args.only or n in args.only) and n not in args.skip)
    for line in skipped:
        print(f"left out: {line}", file=sys.stderr)
    kept = args.work / f"{args.tag}.json"
    results = json.loads(kept.read_text()) if kept.is_file() else {}
    for s in sets:
        if s.gt is None or s.name.startswith("panorama") or s.name in results:
            continue
        print(f"{s.name} ...", file=sys.stderr, flush=True)
        results[s.name] = measure(s, args.work / args.tag / s.name, args)
        kept.parent.mkdir(parents=True, exist_ok=True)
        kept.write_text(json.dumps(results, indent=1) + "\n")
    against = json.loads((args.work / f"{args.against}.json").read_text()) if args.against else None
    print(table({k: v for k, v in results.items() if not args.only or k in args.only}, against))
    return 0


if __name__ == "__main__":
    sys.exit(main())
