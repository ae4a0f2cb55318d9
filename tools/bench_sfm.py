"""Benchmark: mvrecon vs pycolmap end to end on the same images, in one run, on this machine.

Runs `mvrecon reconstruct` and pycolmap (extract_features + match_exhaustive + incremental_mapping, CPU, the
same camera mode and model) each in its own subprocess (mvrecon.eval.runners), then prints registered images,
models, points, mean reprojection error, relative-pose AUC@0.5/1/5/10 deg and median rotation error against
the ground truth (found next to the images, or --gt), wall time and peak memory of both, and the ratios
mvrecon / pycolmap; then each engine's stages, with the cores each kept busy (CPU time over wall time).
Without ground truth, the AUCs of mvrecon are computed against pycolmap's model.

Usage:
  python tools/bench_sfm.py ../shared/data/middlebury_templeSparseRing/images
  python tools/bench_sfm.py IMAGES --gt MODEL_OR_PAR_FILE [--work DIR] [--camera-mode single]
  python tools/bench_sfm.py IMAGES --mvrecon-args "--peak-threshold 0.00667"   (flags for mvrecon only; a
      single flag too: --mvrecon-args "--upright"; checked by reconstruct's parser before anything runs)
  python tools/bench_sfm.py IMAGES --repeat 3   (alternating runs; wall times are their medians)

A 2-core VM's speed can drift by a third between runs a minute apart, so one pair of runs gives a noisy
ratio; --repeat alternates the engines and reports the median wall time of each and every run's ratio.
"""

import argparse
import json
import shlex
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mvrecon.commands._options import join_option_value  # noqa: E402
from mvrecon.commands.compare import check_mvrecon_args  # noqa: E402
from mvrecon.errors import InputError  # noqa: E402
from mvrecon.eval.ground_truth import find_ground_truth, load_ground_truth_for  # noqa: E402
from mvrecon.eval.metrics import AUC_THRESHOLDS, accuracy_summary  # noqa: E402
from mvrecon.eval.models import model_stats  # noqa: E402
from mvrecon.eval.runners import RunOptions, run_colmap, run_mvrecon  # noqa: E402
from mvrecon.io.images import list_images  # noqa: E402


def _basename_poses(result):
    """Poses keyed by file name only (ground-truth files name images without folders)."""
    return [{Path(k).name: v for k, v in p.items()} for p in result.poses]


def summarize(result, gt):
    row = {"error": result.error}
    if result.error:
        return row
    stats = model_stats(result.models[0]) if result.models else {"registered": 0, "points": 0,
                                                                 "mean_reprojection_error_px": float("nan")}
    row.update(models=len(result.models), registered=sum(m.num_reg_images() for m in result.models),
               largest=stats["registered"], points=stats["points"],
               reproj=stats["mean_reprojection_error_px"], wall=result.wall_s, mem=result.peak_mem_mb)
    if gt:
        acc = accuracy_summary(_basename_poses(result), gt)
        for key in ("registered", "registered_pct", "components"):  # counts of the run, not of the overlap
            acc.pop(key)
        row.update(acc)
    return row


