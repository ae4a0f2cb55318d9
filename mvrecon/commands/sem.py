"""SEM tilt-series photogrammetry (parallel projection): tilts, heights, ICP merging, a height map.

Examples:
  mvrecon sem tilt_0.png tilt_5.png tilt_10.png -o out --tilts 0,5,10 --axis y --pixel-size 0.1um
  mvrecon sem series_folder/ -o out --estimate-tilts --max-size 1000 --height-source joint

Images are taken in the order given (a folder: natural name order). Estimated tilts are relative to the
reference image and increase along that order (parallel projection cannot tell a tilt's sign from the relief's).
Outputs in OUT: height.tif (32-bit float), height.png, profile.png, points.ply (merged points), surface.ply
(height map as points), report.json (tilts, axis, scale, matches, point counts, ICP, timings, warnings, and
with --gt the height error against ground truth). A given --axis more than 5 deg from the matches' own
estimate is warned about; one view given twice (the same file, identical pixels, or matches without parallax,
also as one pair inside a longer series) and a tilt of 90 deg or more either way are refused.
"""

import argparse
import logging
import math
from pathlib import Path

from ..errors import InputError
from ..sem.heightmap import read_height_map
from ..sem.icp import IcpConfig
from ..sem.parallax import parse_axis
from ..sem.pipeline import SemConfig, parse_length_um, resolve_images, run_sem
from ._options import positive_int

ORDER = 70
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", help="tilt-series images (files in tilt order, or a folder)")
    parser.add_argument("-o", "--output", required=True, help="output folder")
    tilts = parser.add_mutually_exclusive_group(required=True)
    tilts.add_argument("--tilts", help="known tilt angles in degrees, one per image, e.g. 0,5,10; a list "
                                       "starting with a negative number needs '=': --tilts=-10,0,10")
    tilts.add_argument("--estimate-tilts", action="store_true",
                       help="estimate the tilts by affine factorisation (3 or more images)")
    parser.add_argument("--axis", help="tilt axis in the image: y (vertical), x, or degrees from +x towards +y "
                                       "(default: estimated; a given axis the matches contradict is warned "
                                       "about)")
    parser.add_argument("--pixel-size", help="size of an input pixel, e.g. 0.05um or 50nm (default: heights "
                                             "in pixels)")
    parser.add_argument("--max-size", type=positive_int,
                        help="shrink images so their long side is at most this many px (default: not shrunk)")
    parser.add_argument("--reference", type=int, help="index of the image whose grid the height map uses "
                                                      "(default: tilt closest to 0, or the middle image)")
    parser.add_argument("--pairs", type=positive_int, default=2, help="best-matched pairs merged by ICP (default 2, as "
                                                             "in the paper)")
    parser.add_argument("--icp", choices=("kdtree", "brute", "open3d-point", "open3d-plane"), default="kdtree",
                        help="ICP variant for merging the pair point sets (default kdtree)")
    parser.add_argument("--height-source", choices=("dense", "stereo", "joint", "merged"), default="dense",
                        help="what the height map is made from: dense = the joint points refined at every pixel by "
                             "least-squares matching of all images (default, most accurate); stereo = the same "
                             "refinement started from semi-global matching of the rectified pairs (reference, "
                             "other image) where they agree; joint = the joint adjustment's points interpolated; "
                             "merged = the joint points and the ICP-merged pair point sets interpolated (the paper's "
                             "integration)")
    parser.add_argument("--densify", action="store_true",
                        help="replace the height map by SGBM dense matching of one rectified pair where it matched "
                             "(reference and the image tilted farthest from it; less accurate than the default)")
    parser.add_argument("--gt", help="ground-truth height map (.npy or .tif) on the input images' grid, in um with "
                                      "--pixel-size (else input pixels): the log and report.json give the height "
                                      "error (RMS over the covered pixels, in %% of the true range) and coverage")
    parser.add_argument("--profile", help="profile line x0,y0,x1,y1 in input pixels (default: across the axis "
                                          "through the centre)")


def _floats(text: str, option: str, count: int | None = None) -> tuple:
    try:
        values = tuple(float(v) for v in text.replace(" ", "").split(",") if v != "")
    except ValueError:
        raise InputError(f"{option} {text}: expected comma-separated numbers") from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"{option} {text}: expected finite numbers")
    if count is not None and len(values) != count:
        raise InputError(f"{option} {text}: expected {count} numbers, got {len(values)}")
    return values


def _check_output_folder(output, inputs) -> None:
    """Refuse an output folder that is an input's folder or inside an input folder: the height map and figures
    written there would join the tilt series of the next run (a folder is listed with its subfolders)."""
    out = Path(output).resolve()
    for item in inputs:
        p = Path(item).resolve()
        folder = p if p.is_dir() else p.parent
        if out == folder or (p.is_dir() and folder in out.parents):
            raise InputError(f"{output}: the output folder must be outside the image folder {folder}")


def run(args: argparse.Namespace) -> int:
    try:
        axis = parse_axis(args.axis) if args.axis is not None else None
        pixel_size = parse_length_um(args.pixel_size) if args.pixel_size is not None else None
    except ValueError as exc:
        raise InputError(str(exc)) from None
    config = SemConfig(tilts_deg=_floats(args.tilts, "--tilts") if args.tilts else None, axis_deg=axis,
                       pixel_size_um=pixel_size, max_size=args.max_size, reference=args.reference,
                       pairs=args.pairs, icp_method=args.icp, height_source=args.height_source, densify=args.densify,
                       profile=_floats(args.profile, "--profile", 4) if args.profile else None, icp=IcpConfig())
    config.validate()
    _check_output_folder(args.output, args.images)
    gt = read_height_map(args.gt) if args.gt else None
    report = run_sem(resolve_images(args.images), args.output, config, gt)
    log = logging.getLogger("mvrecon.sem")
    unit = report["units"]
    hm = report["height_map"]
    log.info("tilts (deg): %s; steps: %s; axis %.2f deg; joint RMS %.3f px",
             ", ".join(f"{t:.3f}" for t in report["tilts_deg"]),
             ", ".join(f"{t:.3f}" for t in report["tilt_steps_deg"]), report["axis_deg"], report["joint"]["rms_px"])
    log.info("%d merged points from %d pair sets; height map %.1f%% filled, %.3g to %.3g %s; outputs in %s",
             report["merged_points"], len(report["pair_point_sets"]), 100 * hm["valid_fraction"],
             hm["min"] if hm["min"] is not None else float("nan"),
             hm["max"] if hm["max"] is not None else float("nan"), unit, args.output)
    accuracy = report["accuracy"]
    if accuracy is not None and accuracy["pixels"]:
        log.info("against --gt (%s): height RMS %.3g %s = %.2f%% of the range %.3g %s over %.1f%% of the pixels "
                 "(99th percentile %.2f%%)", accuracy["height_source"], accuracy["rms"], unit,
                 accuracy["rms_percent_of_range"], accuracy["range"], unit, 100 * accuracy["coverage"],
                 accuracy["p99_percent_of_range"])
        log.info("against --gt, every map made on the way: %s", "; ".join(
            f"{name} {a['rms_percent_of_range']:.2f}% over {100 * a['coverage']:.1f}%" if a["pixels"] else
            f"{name}: no pixel" for name, a in accuracy["maps"].items()))
    elif accuracy is not None:
        log.warning("warning: --gt: no pixel has both a true and an estimated height")
    return 0
