"""Calibrate a camera (or a stereo rig) from chessboard images; writes camera.toml for `stereo` and `reconstruct`.

Examples:
  mvrecon calibrate boards/ -o camera.toml                       (board size found automatically)
  mvrecon calibrate boards/ -o camera.toml --size 9x6 --square 25
  mvrecon calibrate pairs/ -o rig.toml --stereo --square 25      (pairs named left*/right*, e.g. left01.jpg)

The file holds the OPENCV model in COLMAP pixels (fx, fy, cx, cy, k1, k2, p1, p2), the RMS reprojection error per
view, the dropped outlier views and, with --stereo, R, t (x_right = R x_left + t, in square units).
Use it with `mvrecon stereo L R --camera rig.toml`, or pass its `colmap_params` line to
`--camera-model OPENCV --camera-params`.

A rerun for the same camera file continues: each image's corners are kept as they are found (in
.stages/calibrate-CAMERA.json next to the file, keyed on the image pixels, the board size and the code), so only
the images not searched yet are.
"""

import argparse
import logging
from pathlib import Path

from ..errors import InputError
from ..io.images import list_images, read_image
from ..io.record import Record
from ..stereo.calibrate import CalibrationConfig, calibrate_mono, calibrate_stereo, stereo_pairs, write_camera_toml
from ._options import check_output_file, positive_float

ORDER = 62
ON_INTERRUPT = "the corners found are kept next to the camera file (in .stages); rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", help="folder with the chessboard images")
    parser.add_argument("-o", "--output", required=True, help="camera file to write (TOML)")
    parser.add_argument("--pattern", choices=("chessboard",), default="chessboard",
                        help="calibration target (default and only choice: chessboard)")
    parser.add_argument("--size", default="auto", help="inner corners CxR, e.g. 9x6, or 'auto' (default)")
    parser.add_argument("--square", type=positive_float, default=1.0,
                        help="square size (sets the unit of the baseline; default 1)")
    parser.add_argument("--stereo", action="store_true", help="stereo rig: pair images named left*/right*")


def _board(text: str):
    if text == "auto":
        return None
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size {text!r}: expected CxR inner corners such as 9x6, or auto") from None
    if cols < 2 or rows < 2:
        raise InputError(f"--size {text!r}: a chessboard needs at least 2x2 inner corners")
    return cols, rows


def run(args: argparse.Namespace) -> int:
    log = logging.getLogger("mvrecon.calibrate")
    config = CalibrationConfig(board=_board(args.size), square=args.square)
    folder = Path(args.images)
    names, _ = list_images(folder)
    check_output_file(args.output, [folder / n for n in names])
    out = Path(args.output)
    stages = Record(out.parent, f"calibrate-{out.stem}.json")  # the corners earlier runs for this file found
    images = {}
    for name in names:  # a board image that cannot be decoded is left out, as a view without a board is
        try:
            images[name] = read_image(folder / name)
        except InputError as exc:
            log.warning("skipping %s", exc)
    if args.stereo:
        lefts, rights, pairs = stereo_pairs(names)
        pairs = [(a, b) for a, b in pairs if a in images and b in images]
        if not pairs:
            raise InputError(f"{folder}: no readable left/right image pairs (names must differ only by "
                             "left <-> right)")
    elif not images:
        raise InputError(f"{folder}: none of the images could be decoded")
    try:  # the library's messages name the images, not where they are
        if args.stereo:
            result = calibrate_stereo({a: images[a] for a, _ in pairs}, {b: images[b] for _, b in pairs}, pairs,
                                      config, stages)
            mono = [("left", result.left), ("right", result.right)]
        else:
            result = calibrate_mono(images, config, stages)
            mono = [("camera", result)]
    except InputError as exc:
        raise InputError(f"{folder}: {exc}") from None
    write_camera_toml(args.output, result, config)
    stages.prune()
    for label, m in mono:
        fx, fy, cx, cy, k1, k2, p1, p2 = m.camera.params
        log.info("%s: fx %.2f fy %.2f cx %.2f cy %.2f k1 %.4f k2 %.4f; RMS %.3f px over %d views%s", label, fx, fy,
                 cx, cy, k1, k2, m.rms_px, len(m.per_view_rms_px),
                 f"; dropped {', '.join(m.dropped)}" if m.dropped else "")
    if args.stereo:
        log.info("stereo: baseline %.4g (square units), RMS %.3f px over %d pairs", float((result.t ** 2).sum()) ** 0.5,
                 result.rms_px, len(result.per_pair_rms_px))
    if stages.reused:
        searched = [n for n in stages.used if n.startswith("corners ")]
        reused = [n for n in stages.reused if n.startswith("corners ")]
        log.info("reused from an earlier run for this camera file (%s): the corners of %s images%s", stages.path,
                 "all" if len(reused) == len(searched) else f"{len(reused)} of the {len(searched)}",
                 " and the board size search" if any(n.startswith("board size ") for n in stages.reused) else "")
    print(f"wrote {args.output}")
    return 0
