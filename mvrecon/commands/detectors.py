"""Compare keypoint detectors (the seed paper's Table 1, extended): SIFT, SURF, FAST, ORB, AKAZE, BRISK.

Examples:
  mvrecon detectors photos/ -o table.md
  mvrecon detectors im0.png im1.png other0.png other1.png --pairs -o table.md

For every image: keypoints per detector and detection time. Per detector: repeatability under a known warp of each
image (rotation by --angle degrees and zoom by --scale about the centre, keypoints within 2.5 px), and, with
--pairs (consecutive images form pairs A, B), the matches verified by a fundamental matrix between A and B.
Writes the markdown table to -o and the same figures as CSV next to it (table.csv).

A rerun into the same table continues: each image's (and pair's) figures per detector are kept as they are measured
(in .stages/detectors-TABLE.json next to the table, keyed on the image pixels, the settings and the code), so
only the missing ones are computed; reused figures keep the times measured then, and the log names them.
"""

import argparse
import logging
from pathlib import Path

from ..features.detector_table import DetectorTableConfig, collect_images, measure_table, write_table
from ._options import check_output_file, finite_float, positive_float

ORDER = 64
ON_INTERRUPT = "the images done are kept next to the table (in .stages); rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", help="image files and/or folders of images")
    parser.add_argument("-o", "--output", required=True, help="markdown table to write (a .csv is written too)")
    parser.add_argument("--pairs", action="store_true", help="consecutive images form pairs (A, B)")
    parser.add_argument("--detectors", default="SIFT,SURF,FAST,ORB,AKAZE,BRISK",
                        help="comma-separated list (default: SIFT,SURF,FAST,ORB,AKAZE,BRISK)")
    parser.add_argument("--angle", type=finite_float, default=20.0,
                        help="rotation of the repeatability warp in degrees (default 20)")
    parser.add_argument("--scale", type=positive_float, default=0.8,
                        help="zoom of the repeatability warp (default 0.8)")


def run(args: argparse.Namespace) -> int:
    config = DetectorTableConfig(detectors=args.detectors, angle=args.angle, scale=args.scale,
                                 pairs=args.pairs)
    config.validate()
    paths = collect_images(args.inputs)
    config.check_images(paths)
    out = Path(args.output)
    for path in (out, out.with_suffix(".csv")):
        check_output_file(path, paths)
    table = measure_table(config, paths, out)
    lines = write_table(table, out)
    log = logging.getLogger("mvrecon.detectors")
    log.info("\n".join(lines))
    if table.reused_images or table.reused_pairs:
        log.info("reused from an earlier run into this table (%s), with the times measured then: %s",
                 table.cache_path, table.reused_text())
    print(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0
