"""Compare mvrecon with COLMAP on the same images (or compare existing models), with an HTML report.

  mvrecon compare IMAGES -o REPORT [--gt GT] [--colmap-global | --global-mappers]
      runs mvrecon end to end, pycolmap end to end (extract_features, match_exhaustive, incremental_mapping;
      --colmap-global adds global_mapping; --global-mappers adds it and mvrecon's global mapper, `--mapper
      global`, as engine mvrecon-global) and COLMAP's incremental mapper on mvrecon's database ("same matches"),
      with the same camera settings; the runs go to REPORT/runs/ and a finished run is reused, not redone.
      --mvrecon-args "--upright" (one string) gives mvrecon's run more flags, checked before anything runs.
  mvrecon compare --models A [B ...] [--labels ...] [--gt GT] -o REPORT
      compares models that exist: run folders (report.json + sparse/), sparse/ folders or COLMAP model folders;
      one model is scored against --gt, without it two or more are needed.

Each model is aligned to the reference (GT when given, else COLMAP's model; with --models, the last one) by a
robust Sim3 of camera centres. Without GT, a reference whose model holds fewer images than another's, or under
half of them, is not trusted: the model with the most images is scored against instead, or none, and the report
says so at its top. GT: a COLMAP model folder, a Middlebury *_par.txt, a Strecha gt_dense_cameras/
folder or an IMC calibration/ folder. Writes REPORT/index.html (self-contained), metrics.json and metrics.csv.
"""

import argparse
import dataclasses
import logging
import shlex
import sys
from pathlib import Path

from ..cameras import CAMERA_MODES, CameraConfig, parse_camera_params
from ..errors import InputError
from ..eval.compare import CompareConfig, compare_images, compare_models
from ..eval.report import format_value, other_models_text, write_report
from ..eval.runners import RunOptions, check_run_masks, colmap_fisheye_warning, forget_if_failed, reconstruct_args
from ..geometry.camera import MODELS
from ..stages.features import require_images
from . import reconstruct
from ._options import config_file, flag_name, frontend_config_from_args, non_negative_int, positive_float

ORDER = 60
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = "finished runs are kept; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="?", help="folder of images (omit with --models)")
    parser.add_argument("-o", "--output", required=True, help="report folder (index.html, metrics.json/.csv, runs/)")
    parser.add_argument("--gt", help="ground truth: COLMAP model folder, *_par.txt, gt_dense_cameras/, calibration/")
    parser.add_argument("--models", nargs="+", metavar="MODEL",
                        help="compare these existing models instead (one is enough with --gt)")
    parser.add_argument("--labels", nargs="+",
                        help="names for --models in the report (default: a run folder's engine from its "
                             "report.json, e.g. mvrecon; another folder's name, without sparse/ and model "
                             "numbers; a repeated name gets a ' added)")
    # the options of runs on IMAGES default to None, so that --models can tell one given and refuse it
    parser.add_argument("--colmap-global", action="store_true", help="also run pycolmap's global mapper")
    parser.add_argument("--global-mappers", action="store_true",
                        help="also run both global mappers: mvrecon's (--mapper global) and pycolmap's")
    parser.add_argument("--no-same-matches", action="store_true",
                        help="skip COLMAP's mapper on mvrecon's database")
    parser.add_argument("--camera-mode", choices=CAMERA_MODES,
                        help="which images share intrinsics, for both engines (default: auto)")
    parser.add_argument("--camera-model", choices=MODELS,
                        help="COLMAP camera model for both engines (default: SIMPLE_RADIAL)")
    parser.add_argument("--camera-params", help="known intrinsics in the model's order, e.g. 1520,320,240,0")
    parser.add_argument("--seed", type=non_negative_int, help="random seed of both engines (default: 0)")
    parser.add_argument("--masks", metavar="DIR",
                        help="image masks for both engines, in COLMAP's layout (the mask of IMAGES/a.jpg is "
                             "DIR/a.jpg.png; no features where it is black)")
    parser.add_argument("--mvrecon-args", metavar="FLAGS",
                        help='extra flags for `mvrecon reconstruct` only, as one quoted string, e.g. '
                             '--mvrecon-args "--upright --max-features 4000"')
    parser.add_argument("--timeout", type=positive_float,
                        help="seconds per run (default: no limit); a run over time is reported as failed")
    parser.add_argument("--retry-failed", action="store_true",
                        help="run again the engines whose run in OUTPUT failed (otherwise a failure is kept)")


RUN_ONLY = ("colmap_global", "global_mappers", "no_same_matches", "camera_mode", "camera_model", "camera_params",
            "seed", "masks", "mvrecon_args", "timeout", "retry_failed")  # the dests only a run on IMAGES uses


