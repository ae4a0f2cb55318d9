"""Two-view stereo (the seed paper): SIFT matches, eight-point F, rectification, disparity, depth, point cloud.

Examples:
  mvrecon stereo im0.png im1.png -o out --calib calib.txt --method best --gt disp0GT.pfm --mask mask0nocc.png
  mvrecon stereo left.jpg right.jpg -o out --camera camera.toml --method sgbm
  mvrecon stereo a.png b.png -o out --method gee          (uncalibrated: Hartley rectification, disparity only)
  mvrecon stereo left.png right.png -o out --rectified --gt disp_left.tif --mask occlusion.png   (Cones 2003)

Outputs in OUT: matches_epipolar.png, rectified_{left,right}.png, rectified_pair.png, disparity.pfm,
disparity.png (16-bit, 256 d, 0 = hole), disparity_view.png, depth.pfm, depth_view.png and cloud.ply (with a
calibration), error_map.png (with --gt), report.json. A rerun into the same OUT reuses the stages done before
with the same inputs and settings (SIFT matches and F, each method's disparity, the figures; kept in OUT/.stages).
"""

import argparse
import logging
from dataclasses import replace

from ..geometry.fundamental import RansacConfig
from ..stereo.evaluate import format_table
from ..stereo.gee import GEEConfig
from ..stereo.pipeline import StereoConfig, run_stereo
from ._options import positive_float, positive_int

ORDER = 60
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = ("the matches, disparities and figures done are kept in the output folder; rerun the same command "
                "to continue")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("left", help="left image (the reference view)")
    parser.add_argument("right", help="right image")
    parser.add_argument("-o", "--output", required=True, help="output folder")
    cal = parser.add_mutually_exclusive_group()
    cal.add_argument("--calib", help="Middlebury calib.txt (the pair is already rectified)")
    cal.add_argument("--camera", help="camera.toml from `mvrecon calibrate --stereo` (undistort + rectify)")
    cal.add_argument("--rectified", action="store_true",
                     help="the pair is already rectified but has no calib.txt: skip rectification (no depth)")
    parser.add_argument("--method", choices=("gee", "sgbm", "best"), default="best",
                        help="gee: the paper's global error energy minimisation; sgbm: OpenCV; best: census SGM "
                             "with left-right check, sub-pixel, hole filling, weighted median (default)")
    parser.add_argument("--gt", help="ground-truth disparity (.pfm inf=unknown, .npz, .tif 0=unknown, .png)")
    parser.add_argument("--gt-scale", type=positive_float, default=1.0,
                        help="divide the ground truth by this (default 1; 4 for Middlebury 2003 PNGs); "
                             "with --gt")
    parser.add_argument("--mask", help="non-occlusion mask (brightest value = non-occluded); with --gt")
    parser.add_argument("--min-disparity", type=int, help="search range start (default: calib/matches)")
    parser.add_argument("--num-disparities", type=positive_int, help="search range length (default: calib/matches)")
    parser.add_argument("--ransac-threshold", type=positive_float, default=1.0,
                        help="Sampson inlier threshold, px (default 1)")
    parser.add_argument("--gee-window", type=positive_int, help="gee: error-energy window n=m in px (default 9)")
    parser.add_argument("--gee-iterations", type=positive_int, help="gee: averaging-filter iterations (default 16)")
    parser.add_argument("--gee-alpha", type=positive_float,
                        help="gee: reliability tolerance; estimates above alpha * mean energy are removed (default 3)")


def run(args: argparse.Namespace) -> int:
    gee = {k: v for k, v in (("window", args.gee_window), ("smoothing_iterations", args.gee_iterations),
                             ("alpha", args.gee_alpha)) if v is not None}
    config = StereoConfig(method=args.method, min_disparity=args.min_disparity,
                          num_disparities=args.num_disparities,
                          ransac=replace(RansacConfig(), threshold=args.ransac_threshold),
                          gee=replace(GEEConfig(), **gee))
    report = run_stereo(config, args.left, args.right, args.output, calib_path=args.calib, camera_path=args.camera,
                        gt_path=args.gt, mask_path=args.mask, gt_scale=args.gt_scale, rectified=args.rectified)
    log = logging.getLogger("mvrecon.stereo")
    cv = report.get("opencv", {})
    log.info("%d matches, %d F inliers (median Sampson %.3f px; OpenCV's F on our inliers %.3f px)",
             report["matches"], report["inliers"], report["sampson_median_px"],
             cv.get("sampson_median_px_of_our_inliers", float("nan")))
    vd = report["vertical_disparity_px"]
    log.info("%s rectification: vertical disparity of inliers median %.2f px, 95%% %.2f px; disparity range %s",
             report["rectification"], vd["median"], vd["p95"], report["disparity_range"])
    log.info("%s disparity: %.1f %% holes, %.1f s%s", args.method, report["invalid_percent"],
             report["timings_s"]["disparity"], " (earlier run, reused)" if f"disparity_{args.method}" in
             report["reused"] else "")
    if "metrics" in report:
        print(format_table({args.method: report["metrics"]}))
    print(f"wrote {args.output}/report.json")
    return 0
