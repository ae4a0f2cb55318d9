"""Dense reconstruction of a finished run: depth maps, a fused point cloud and a mesh, on the CPU.

Reads OUT/sparse/0 (or --model) of a `mvrecon reconstruct` run and the images it was made from, and writes
COLMAP's dense workspace into OUT/dense (or -o): images/ and sparse/ undistorted to PINHOLE,
stereo/depth_maps/ and stereo/normal_maps/ (NAME.photometric.bin, NAME.geometric.bin, COLMAP's format, which
`colmap stereo_fusion` reads), previews/NAME.depth.png and .pfm, fused.ply (points, colours, normals) and mesh.ply
(Poisson). A rerun continues where an interrupted one stopped; a view without a depth map is named with the
reason.

Example:
  mvrecon dense out/
  mvrecon dense out/ -o out/dense --max-image-size 1000 --views 6
"""

import argparse
import logging

from ..dense import dense_from_run
from ._options import add_dense_options

ORDER = 33
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = "the depth maps done are kept; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="output folder of `mvrecon reconstruct` (holds sparse/0)")
    parser.add_argument("-o", "--output", default=None, help="dense folder (default: RUN/dense)")
    add_dense_options(parser)
    parser.add_argument("--model", default=None, help="model folder (default: RUN/sparse/0, the largest)")
    parser.add_argument("--image-dir", default=None, help="images (default: the folder the run was made from)")


def run(args: argparse.Namespace) -> int:
    summary = dense_from_run(args.run, args.output, model_dir=args.model, image_dir=args.image_dir,
                             max_image_size=args.max_image_size, views=args.views)
    logging.getLogger("mvrecon").info("%s", summary.text())
    return 0 if summary.views else 1
