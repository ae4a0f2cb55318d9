"""Map an existing workspace database (ours, or one COLMAP made) with mvrecon's mapper: incremental, global or in parts.

Reads WORKSPACE/database.db (keypoints and verified two-view geometries) and writes WORKSPACE/sparse/0..k/,
WORKSPACE/points.ply and WORKSPACE/report.json. This is how mapper differences are separated from front-end
differences: COLMAP's matches through our mapper, or ours through COLMAP's.

Example:
  mvrecon map -o out/ --image-dir images/
"""

import argparse
import logging
from pathlib import Path

from ..config import config_hash
from ..database import database_counts
from ..errors import InputError
from ..executor import StageClock
from ..io.files import read_json_object
from ..stages.mapping import map_workspace
from ..stages.report import write_report
from ..workspace import Workspace
from ._options import add_cluster_options, add_workspace, cluster_from_args
from .reconstruct import add_mapper_options, mapper_config, no_model

ORDER = 31
ON_INTERRUPT = "rerun the same command with --resume to continue mapping from its last snapshot"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_workspace(parser, "folder holding database.db (a run's output folder, or a COLMAP workspace)")
    parser.add_argument("--image-dir", default=None,
                        help="images, only used to colour the points (default: the image folder recorded in "
                             "the workspace's record, if it still exists; else the points stay black, with a "
                             "warning)")
    add_mapper_options(parser)
    add_cluster_options(parser)


def run(args: argparse.Namespace) -> int:
    config = mapper_config(args)
    if args.image_dir is not None and not Path(args.image_dir).is_dir():
        raise InputError(f"{args.image_dir}: no such image folder (--image-dir)")
    earlier = read_json_object(Path(args.workspace) / "report.json")  # before this run replaces it
    clock = StageClock()
    with cluster_from_args(args) as cluster:
        summary = map_workspace(config, args.workspace, image_dir=args.image_dir, text=args.text,
                                resume=args.resume, overwrite=args.overwrite, cluster=cluster)
    stage = clock.done("mapping")
    counts = database_counts(f"{args.workspace}/database.db")
    try:
        ours = Workspace(args.workspace).stage_config("features") is not None
    except InputError:  # an unreadable record that --overwrite mapped past
        ours = False
    stages = clock.stages
    if ours and earlier and earlier.get("counts") == counts and isinstance(earlier.get("stages"), dict):
        # the same database as the earlier report's: keep its front-end stages (times, memory)
        stages = {**{k: v for k, v in earlier["stages"].items() if k != "mapping"}, **clock.stages}
    write_report(args.workspace, config_hash=config_hash(config), seed=config.seed, summary=summary,
                 stages=stages, total=stage, counts=counts,
                 database={"made_by": "mvrecon" if ours else "another tool (no mvrecon features record in "
                           "the workspace)"})
    logging.getLogger("mvrecon").info("%s", summary.text())
    return 0 if summary.models else no_model(args.workspace, summary.status)