def _stage(name: str, s: dict) -> str:
    """'features 1.0 s (1.9 cores)': CPU over wall time is how many cores the stage kept busy."""
    cores = f" ({s['cpu_s'] / s['wall_s']:.1f} cores)" if s.get("cpu_s") and s["wall_s"] > 0 else ""
    return f"{name} {s['wall_s']:.1f} s{cores}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images")
    ap.add_argument("--gt", default=None,
                    help="ground truth (COLMAP model, *_par.txt, gt_dense_cameras/, ...)")
    ap.add_argument("--work", default=None, help="keep the runs here (a finished run is reused)")
    ap.add_argument("--camera-mode", default="auto",
                    help="which images share intrinsics, for both engines: auto (default), single, "
                         "per-folder, per-image")
    ap.add_argument("--camera-model", default="SIMPLE_RADIAL",
                    help="COLMAP camera model for both engines (default SIMPLE_RADIAL)")
    ap.add_argument("--seed", type=int, default=0, help="random seed of both engines (default 0)")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ap.add_argument("--mvrecon-args", default="", help="extra flags for `mvrecon reconstruct`, in one string")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run both engines this many times, alternating; accuracy from the first run")
    # `--mvrecon-args "--upright"`: argparse alone takes a value starting with a dash for an unknown option
    args = ap.parse_args(join_option_value(sys.argv[1:] if argv is None else argv, "--mvrecon-args"))
    try:
        extra = tuple(shlex.split(args.mvrecon_args))
    except ValueError as exc:  # an unclosed quote
        ap.error(f"--mvrecon-args: {exc}")
    try:
        options = RunOptions(camera_mode=args.camera_mode, camera_model=args.camera_model, seed=args.seed,
                             mvrecon_args=extra)
        check_mvrecon_args(options)  # before any run: a misspelt flag would fail mvrecon's run only
    except InputError as exc:
        ap.error(str(exc))

    images = Path(args.images)
    gt_path = args.gt or find_ground_truth(images) or find_ground_truth(images.parent)
    # only the images in the folder count (templeRing's par file lists 47 views, the folder holds 19)
    names = [Path(n).name for n in list_images(images)[0]]
    gt = load_ground_truth_for(gt_path, names) if gt_path else None
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_sfm_"))
    runs = []
    for k in range(max(args.repeat, 1)):
        where = work if args.repeat <= 1 else work / f"run{k + 1}"
        runs.append((run_mvrecon(images, where / "mvrecon", options),
                     run_colmap(images, where / "colmap", options)))
    ours, theirs = runs[0]
    reference = gt
    if reference is None and theirs.models:
        reference = _basename_poses(theirs)[0]
    rows = {"mvrecon": summarize(ours, reference), "pycolmap": summarize(theirs, gt)}
    if len(runs) > 1:
        for column, row in enumerate(rows.values()):
            if "wall" in row:  # a failed run has no wall time to replace
                walls = [r[column].wall_s for r in runs]
                row.update(wall=statistics.median(walls), walls=walls)

    source = f"ground truth: {gt_path}" if gt else "no ground truth: AUC vs pycolmap"
    print(f"images: {images}  ({source})")
    keys = [("registered", "registered images", "{:d}"), ("models", "models", "{:d}"),
            ("points", "points (largest model)", "{:d}"), ("reproj", "mean reprojection error px", "{:.3f}")]
    keys += [(f"auc@{t:g}", f"AUC@{t:g}", "{:.3f}") for t in AUC_THRESHOLDS]
    keys += [("median_rotation_error_deg", "median rotation error deg", "{:.3f}"),
             ("wall", "wall time s" + (f", median of {len(runs)}" if len(runs) > 1 else ""), "{:.1f}"),
             ("mem", "peak memory MB", "{:.0f}")]
    print(f"{'':30s} {'mvrecon':>10s} {'pycolmap':>10s} {'ratio':>8s}")
    for key, label, fmt in keys:
        a, b = rows["mvrecon"].get(key), rows["pycolmap"].get(key)
        cell = lambda v: fmt.format(v) if isinstance(v, (int, float)) else "-"  # noqa: E731
        ratio = f"{a / b:.2f}" if isinstance(a, (int, float)) and isinstance(b, (int, float)) and b else "-"
        print(f"{label:30s} {cell(a):>10s} {cell(b):>10s} {ratio:>8s}")
    for name, row in rows.items():
        if row.get("error"):
            print(f"{name} failed: {row['error']}")
    if len(runs) > 1:
        print("wall times of the runs: mvrecon " + " ".join(f"{r[0].wall_s:.1f}" for r in runs)
              + ", pycolmap " + " ".join(f"{r[1].wall_s:.1f}" for r in runs)
              + ", ratios " + " ".join(f"{r[0].wall_s / r[1].wall_s:.2f}" for r in runs))
    if ours.report:
        missing = {n: s["reason"] for n, s in ours.report.get("images", {}).items()
                   if s["status"] != "registered"}
        for n, r in sorted(missing.items()):
            print(f"  mvrecon did not register {n}: {r}")
    for name, result in (("mvrecon", ours), ("pycolmap", theirs)):
        if result.report:
            print(f"{name} stages: " + ", ".join(_stage(k, v) for k, v in result.report.get("stages", {}).items()))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str) + "\n")
    print(f"runs kept in {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
