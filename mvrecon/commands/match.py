"""Match and geometrically verify image pairs of a workspace (after `mvrecon features`).

Selects pairs (exhaustive, sequential:K, retrieval:K or a pairs file), matches SIFT descriptors (ratio test,
mutual check), verifies each pair with F/E/H (USAC MAGSAC++) and stores raw matches and verified two-view geometries in
WORKSPACE/database.db, ready for a mapper (ours or COLMAP's). A rerun skips pairs already done.

example:  mvrecon match -o work/ --pairs sequential:10
"""

import argparse
import logging

from ..stages.matching import match
from ._options import (
    add_matching_options,
    add_run_options,
    add_workspace,
    cluster_from_args,
    frontend_config_from_args,
    warn_if_config_unread,
)

ORDER = 20
ON_INTERRUPT = "the pairs done are kept in the workspace; rerun the same command to continue"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_workspace(parser, "workspace folder made by `mvrecon features`")
    add_matching_options(parser)
    add_run_options(parser, config_help='pairs = "sequential:5" and the [matcher] and [verify] tables, e.g. '
                                        "[verify] max_error = 2.0")


def run(args: argparse.Namespace) -> int:
    warn_if_config_unread(args, "match", ("pairs", "matcher", "verify", "workers"))
    config = frontend_config_from_args(args)
    with cluster_from_args(args) as cluster:
        summary = match(config, args.workspace, overwrite=args.overwrite, cluster=cluster)
    logging.getLogger("mvrecon").info("%s", summary.text())  # as every command's summary: -q hides it
    return 0
