"""Degradation study: how noise, blur, JPEG and more hurt each engine's reconstruction.

For each degradation and level (one degradation varied at a time), degrades the images, runs every engine
(mvrecon and COLMAP through pycolmap) and measures registered %, points, track length, reprojection error,
relative-pose AUC@1/5 (against --gt, else against each engine's own clean reconstruction), keypoints per image,
verified inliers per pair and wall time. Cells are cached in STUDY: an interrupted study resumes and a wider
grid reuses what exists. Writes study.csv, plots/, contact_sheet.png and study.html with each engine's breaking
point per degradation (the first level where registered % or AUC@5 drops below half of the clean value).

Example:
  mvrecon study images/ -o study/ --noise 0,5,10,20,40 --blur 0,1,2,4 --jpeg 95,75,50,25,10 --gt templeR_par.txt
"""

import argparse
import logging
import shlex
import sys
from pathlib import Path

from ..cameras import CAMERA_MODES, CameraConfig, parse_camera_params
from ..errors import InputError
from ..eval.runners import COLMAP_ENGINES, RunOptions, check_run_masks, colmap_fisheye_warning
from ..geometry.camera import MODELS
from ..stages.features import require_images
from ..study.config import StudyConfig
from ..study.degrade import Degradation
from ..study.grid import AXES, Grid, parse_levels
from ..study.study import breaking_points, run_study
from ._options import non_negative_int, positive_float

ORDER = 61
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = "finished cells are kept; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", help="folder of the clean images (searched with its sub-folders, as reconstruct "
                                       "searches it)")
    parser.add_argument("-o", "--output", required=True, metavar="STUDY", help="study folder (created; reused)")
    parser.add_argument("--gt", metavar="MODEL",
                        help="ground truth: COLMAP model folder, Middlebury *_par.txt, Strecha gt_dense_cameras/, "
                             "IMC calibration/ (default: each engine's clean reconstruction)")
    g = parser.add_argument_group("grid (comma-separated levels, mild to severe; a 0 / identity level is the "
                                  "clean run)")
    for axis in AXES.values():
        g.add_argument(f"--{axis.name}", metavar="LEVELS", help=axis.label)
    g.add_argument("--motion-angle", type=float, default=0.0, metavar="DEG",
                   help="direction of the motion blur (default 0 = horizontal)")
    parser.add_argument("--engines", default="mvrecon,colmap",
                        help="engines to compare: mvrecon, colmap, colmap-global (default mvrecon,colmap)")
    parser.add_argument("--jobs", type=non_negative_int, default=0,
                        help="cells run at the same time (default: CPU cores)")
    parser.add_argument("--seed", type=non_negative_int, default=0,
                        help="seed of the noise and of both engines (default 0)")
    parser.add_argument("--camera-mode", default="auto", choices=CAMERA_MODES,
                        help="camera sharing for both engines (default auto)")
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL", choices=MODELS,
                        help="COLMAP camera model (default SIMPLE_RADIAL)")
    parser.add_argument("--camera-params", metavar="PARAMS",
                        help="known intrinsics of the clean images in the model's order, trusted and held fixed "
                             "in both engines, e.g. 285,285,320,240,0,0,0,0 for OPENCV_FISHEYE (which COLMAP "
                             "needs to verify any pair of it; default: estimated)")
    parser.add_argument("--masks", metavar="DIR",
                        help="image masks for both engines, in COLMAP's layout (the mask of IMAGES/a.jpg is "
                             "DIR/a.jpg.png; no features where it is black); not with --downscale")
    parser.add_argument("--timeout", type=positive_float, default=None, metavar="S",
                        help="seconds per engine run (default: no limit); a run past it counts as failed")
    parser.add_argument("--retry-failed", action="store_true",
                        help="rerun cells whose engine run failed or timed out before (else failures are kept)")


def run(args: argparse.Namespace) -> int:
    listing = require_images(args.images)  # the images reconstruct takes: every cell is made from these
    images, out = Path(args.images).resolve(), Path(args.output).resolve()
    if out == images or images in out.parents:  # its degraded copies would count as images of the clean run
        raise InputError(f"{args.output}: inside the image folder {args.images}; choose an output folder outside it")
    levels = {name: parse_levels(name, getattr(args, name)) for name in AXES if getattr(args, name) is not None}
    grid = Grid(levels)
    params = parse_camera_params(args.camera_params)
    CameraConfig(model=args.camera_model, params=params).validate()
    config = StudyConfig(images=Path(args.images), gt=Path(args.gt) if args.gt else None,
                         engines=tuple(e.strip() for e in args.engines.split(",") if e.strip()), seed=args.seed,
                         base=Degradation(motion_angle=args.motion_angle),
                         run_options=RunOptions(camera_mode=args.camera_mode, camera_model=args.camera_model,
                                                camera_params=params, seed=args.seed,
                                                masks=str(Path(args.masks).resolve()) if args.masks else ""),
                         jobs=args.jobs, timeout_s=args.timeout)
    config.check_grid(grid, args.downscale)
    log = logging.getLogger("mvrecon")
    masks_warning = check_run_masks(config.run_options, args.images, listing[0])  # raises on a mask that misfits
    if set(config.engines) & set(COLMAP_ENGINES):
        for warning in (masks_warning, colmap_fisheye_warning(config.run_options, args.images, listing[0])):
            if warning:
                log.warning("%s", warning)
    command = "mvrecon " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    rows = run_study(config, grid, args.output, command=command, retry_failed=args.retry_failed, listing=listing)
    for (engine, axis), verdict in breaking_points(rows).items():
        where = ("holds at every level" if verdict["level"] is None and verdict["metric"] is None else
                 verdict["metric"] if verdict["level"] is None else
                 f"breaks at {axis} {verdict['level']:g} ({verdict['metric']})")
        log.info("%-8s %-10s %s", engine, axis, where)
    log.info("wrote %s/study.csv and %s/study.html", args.output, args.output)
    return 0
