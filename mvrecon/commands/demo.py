"""Demo: render a small ground-truth scene, reconstruct it end to end, and print the accuracy.

Renders the catalog scene `object_orbit_small` (10 views, 640x480, known cameras) into OUT/scene, runs
`reconstruct` on its images into OUT/run, and compares the result with the scene's ground truth: registered
images, points, reprojection error, relative-pose AUC@1/5 deg, median rotation and camera-centre errors after
a
Sim3 alignment. The figures are also written to OUT/accuracy.json. Everything is cached: a second run reuses
the
scene and the finished reconstruction.

Example:
  mvrecon demo -o out/demo
"""

ORDER = 1
ON_INTERRUPT = "features, matches and the mapping snapshot are kept; rerun the same command to continue"

SCENE = "object_orbit_small"


def add_arguments(parser) -> None:
    from ._options import non_negative_int

    parser.add_argument("-o", "--output", default="out/demo", help="output folder (default: out/demo)")
    parser.add_argument("--scene", default=SCENE, help=f"catalog scene to use (default: {SCENE})")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="mapper seed")


def run(args) -> int:
    import json
    import logging
    from pathlib import Path

    from ..eval.ground_truth import load_ground_truth
    from ..eval.metrics import accuracy_summary
    from ..eval.models import model_stats, poses, sparse_models
    from ..pipeline import ReconstructConfig, reconstruct
    from ..scenes import make_scene
    from ..sfm.config import MapperConfig

    log = logging.getLogger("mvrecon")
    out = Path(args.output)
    log.info("rendering scene %s into %s ...", args.scene, out / "scene")
    scene = make_scene(args.scene, out / "scene")
    run_dir = out / "run"
    report = reconstruct(ReconstructConfig(mapper=MapperConfig(seed=args.seed)), scene / "images", run_dir,
                         resume=True)
    models = sparse_models(run_dir / "sparse")
    gt = load_ground_truth(scene / "gt" / "sparse")
    summary = accuracy_summary([poses(m) for m in models], gt)
    stats = model_stats(models[0]) if models else {"registered": 0, "points": 0,
                                                   "mean_reprojection_error_px": float("nan")}
    keys = ("registered", "points", "mean_reprojection_error_px")
    result = {"scene": args.scene, "images": len(gt), **{k: stats[k] for k in keys},
              "models": len(models), "wall_s": report["total"]["wall_s"], **summary}
    (out / "accuracy.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [
        f"mvrecon demo: scene {args.scene} ({len(gt)} images, ground truth in {scene / 'gt' / 'sparse'})",
        f"  registered images      {summary['registered']} / {len(gt)} in {len(models)} model(s)",
        f"  points                 {stats['points']}",
        f"  reprojection error     {stats['mean_reprojection_error_px']:.3f} px (mean)",
        f"  relative pose AUC@1    {summary['auc@1']:.3f}",
        f"  relative pose AUC@5    {summary['auc@5']:.3f}",
    ]
    if "median_rotation_error_deg" in summary:
        lines += [f"  median rotation error  {summary['median_rotation_error_deg']:.4f} deg",
                  f"  median centre error    {summary['median_center_error']:.5f} "
                  f"({summary['median_center_error_pct']:.3f}% of the scene)"]
    lines += [f"  wall time              {report['total']['wall_s']:.1f} s (features, matching, mapping)",
              f"  outputs                {run_dir}/sparse/0, {run_dir}/points.ply, {run_dir}/report.json"]
    print("\n".join(lines))
    return 0
