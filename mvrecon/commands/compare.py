"""Compare mvrecon with COLMAP on the same images (or compare existing models), with an HTML report.

  mvrecon compare IMAGES -o REPORT [--gt GT] [--colmap-global]
      runs mvrecon end to end, pycolmap end to end (extract_features, match_exhaustive, incremental_mapping;
      --colmap-global adds global_mapping) and COLMAP's incremental mapper on mvrecon's database ("same matches"),
      with the same camera settings; the runs go to REPORT/runs/ and a finished run is reused, not redone.
  mvrecon compare --models A B [C ...] [--labels ...] [--gt GT] -o REPORT
      compares models that exist: run folders (report.json + sparse/), sparse/ folders or COLMAP model folders.

Each model is aligned to the reference (GT when given, else COLMAP's model; with --models, the last one) by a
robust Sim3 of camera centres. GT: a COLMAP model folder, a Middlebury *_par.txt, a Strecha gt_dense_cameras/
folder or an IMC calibration/ folder. Writes REPORT/index.html (self-contained), metrics.json and metrics.csv.
"""

ORDER = 60
ON_INTERRUPT = "finished runs are kept; rerun the same command to continue"


def add_arguments(parser) -> None:
    from ..geometry.camera import MODELS
    from ._options import non_negative_int, positive_float

    parser.add_argument("images", nargs="?", help="folder of images (omit with --models)")
    parser.add_argument("-o", "--output", required=True, help="report folder (index.html, metrics.json/.csv, runs/)")
    parser.add_argument("--gt", help="ground truth: COLMAP model folder, *_par.txt, gt_dense_cameras/, calibration/")
    parser.add_argument("--models", nargs="+", metavar="MODEL", help="compare these existing models instead")
    parser.add_argument("--labels", nargs="+", help="names for --models in the report (default: folder names)")
    parser.add_argument("--colmap-global", action="store_true", help="also run pycolmap's global mapper")
    parser.add_argument("--no-same-matches", action="store_true",
                        help="skip COLMAP's mapper on mvrecon's database")
    parser.add_argument("--camera-mode", default="auto", choices=("auto", "single", "per-folder", "per-image"),
                        help="which images share intrinsics, for both engines (default: auto)")
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL", choices=MODELS,
                        help="COLMAP camera model for both engines (default: SIMPLE_RADIAL)")
    parser.add_argument("--camera-params", help="known intrinsics in the model's order, e.g. 1520,320,240,0")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="random seed of both engines (default: 0)")
    parser.add_argument("--mvrecon-args", default="",
                        help="extra flags for `mvrecon reconstruct` only, as one quoted string")
    parser.add_argument("--timeout", type=positive_float, help="seconds per run; a run over time is reported as failed")
    parser.add_argument("--retry-failed", action="store_true",
                        help="run again the engines whose run in OUTPUT failed (otherwise a failure is kept)")


def run(args) -> int:
    import shlex
    import sys
    from pathlib import Path

    from ..cameras import CameraConfig, parse_camera_params
    from ..errors import InputError
    from ..eval.compare import CompareConfig, compare_images, compare_models
    from ..eval.report import format_value, write_report
    from ..eval.runners import RunOptions, forget_if_failed

    if bool(args.images) == bool(args.models):
        raise InputError("give either IMAGES or --models A B (not both, not neither)")
    if args.labels and not args.models:
        raise InputError("--labels goes with --models")
    if args.images:
        from ..pipeline import require_images

        require_images(args.images)
    params = parse_camera_params(args.camera_params)
    CameraConfig(model=args.camera_model, params=params).validate()
    options = RunOptions(camera_mode=args.camera_mode, camera_model=args.camera_model, camera_params=params,
                         seed=args.seed,
                         mvrecon_args=tuple(shlex.split(args.mvrecon_args)))
    config = CompareConfig(options=options, colmap_global=args.colmap_global,
                           same_matches=not args.no_same_matches, timeout_s=args.timeout)
    if args.retry_failed and not args.models:
        for run_dir in sorted((Path(args.output) / "runs").glob("*")):
            if forget_if_failed(run_dir):
                print(f"retrying {run_dir.name} (it failed before)")
    if args.models:
        comparison = compare_models(args.models, gt=args.gt, labels=args.labels, config=config)
    else:
        comparison = compare_images(args.images, args.output, gt=args.gt, config=config)
    page = write_report(comparison, args.output)
    m = comparison.metrics
    engines = list(m["engines"])
    shown = ("registered", "points", "mean_reprojection_error_px", "auc@1", "auc@5", "median_rotation_error_deg",
             "wall_s", "time_ratio_vs_colmap", "peak_mem_mb")
    table = [(row["label"] + (f" ({row['unit']})" if row["unit"] else ""),
              [format_value(row["metric"], row["values"][e]) + ("*" if e in row["winners"] else "") for e in engines])
             for row in m["rows"] if row["metric"] in shown]
    width = max(len(t) for t in [*engines, *(t for _, texts in table for t in texts)]) + 2
    print(f"{'':34}" + "".join(f"{e:>{width}}" for e in engines))
    for label, texts in table:
        print(f"{label:34}" + "".join(f"{t:>{width}}" for t in texts))
    for name, e in m["engines"].items():
        if e["error"]:
            print(f"{name} failed: {e['error']}")
    print(f"reference: {m['reference']['name']}; report: {page}")
    if not any((e["summary"] or {}).get("registered") for e in m["engines"].values()):  # nothing compared
        print(f"mvrecon: error: {args.output}: no engine registered any image; see the runs' run.log",
              file=sys.stderr)
        return 1
    return 0
