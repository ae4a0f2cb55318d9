"""The front end's command-line options, shared by every command that extracts or matches features.

`add_camera_options`, `add_feature_options`, `add_matching_options` and `add_run_options` add one argument group
each (`add_frontend_options` adds all four); `frontend_config_from_args(args)` builds the `FrontendConfig` from
the defaults, then a `--config` TOML file, then the flags actually given. Commands such as `reconstruct` reuse these
instead of redefining flags, so the same words mean the same thing everywhere. The argparse number types
(`positive_int`, `finite_float`, ...) and `check_output_file` serve every command.
"""

import argparse
import contextlib
import dataclasses
import logging
import math
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path

from ..cameras import CAMERA_MODES, CameraConfig, parse_camera_params
from ..cluster import INSECURE, open_cluster, parse_cluster
from ..config import check_tables, load_toml, with_field, with_overrides
from ..errors import InputError
from ..geometry.camera import MODELS
from ..matching.pairs import check_spec
from ..stages.common import FrontendConfig


def _number(kind, low=None, low_open: bool = False):
    """An argparse `type` for finite numbers of `kind`, at least `low` (above it with `low_open`) when given."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        if low is None and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        if low is not None and (not math.isfinite(value) or value < low or (low_open and value == low)):
            raise argparse.ArgumentTypeError(f"must be {'above' if low_open else 'at least'} {low}, got {text}")
        return value
    return parse


non_negative_int = _number(int, 0)  # seeds, counts where 0 means "none" or "all"
positive_int = _number(int, 1)
positive_float = _number(float, 0.0, low_open=True)
finite_float = _number(float)  # an angle, say: nan or inf would run on into meaningless results


def check_output_file(path: Path | str, inputs: Iterable[Path | str]) -> None:
    """Refuse, before the work, an output file that is a folder, would replace one of `inputs`, or cannot be
    written (its folder is made if missing): a bad -o should not cost the whole computation (calibrate, detectors)."""
    out = Path(path)
    if out.is_dir():
        raise InputError(f"{out}: is a folder; give a file name to write")
    if any(out.resolve() == Path(p).resolve() for p in inputs):
        raise InputError(f"{out}: is one of the input images; choose another output file")
    folder = out.parent
    try:  # as every other -o: a missing folder is made
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot make folder {folder} ({exc.strerror})") from None
    if not os.access(folder, os.W_OK):
        raise InputError(f"{out}: folder {folder} is not writable")
    if out.exists() and not os.access(out, os.W_OK):
        raise InputError(f"{out}: file is not writable")
    try:  # os.access says yes to root even for /proc: a real (unnamed, at once deleted) file tells
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise InputError(f"{out}: cannot write in {folder} ({exc.strerror})") from None


def add_camera_options(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("cameras")
    g.add_argument("--camera-model", choices=MODELS, default=None,
                   help=f"camera model (default {CameraConfig.model}; OPENCV_FISHEYE for fisheye lenses)")
    g.add_argument("--camera-mode", choices=CAMERA_MODES, default=None,
                   help="which images share intrinsics: auto = same size and EXIF make/model/focal (default), "
                        "single, per-folder, per-image")
    g.add_argument("--camera-params", default=None, metavar="P1,P2,...",
                   help="known intrinsics in the model's COLMAP order, e.g. 'f,cx,cy,k' for SIMPLE_RADIAL, "
                        "'fx,fy,cx,cy,k1,k2,k3,k4' for OPENCV_FISHEYE (trusted)")


def add_feature_options(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("SIFT features")
    g.add_argument("--max-features", type=int, default=None, help="keypoints per image (default 8192)")
    g.add_argument("--min-features", type=int, default=None,
                   help="an image with fewer keypoints keeps the strongest of half the peak threshold up to "
                        "this many, e.g. 2000 for weakly textured images (default 0: off)")
    g.add_argument("--max-image-size", type=int, default=None,
                   help="shrink images to this long side before detection (default 3200)")
    g.add_argument("--peak-threshold", type=float, default=None,
                   help="smallest DoG peak, as COLMAP's peak_threshold (default 0.0133, twice COLMAP's; "
                        "COLMAP's 0.00667 finds 1.2-3.4x the keypoints: AUC@1 up on most sets, at 1.1-4.1x "
                        "the front end's time)")
    g.add_argument("--upright", action="store_true", default=None,
                   help="no orientation (cameras that never roll)")
    g.add_argument("--no-root-sift", dest="root_sift", action="store_false", default=None,
                   help="plain L2-normalised SIFT instead of RootSIFT")
    g.add_argument("--masks", default=None, metavar="DIR",
                   help="no features where a mask is black, in COLMAP's layout: the mask of IMAGES/sub/a.jpg is "
                        "DIR/sub/a.jpg.png, in the image's stored frame or upright (people, sky, a lens hood)")
    g.add_argument("--pose-priors", default=None, metavar="CSV",
                   help="camera positions (name,lat,lon,alt or name,x,y,z with optional sigma columns; see "
                        "docs/georef.md) as the position priors instead of the images' EXIF GPS")


def add_matching_options(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("matching")
    g.add_argument("--pairs", default=None, metavar="SPEC",
                   help="auto (default: exhaustive below 50 images, else by GPS, video frame names or "
                        "retrieval), exhaustive, sequential:K (the next K frames, and loop closures), spatial:K[:R] "
                        "(the K nearest by GPS, within R m), retrieval:K (the K most similar), A+B (both), or a "
                        "file of 'name1 name2' lines; see docs/pairs.md")
    g.add_argument("--ratio", type=float, default=None, help="Lowe's ratio test threshold (default 0.8)")
    g.add_argument("--max-error", type=float, default=None,
                   help="RANSAC inlier threshold in pixels (default 4)")
    g.add_argument("--min-inliers", type=int, default=None,
                   help="inliers for a pair to count as verified (default 15)")


def add_workspace(parser: argparse.ArgumentParser, help: str, dest: str = "workspace") -> None:
    """The run's folder: -o/--output, as every command names the folder it writes; -w/--workspace, the name
    `features`, `match` and `map` gave it first, is the same option."""
    parser.add_argument("-o", "--output", "-w", "--workspace", dest=dest, required=True, metavar="FOLDER",
                        help=f"{help} (-w/--workspace is the same option)")


# --config help of commands that read every table (reconstruct); features and match name their own
RUN_CONFIG_HELP = "e.g. [sift] max_num_features = 4096 or [mapper] init_min_inliers = 50"


def add_run_options(parser: argparse.ArgumentParser, *, config_help: str = RUN_CONFIG_HELP) -> None:
    """`config_help`: which --config tables the command reads, with an example (features ignores [mapper])."""
    g = parser.add_argument_group("run")
    g.add_argument("--config", default=None, metavar="TOML",
                   help=f"config overrides, {config_help} (flags win over the file)")
    g.add_argument("--workers", type=int, default=None, help="parallel processes (default: all cores)")
    g.add_argument("--overwrite", action="store_true",
                   help="recompute instead of refusing when the workspace was made with other settings")
    add_cluster_options(parser)


def add_cluster_options(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("cluster (docs/distributed.md)")
    g.add_argument("--cluster", default=None, metavar="ADDRESS",
                   help="run the features, matching and the parts of --partition-size on Dask: local:N (N worker "
                        "processes on this machine, listening on 127.0.0.1 only) or a running scheduler's "
                        "tcp://HOST:8786 / tls://HOST:8786 (default: a process pool on this machine)")
    g.add_argument("--cluster-security", default=None, metavar="FILE",
                   help="TOML or YAML file naming the TLS ca-file, cert and key of a remote scheduler; "
                        f"'{INSECURE}' accepts an unauthenticated scheduler on a network you trust")


def cluster_from_args(args: argparse.Namespace):
    """A context manager giving the cluster of --cluster, connected (mvrecon.cluster.open_cluster), or None
    without --cluster; the address and security file are checked when this is called, before any work."""
    if not getattr(args, "cluster", None):
        if getattr(args, "cluster_security", None):
            raise InputError("--cluster-security: needs --cluster")
        return contextlib.nullcontext(None)
    return open_cluster(parse_cluster(args.cluster, args.cluster_security))


def add_dense_options(parser, prefix: str = "") -> None:
    """The dense options of `dense` (--max-image-size, --views) and `reconstruct --dense` (prefix "dense-":
    its --max-image-size is SIFT's)."""
    parser.add_argument(f"--{prefix}max-image-size", type=positive_int, default=1600,
                        help="undistorted images (and depth maps) fit this long side (default 1600)")
    parser.add_argument(f"--{prefix}views", type=positive_int, default=8,
                        help="source views per depth map, chosen from the sparse model (default 8)")


def add_frontend_options(parser: argparse.ArgumentParser) -> None:
    add_camera_options(parser)
    add_feature_options(parser)
    add_matching_options(parser)
    add_run_options(parser)


_FLAG_FIELDS = {  # argparse dest -> (config section, field)
    "camera_model": ("camera", "model"),
    "camera_mode": ("camera", "mode"),
    "max_features": ("sift", "max_num_features"),
    "min_features": ("sift", "min_num_features"),
    "max_image_size": ("sift", "max_image_size"),
    "peak_threshold": ("sift", "peak_threshold"),
    "upright": ("sift", "upright"),
    "root_sift": ("sift", "root_sift"),
    "pairs": (None, "pairs"),
    "ratio": ("matcher", "max_ratio"),
    "max_error": ("verify", "max_error"),
    "min_inliers": ("verify", "min_num_inliers"),
    "masks": (None, "masks"),
    "pose_priors": (None, "pose_priors"),
    "workers": (None, "workers"),
}
_FLAG_NAMES = {"root_sift": "--no-root-sift"}  # argparse dest -> flag, where not "--" + dest with dashes


def flag_name(dest: str) -> str:
    """The command-line flag of an argparse dest (`camera_model` -> `--camera-model`)."""
    return _FLAG_NAMES.get(dest, "--" + dest.replace("_", "-"))


def config_file(args: argparse.Namespace) -> tuple[FrontendConfig, dict]:
    """(FrontendConfig with the --config TOML file's front-end tables applied, the file's [mapper] table); the
    defaults and {} without a file. The front-end tables are checked whichever command reads the file (`map`
    uses only [mapper]): a misspelt table or an option outside its table is an InputError, not ignored."""
    if not getattr(args, "config", None):
        return FrontendConfig(), {}
    tables = load_toml(args.config)
    defaults = FrontendConfig()
    check_tables(tables, [f.name for f in dataclasses.fields(defaults) if dataclasses.is_dataclass(
        getattr(defaults, f.name))] + ["mapper"], source=args.config)
    mapper = tables.pop("mapper", {})
    known = sorted({f.name for f in dataclasses.fields(FrontendConfig)} | {"mapper"})
    for key in tables:
        if key not in known:
            raise InputError(f"{args.config}: unknown table or option {key!r} (known: {', '.join(known)})")
    config = with_overrides(FrontendConfig(), tables, source=args.config)
    if "model" in tables.get("camera", {}):  # named, even as the default: kept as named (sfm/lens.py)
        config = dataclasses.replace(config, camera=dataclasses.replace(config.camera, model_given=True))
    return config, mapper


def warn_if_config_unread(args: argparse.Namespace, command: str, reads: tuple[str, ...]) -> None:
    """A warning when the --config file holds none of the tables or keys `command` reads (`reads`): a file of
    [mapper] settings given to `features` was taken without a word, as if its settings had been applied."""
    if not getattr(args, "config", None):
        return

    def shown(key):  # a table as the file writes it, a plain key as itself
        return f"[{key}]" if key in ("camera", "sift", "matcher", "verify", "mapper") else key

    keys = set(load_toml(args.config))
    if keys and not keys & set(reads):
        logging.getLogger("mvrecon").warning(
            "%s: `mvrecon %s` reads none of this file's %s (it reads %s); they take effect in the commands that "
            "read them", args.config, command, ", ".join(map(shown, sorted(keys))), ", ".join(map(shown, reads)))


def frontend_config_from_args(args: argparse.Namespace,
                              from_file: tuple[FrontendConfig, dict] | None = None) -> FrontendConfig:
    """FrontendConfig = defaults < --config TOML < flags given on the command line. `from_file`: what
    `config_file(args)` returned, when the caller has read the file already."""
    config = (from_file or config_file(args))[0]
    # each value checked where the user gave it: a flag is named as typed ("--max-features: must be at least
    # 1, got 0"), a value of the --config file by the file, table and key
    for dest, (section, name) in _FLAG_FIELDS.items():
        value = getattr(args, dest, None)
        if value is not None:
            config = with_field(config, (name,) if section is None else (section, name), value, where=flag_name(dest))
    if getattr(args, "camera_params", None):
        config = with_field(config, ("camera", "params"), list(parse_camera_params(args.camera_params)),
                            where="--camera-params")
    origin, default = {}, CameraConfig()
    for name, dest in (("mode", "camera_mode"), ("model", "camera_model"), ("params", "camera_params")):
        value = getattr(config.camera, name)
        if getattr(args, dest, None):  # a flag's params are numbers (parse_camera_params)
            origin[name] = f"{flag_name(dest)} {','.join(f'{v:g}' for v in value) if name == 'params' else value}"
        elif value != getattr(default, name):  # not a flag, not the default: the file's
            origin[name] = f"{args.config}: camera: {name} = {list(value) if name == 'params' else value!r}"
    config.camera.validate(origin)
    if "model" in origin:  # named by a flag, even as the default: kept as named (a file's: `config_file`)
        config = dataclasses.replace(config, camera=dataclasses.replace(config.camera, model_given=True))
    if getattr(args, "pairs", None) is not None:
        check_spec(config.pairs)
    elif config.pairs != type(config)().pairs:
        check_spec(config.pairs, where=f"{args.config}: pairs = {config.pairs!r}")
    return config


DASHED_VALUES = ("--mvrecon-args",)  # options whose value is itself a list of flags


def join_option_value(argv: list[str], option: str) -> list[str]:
    """`OPTION VALUE` as `OPTION=VALUE` in argv (up to a `--`), so that a VALUE starting with a dash is the
    option's value: argparse takes a lone `--upright` for an unknown option and stops at `--mvrecon-args
    "--upright"` (the documented form) with "expected one argument"; only values with a space got through."""
    argv, out, k = list(argv), [], 0
    while k < len(argv):
        if argv[k] == "--":
            return out + argv[k:]
        if argv[k] == option and k + 1 < len(argv):
            out.append(f"{option}={argv[k + 1]}")
            k += 2
        else:
            out.append(argv[k])
            k += 1
    return out
