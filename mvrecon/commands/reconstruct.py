"""Reconstruct a folder of images: features, matches, incremental SfM; writes COLMAP models.

Writes OUT/database.db (COLMAP schema), OUT/sparse/0..k/ (binary COLMAP models, 0 = largest; --text adds
.txt),
OUT/points.ply (coloured points of the largest model) and OUT/report.json (per-image status and reason, model
statistics, per-stage wall time and peak memory). A finished run with the same settings is not redone; an
interrupted one resumes (features and matches are kept; --resume continues mapping from its snapshot).

Examples:
  mvrecon reconstruct images/ -o out/
  mvrecon reconstruct images/ -o out/ --camera-model PINHOLE --camera-params 1520,1520,302,246 --text
"""

import argparse
import logging
import re
from collections import Counter
from pathlib import Path

from ..config import with_overrides
from ..errors import InputError
from ..pipeline import ReconstructConfig, reconstruct
from ..sfm.config import FRAMES, MAPPERS, OPTIMIZERS, MapperConfig
from ..stages.common import FrontendConfig
from ._options import (
    add_dense_options,
    add_frontend_options,
    add_workspace,
    cluster_from_args,
    config_file,
    frontend_config_from_args,
    non_negative_int,
)

ORDER = 30
ON_INTERRUPT = ("features and matches done are kept; rerun the same command to continue, with --resume "
                "to continue mapping from its last snapshot too")


def add_mapper_options(parser: argparse.ArgumentParser, *, standalone: bool = True) -> None:
    """Mapper flags shared by `reconstruct` and `map`; only the standalone `map` adds its own --config and
    --overwrite (`reconstruct` has them from the front end's options, and one --config file holds both)."""
    g = parser.add_argument_group("mapping")
    g.add_argument("--seed", type=non_negative_int, default=None,
                   help="random seed: equal inputs and seed give equal models (default 0)")
    g.add_argument("--mapper", choices=MAPPERS, default=None,
                   help="incremental (default: image by image, as COLMAP's) or global (all poses at once by "
                        "rotation and translation averaging, then bundle adjustment; see docs/global-mapper.md)")
    g.add_argument("--partition-size", type=non_negative_int, default=None, metavar="P",
                   help="map the view graph in overlapping parts of at most P images (at least 10), each its own "
                        "task on the process pool, then merge them by similarity transforms and refine the whole "
                        "by one bundle adjustment (default 0: the whole set at once)")
    g.add_argument("--frame", choices=FRAMES, default=None,
                   help="with camera position priors (EXIF GPS or --pose-priors): the model in metres east, north, "
                        "up of the origin in report.json (enu, default) or earth-centred (ecef); docs/georef.md")
    g.add_argument("--optimizer", choices=OPTIMIZERS, default=None,
                   help="GTSAM optimizer for bundle adjustment: plain Levenberg-Marquardt with the points "
                        "eliminated first (lm, default) or SfmLevenbergMarquardt with Schur elimination (sfm)")
    g.add_argument("--fix-intrinsics", action="store_true", help="do not refine focal length and distortion")
    g.add_argument("--text", action="store_true", help="also write the models as COLMAP text files")
    g.add_argument("--resume", action="store_true", help="continue an interrupted mapping from its snapshot")
    if standalone:
        g.add_argument("--config", default=None, metavar="TOML",
                       help="mapper settings in a [mapper] table, e.g. abs_pose_min_inliers = 20 "
                            "(flags win over the file)")
        g.add_argument("--overwrite", action="store_true", help="start mapping over even with a snapshot")


def mapper_config(args: argparse.Namespace,
                  from_file: tuple[FrontendConfig, dict] | None = None) -> MapperConfig:
    """MapperConfig = defaults < the [mapper] table of --config < flags given on the command line.
    `from_file`: what `config_file(args)` returned, when the caller has read the file already."""
    table = (from_file or config_file(args))[1]
    config = with_overrides(MapperConfig(), table, source=f"{args.config}: mapper")
    flags = {"seed": args.seed, "optimizer": args.optimizer, "mapper": args.mapper,
             "partition_size": args.partition_size, "frame": args.frame}
    if args.fix_intrinsics:
        flags["refine_intrinsics"] = False
    config = with_overrides(config, {k: v for k, v in flags.items() if v is not None}, source="command line")
    config.validate(args.config)
    return config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", help="folder of images (searched recursively)")
    add_workspace(parser, "output folder (the workspace)", dest="output")
    add_frontend_options(parser)
    add_mapper_options(parser, standalone=False)
    g = parser.add_argument_group("dense")
    g.add_argument("--dense", action="store_true",
                   help="then run `mvrecon dense` on the largest model: depth maps, fused.ply and mesh.ply in "
                        "OUT/dense")
    add_dense_options(g, prefix="dense-")


def run(args: argparse.Namespace) -> int:
    if not Path(args.images).is_dir():
        raise InputError(f"{args.images}: not a folder of images")
    from_file = config_file(args)  # read once for both configs
    config = ReconstructConfig(frontend=frontend_config_from_args(args, from_file),
                               mapper=mapper_config(args, from_file))
    with cluster_from_args(args) as cluster:
        report = reconstruct(config, args.images, args.output, text=args.text, resume=args.resume,
                             overwrite=args.overwrite, cluster=cluster)
    log = logging.getLogger("mvrecon")
    registered = sum(1 for s in report["images"].values() if s["status"] == "registered")
    if not report["models"]:
        return no_model(args.output, report["images"])
    log.info("%s: %d of %d images registered in %d model(s): sparse/, points.ply, report.json",
             args.output, registered, len(report["images"]), len(report["models"]))
    if args.dense:
        # OpenCV and numba load after the feature workers have forked (executor._get_context)
        from ..dense import dense_from_run  # noqa: PLC0415 - see above

        summary = dense_from_run(args.output, image_dir=args.images, max_image_size=args.dense_max_image_size,
                                 views=args.dense_views)
        log.info("%s", summary.text())
    return 0


def no_model(out: Path | str, status: dict) -> int:
    """Exit code 1 and one error line when mapping made no model: the input was readable (bad input exits 2
    earlier), but the run failed. `status`: image name -> {"status", "reason", ...}, as in report.json."""
    reasons = [s["reason"] for s in status.values()]
    kinds = [_reason_kind(r) for r in reasons]
    kind, count = Counter(kinds).most_common(1)[0]
    reason, exact = Counter(r for r, k in zip(reasons, kinds) if k == kind).most_common(1)[0]
    logging.getLogger("mvrecon").error("%s: no model: none of the %d images could be registered (%d of them: %s%s); "
                                       "wrote only report.json, with the reason for each image", out, len(status),
                                       count, "" if exact == count else "for example ", reason)
    return 1


def _reason_kind(reason: str) -> str:
    """A reason without its image pair and figures, so that reasons are counted by kind: each image of a
    panorama names its own best pair and figures, and as whole strings the most common covered 2 of 10."""
    return re.sub(r"\d+(\.\d+)?", "#", re.sub(r"\([^()]* / [^()]*\)", "(...)", reason))
