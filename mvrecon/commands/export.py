"""Export a reconstruction: undistorted images + PINHOLE model for nerfstudio / Gaussian splatting.

Reads OUT/sparse/0 (or --model) of a `mvrecon reconstruct` run, takes the images from the run's image folder
(recorded in OUT/.stages/record.json) or --image-dir, and writes DIR/images/ and DIR/sparse/0/. The run's folder is held
while it is read: while another run writes it (a `reconstruct --overwrite`, a `map`), the export is refused
instead of reading a half-made model.

Example:
  mvrecon export out/ -o out/splat
  ns-train splatfacto colmap --data out/splat     (nerfstudio)
"""

import argparse
import logging
from pathlib import Path

from ..errors import InputError
from ..io.undistort import export_undistorted
from ..workspace import Workspace
from ._options import positive_int

ORDER = 32
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = "the export is written aside and moved into place when complete; rerun the same command"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="output folder of `mvrecon reconstruct` (holds sparse/0)")
    parser.add_argument("--undistort", action="store_true",
                        help="write undistorted images and a PINHOLE model: the only export so far, so the "
                             "default (the flag is still accepted)")
    parser.add_argument("-o", "--output", required=True, help="export folder")
    parser.add_argument("--model", default=None, help="model folder (default: RUN/sparse/0, the largest)")
    parser.add_argument("--image-dir", default=None,
                        help="images (default: the folder the run was made from)")
    parser.add_argument("--max-image-size", type=positive_int, default=-1,
                        help="downscale so the long side fits (default: full size)")
    parser.add_argument("--text", action="store_true", help="also write the model as text")


def run(args: argparse.Namespace) -> int:
    run_dir = Path(args.run)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run folder (the output folder of `mvrecon reconstruct`)")
    with Workspace(run_dir).lock():  # another run writing the folder is refused, as `map` refuses it
        model = Path(args.model) if args.model else run_dir / "sparse" / "0"
        image_dir = args.image_dir
        if image_dir is None:
            features = Workspace(run_dir).stage_config("features")
            if not features or "images" not in features:
                raise InputError(f"{run_dir}: cannot tell where its images are; pass --image-dir")
            image_dir = features["images"]
        # the database the model was mapped from tells the frame of EXIF-rotated images (COLMAP's are as
        # stored); without one (a bare model folder) the model's camera sizes do
        target = export_undistorted(model, image_dir, args.output, max_image_size=args.max_image_size,
                                    text=args.text, database=run_dir / "database.db")
    logging.getLogger("mvrecon").info("%s: undistorted images in %s, PINHOLE model in %s", args.output,
                                      Path(args.output) / "images", target)
    return 0
