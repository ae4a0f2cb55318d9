"""Write degraded copies of images (noise, blur, JPEG, ...) with the same names and EXIF.

The degradations compose in one fixed order, the path light takes through a camera and its software:
  downscale -> blur -> motion blur -> brightness -> Poisson noise -> Gaussian noise -> gamma -> sharpen -> JPEG
Noise is seeded per image from --seed and the file name, so the same command writes the same bytes.
8/16-bit, grey, colour and alpha images are handled (grey levels are 8-bit levels, scaled for 16-bit images).
A folder's images are the ones `reconstruct` takes (sub-folders searched; unreadable files and folders holding a
run's outputs left out, with a warning); the output keeps their sub-folder paths.

Example:
  mvrecon degrade images/ -o noisy/ --noise 10 --jpeg 50

A rerun of an interrupted command continues: images finished with the same settings are kept (the settings are
recorded in OUTPUT/.mvrecon-degrade.json; other settings need another output folder).
"""

import argparse
import logging

from ..study.degrade import Degradation, degrade_folder
from ._options import non_negative_int

ORDER = 60
HOLDS_OUTPUT = True  # its -o folder is held against a second run (`io.files.hold_folder`)
ON_INTERRUPT = "finished images are kept; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images",
                        help="an image folder (JPEG, PNG, TIFF, BMP, PNM; sub-folders too) or a single image")
    parser.add_argument("-o", "--output", required=True,
                        help="output folder, outside IMAGES (created; files keep their names and sub-folders)")
    g = parser.add_argument_group("degradations (defaults leave the image unchanged)")
    g.add_argument("--downscale", type=float, default=1.0, metavar="F", help="divide width and height by F (>= 1)")
    g.add_argument("--blur", type=float, default=0.0, metavar="SIGMA", help="Gaussian blur sigma in pixels")
    g.add_argument("--motion", type=float, default=0.0, metavar="LENGTH", help="motion blur length in pixels")
    g.add_argument("--motion-angle", type=float, default=0.0, metavar="DEG",
                   help="motion direction, degrees counter-clockwise from the x axis (default 0)")
    g.add_argument("--brightness", type=float, default=1.0, metavar="GAIN", help="exposure gain (1 = unchanged)")
    g.add_argument("--poisson", type=float, default=0.0, metavar="PEAK",
                   help="shot noise with PEAK photo-electrons at full scale (lower = noisier; 0 = off)")
    g.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                   help="additive Gaussian noise, sigma in 8-bit grey levels")
    g.add_argument("--gamma", type=float, default=1.0, metavar="G", help="tone curve out = in**G (1 = unchanged)")
    g.add_argument("--sharpen", type=float, default=0.0, metavar="AMOUNT", help="unsharp mask amount (0 = off)")
    g.add_argument("--sharpen-radius", type=float, default=1.0, metavar="SIGMA",
                   help="unsharp mask Gaussian sigma in pixels (default 1)")
    g.add_argument("--jpeg", type=int, default=0, metavar="QUALITY", help="JPEG re-compression quality 1..100")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="random seed of the noise (default 0)")


def degradation_from_args(args: argparse.Namespace) -> Degradation:
    return Degradation(downscale=args.downscale, blur_sigma=args.blur, motion_length=args.motion,
                       motion_angle=args.motion_angle, brightness=args.brightness, poisson_peak=args.poisson,
                       noise_sigma=args.noise, gamma=args.gamma, sharpen_amount=args.sharpen,
                       sharpen_radius=args.sharpen_radius, jpeg_quality=args.jpeg)


def run(args: argparse.Namespace) -> int:
    deg = degradation_from_args(args)
    written = degrade_folder(args.images, args.output, deg, seed=args.seed)
    logging.getLogger("mvrecon").info("%d images -> %s (%s; order %s)", len(written), args.output, deg.describe(),
                                      " -> ".join(deg.active()) or "copy")
    return 0