def check_mvrecon_args(options: RunOptions) -> None:
    """Refuse, before any engine runs, extra flags that `mvrecon reconstruct` would reject (a misspelt one
    failed mvrecon's run only after COLMAP's, and compare still exited 0) and flags that would override what
    compare sets for both engines (the comparison would no longer be like for like). The flags are parsed by
    reconstruct's own parser, in the very command `run_mvrecon` runs, and their values checked as reconstruct
    checks them (bounds, a --config file)."""
    if not options.mvrecon_args:
        return

    class Parser(argparse.ArgumentParser):
        def error(self, message):
            raise InputError(f"--mvrecon-args: {message} (see `mvrecon reconstruct --help`)")

    parser = Parser(prog="mvrecon reconstruct", add_help=False)
    parser.add_argument("-v", "--verbose", action="count", default=0)
    parser.add_argument("-q", "--quiet", action="store_true")
    reconstruct.add_arguments(parser)
    given = parser.parse_args(reconstruct_args("IMAGES", "OUT", options)[1:])
    plain = parser.parse_args(reconstruct_args("IMAGES", "OUT", dataclasses.replace(options, mvrecon_args=()))[1:])
    if given.output != plain.output:
        raise InputError("--mvrecon-args: -o/--output is compare's to choose (mvrecon's run goes to "
                         "OUTPUT/runs/mvrecon); leave it out")
    own = [flag_name(dest) for dest in ("seed", "camera_mode", "camera_model", "camera_params", "masks")
           if getattr(given, dest) != getattr(plain, dest)]
    if own:
        raise InputError(f"--mvrecon-args: {', '.join(own)} would make mvrecon's run differ from COLMAP's; give "
                         f"{', '.join(own)} as {'an option' if len(own) == 1 else 'options'} of "
                         f"{'its' if len(own) == 1 else 'their'} own, which go to both engines")
    try:
        from_file = config_file(given)
        frontend_config_from_args(given, from_file)
        reconstruct.mapper_config(given, from_file)
    except InputError as exc:
        raise InputError(f"--mvrecon-args: {exc}") from None


def run(args: argparse.Namespace) -> int:
    if bool(args.images) == bool(args.models):
        raise InputError("give either IMAGES or --models A B (not both, not neither)")
    if args.labels and not args.models:
        raise InputError("--labels goes with --models")
    if args.models:
        given = [flag_name(dest) for dest in RUN_ONLY if getattr(args, dest) is not None
                 and getattr(args, dest) is not False]  # `--seed 0` is given too (0 == False)
        if given:
            raise InputError(f"{', '.join(given)}: only for runs on IMAGES; --models compares models that exist, "
                             f"so {'it' if len(given) == 1 else 'they'} would have no effect")
    params = parse_camera_params(args.camera_params)
    chosen = {dest: getattr(args, dest) for dest in ("camera_mode", "camera_model", "seed")
              if getattr(args, dest) is not None}  # the others keep RunOptions' defaults
    CameraConfig(model=chosen.get("camera_model", RunOptions.camera_model), params=params).validate()
    try:
        extra = tuple(shlex.split(args.mvrecon_args or ""))
    except ValueError as exc:  # an unclosed quote
        raise InputError(f"--mvrecon-args: {exc}") from None
    options = RunOptions(**chosen, camera_params=params, mvrecon_args=extra,
                         masks=str(Path(args.masks).resolve()) if args.masks else "")
    config = CompareConfig(options=options, colmap_global=args.colmap_global or args.global_mappers,
                           mvrecon_global=args.global_mappers,
                           same_matches=not args.no_same_matches, timeout_s=args.timeout)
    if args.images:
        check_mvrecon_args(options)
        listing = require_images(args.images)  # listed once: its warnings are printed once
        for warning in (check_run_masks(options, args.images, listing[0]),
                        colmap_fisheye_warning(options, args.images, listing[0])):
            if warning:
                logging.getLogger("mvrecon").warning("%s", warning)
    if args.retry_failed:
        for run_dir in sorted((Path(args.output) / "runs").glob("*")):
            if forget_if_failed(run_dir):
                print(f"retrying {run_dir.name} (it failed before)")
    if args.models:
        comparison = compare_models(args.models, gt=args.gt, labels=args.labels, config=config)
    else:
        comparison = compare_images(args.images, args.output, gt=args.gt, config=config, listing=listing)
    page = write_report(comparison, args.output)
    m = comparison.metrics
    engines = list(m["engines"])
    shown = ("registered", "points", "mean_reprojection_error_px", "auc@1", "auc@5", "median_rotation_error_deg",
             "wall_s", "time_ratio_vs_colmap", "peak_mem_mb")
    table = [(row["label"] + (f" ({row['unit']})" if row["unit"] else ""),
              [format_value(row["metric"], row["values"][e])
               + (other_models_text(m["engines"][e]["summary"]) if row["metric"] == "registered" else "")
               + ("*" if e in row["winners"] else "") for e in engines])
             for row in m["rows"] if row["metric"] in shown]
    width = max(len(t) for t in [*engines, *(t for _, texts in table for t in texts)]) + 2
    print(f"{'':34}" + "".join(f"{e:>{width}}" for e in engines))
    for label, texts in table:
        print(f"{label:34}" + "".join(f"{t:>{width}}" for t in texts))
    for name, e in m["engines"].items():
        if e["error"]:
            print(f"{name} failed: {e['error']}")
    if m["reference"]["note"]:
        logging.getLogger("mvrecon").warning("%s: %s", args.output, m["reference"]["note"])
    print(f"reference: {m['reference']['name'] or 'none'}; report: {page}")
    if not any((e["summary"] or {}).get("registered") for e in m["engines"].values()):  # nothing compared
        print(f"mvrecon: error: {args.output}: no engine registered any image; see the runs' run.log",
              file=sys.stderr)
        return 1
    return 0
