"""Detect SIFT features in a folder of images into a workspace database.

Finds every JPEG/PNG/TIFF/BMP/PNM under IMAGES (recursively), groups them into cameras, and writes cameras, images,
keypoints and descriptors to WORKSPACE/database.db (COLMAP's schema). A rerun skips images already done; a
different config is refused unless --overwrite.

example:  mvrecon features photos/ -o work/
"""

import argparse
import logging

from ..stages.features import extract_features
from ._options import (
    add_camera_options,
    add_feature_options,
    add_run_options,
    add_workspace,
    cluster_from_args,
    frontend_config_from_args,
    warn_if_config_unread,
)

ORDER = 10
ON_INTERRUPT = "the images done are kept in the workspace; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", help="folder of images (searched recursively)")
    add_workspace(parser, "workspace folder (created if missing)")
    add_camera_options(parser)
    add_feature_options(parser)
    add_run_options(parser, config_help="in the [camera] and [sift] tables, e.g. [sift] "
                                        "max_num_features = 4096")


def run(args: argparse.Namespace) -> int:
    warn_if_config_unread(args, "features", ("camera", "sift", "workers"))
    config = frontend_config_from_args(args)
    with cluster_from_args(args) as cluster:
        summary = extract_features(config, args.images, args.workspace, overwrite=args.overwrite,
                                   cluster=cluster)
    logging.getLogger("mvrecon").info("%s", summary.text())  # as every command's summary: -q hides it
    return 0
