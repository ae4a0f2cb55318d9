"""The mapping stage: the verified pairs in the workspace's database -> models in sparse/N/ and points.ply.

`map_workspace(config, workspace)` runs the incremental mapper (sfm/incremental.py), or the global one
(sfm/global_mapper.py) with `mapper = "global"`, through `_run_mapper`; with `partition_size` P and more than P
images, it maps overlapping parts of the view graph with either mapper and merges them (stages/partitioned.py).
With `resume`, incremental mapping continues from the workspace's snapshot, partitioned mapping from its finished
parts.
"""

import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import database as dbmod
from ..cameras import recorded_model_left_open, report_entry
from ..cluster import Cluster
from ..config import to_dict
from ..errors import InputError
from ..executor import default_workers
from ..io.colmap_model import warn_text_names, write_models, write_points_ply
from ..io.files import write_json
from ..matching.overlay import fixed_keypoints, same_view
from ..sfm.config import MapperConfig
from ..sfm.georef import CenterPriors, georeference_models
from ..sfm.model import Reconstruction, coverage
from ..workspace import Workspace
from .common import as_workspace, holding_workspace
from .partitioned import map_in_parts

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GlobalFallback:
    """The global mapper's run after an incremental mapping that left out images of verified pairs (`_run_mapper`),
    as report.json's `global_fallback` records it: its time is part of the mapping's, which a user sees grow."""

    incremental_largest: int  # images in the incremental mapper's largest model
    paired_images: int  # images in at least one verified pair
    global_largest: int  # images in the global mapper's largest model
    kept: str  # whose models were written: "global" where its largest held more, else "incremental"
    global_seconds: float

    def text(self) -> str:
        return (f"The incremental mapper's largest model held {self.incremental_largest} of the "
                f"{self.paired_images} images with verified pairs: the global mapper mapped them too "
                f"({self.global_seconds:.1f} s), its largest model held {self.global_largest}, and the {self.kept} "
                "models are written.")


@dataclass(kw_only=True)
class MapSummary:
    """What the mapping stage made: the models, each image's status, each model's figures."""

    models: list  # sfm.model.Reconstruction, largest first
    status: dict  # image name -> {"status", "model", "reason"}
    model_stats: list  # per model: registered, points, mean_track_length, mean_reprojection_error_px, cameras
    seconds: float = 0.0
    georef: dict | None = None  # with position priors: sfm.georef.georeference_models' report entry
    mapper: str = "incremental"  # the mapper whose models these are ("global" where the incremental one fell short)
    fallback: GlobalFallback | None = None  # where the global mapper ran after the incremental one

    def text(self) -> str:
        n = sum(1 for s in self.status.values() if s["status"] == "registered")
        parts = [f"Mapping: {n} of {len(self.status)} images registered in {len(self.models)} model(s) "
                 f"in {self.seconds:.1f} s."]
        if self.fallback is not None:
            parts.append(self.fallback.text())
        for k, s in enumerate(self.model_stats):
            parts.append(f"Model {k}: {s['registered']} images, {s['points']} points, mean track length "
                         f"{s['mean_track_length']:.2f}, mean reprojection error "
                         f"{s['mean_reprojection_error_px']:.3f} px.")
        missing = {name: s["reason"] for name, s in self.status.items() if s["status"] != "registered"}
        for name, reason in sorted(missing.items())[:20]:
            parts.append(f"  {name}: {reason}")
        if len(missing) > 20:
            parts.append(f"  ... and {len(missing) - 20} more (see report.json)")
        return "\n".join(parts)


@holding_workspace
def map_workspace(config: MapperConfig, workspace: Workspace | Path | str, *,
                  image_dir: Path | str | None = None, text: bool = False, resume: bool = False,
                  overwrite: bool = False, keypoint_colors: dict[str, np.ndarray] | None = None,
                  cluster: Cluster | None = None) -> MapSummary:
    """Run the mapper (`config.mapper`) on the workspace's database and write `sparse/N/` and `points.ply`.

    With `resume`, mapping continues from the last snapshot in the workspace (`snapshots/mapper.pkl`);
    without it mapping starts over. The points are coloured from `keypoint_colors`
    (FeatureSummary's) when it covers a model's images, otherwise from the images in `image_dir`. With
    `cluster` (mvrecon/cluster.py) and `config.partition_size`, the parts are mapped there.
    """
    start = time.perf_counter()
    ws = as_workspace(workspace)
    if not ws.database_path.is_file():
        raise InputError(f"{ws.path}: no database.db here; run `mvrecon reconstruct IMAGES -o {ws.path}` "
                         "first")
    record, snapshot = to_dict(config), ws.snapshot_path
    ws.check_stage("mapping", record, overwrite, hint=f"rerun with --overwrite to map again (`mvrecon map -o "
                   f"{ws.path} --overwrite` redoes only the mapping), or use another workspace")
    try:
        stages = ws.stages()
    except InputError:  # an unreadable record, which check_stage lets --overwrite map past
        stages = {}
    corr = dbmod.read_correspondences(ws.database_path)
    if not corr.pairs:
        raise NoVerifiedPairs(ws.database_path,
                              _no_verified_pairs(ws, corr, matched_by_mvrecon="matching" in stages))
    _warn_same_views(ws, corr)
    if image_dir is None and not keypoint_colors:
        image_dir = _recorded_images(stages)
    if overwrite:  # --overwrite starts mapping over, --resume or not
        snapshot.unlink(missing_ok=True)
        resume = False
    ws.begin_stage("mapping", record, overwrite)
    if config.partition_size and len(corr.images) > config.partition_size:
        result, mapper, fallback = map_in_parts(corr, config, ws, resume, cluster=cluster), config.mapper, None
    else:
        features = (stages.get("features") or {}).get("config")
        choose = config.choose_camera_model and recorded_model_left_open(features)
        result, mapper, fallback = _run_mapper(corr, config, snapshot, resume, choose_lens=choose)
    georef = georeference_models(result.models, CenterPriors.of(corr.priors), frame=config.frame,
                                 max_sigmas=config.prior_max_sigmas, seed=config.seed)
    _write_models(ws, result.models, image_dir, text, keypoint_colors)
    _write_georef(ws, georef)
    stats = []
    for m in result.models:
        s = m.stats()
        stats.append({**{k: s[k] for k in ("registered", "points", "mean_track_length",
                                           "mean_reprojection_error_px")}, "cameras": camera_entries(m)})
    return MapSummary(models=result.models, status=result.status, model_stats=stats,
                      seconds=time.perf_counter() - start, georef=georef, mapper=mapper, fallback=fallback)


GEOREF = "georef.json"  # in the workspace: the frame of the models and its origin, with position priors


def _write_georef(ws: Workspace, georef: dict | None) -> None:
    """The workspace's record of the models' frame (frame and ENU origin), or none without priors."""
    path = ws.path / GEOREF
    if georef is None:
        path.unlink(missing_ok=True)
        return
    write_json(path, {"frame": georef["frame"], "origin": georef["origin"],
                      "models": [{k: v for k, v in m.items() if k != "flagged"} for m in georef["models"]]}, indent=1)


def _run_mapper(corr, config, snapshot: Path, resume: bool, choose_lens: bool = False) -> tuple:
    """(result, mapper, fallback): the models of the correspondences `corr` (database.Correspondences) with each
    image's status, the name of the mapper that made them, and the GlobalFallback where the global mapper ran after
    the incremental one (else None). The incremental mapper (sfm/incremental.py; with `choose_lens`, each camera's
    model chosen from the data, sfm/lens.py) or, with `mapper = "global"`, the global one (sfm/global_mapper.py,
    which maps in one go and has no snapshot to resume from; it chooses the models with `choose_lens` too). Their
    modules load only when mapping runs (GTSAM is heavy for the commands that never map).

    With `global_fallback`, an incremental mapping whose largest model leaves out images of verified pairs (under
    half of them, or split into several models, or short of a few) is followed by a global one, whose models replace
    it when their largest holds more images: the two mappers fail on different view graphs (a graph of pairs with
    few matches each, whose tracks rarely reach a third view, starts no incremental model but gives every rotation
    and position to the global mapper; on a facade of repeated windows or bricks, or a sparse ring of views, images
    the incremental mapper cannot chain to its first model start a second one or none, while the global mapper
    places them all at once; a facade whose incremental model held 44 of its 48 images, half of them misplaced, had
    all 48 right in the global one). Where the incremental mapper leaves an image out, the global mapper's time
    comes on top; both mapping nothing costs a panorama a second."""
    if config.mapper == "global":
        return _map_globally(corr, config, choose_lens), "global", None
    from ..sfm.incremental import map_correspondences  # noqa: PLC0415 - GTSAM, after the workers fork

    result = map_correspondences(corr, config, snapshot_path=snapshot, resume=resume, choose_lens=choose_lens)
    largest, n, paired = coverage(result.models)[0], len(corr.images), len(corr.paired_images())
    if not config.global_fallback or largest >= paired:
        return result, "incremental", None
    log.info("the incremental mapper's largest model holds %d of %d images (%d models): mapping them with the "
             "global mapper too", largest, n, len(result.models))
    start = time.perf_counter()
    other = _map_globally(corr, config, choose_lens)
    other_largest = coverage(other.models)[0]
    fallback = GlobalFallback(incremental_largest=largest, paired_images=paired, global_largest=other_largest,
                              kept="global" if other_largest > largest else "incremental",
                              global_seconds=round(time.perf_counter() - start, 1))
    if fallback.kept == "incremental":
        log.info("the global mapper's largest model holds %d images: the incremental models are kept", other_largest)
        return result, "incremental", fallback
    log.warning("the incremental mapper's largest model held %d of %d images, the global mapper's holds %d: the "
                "global models are written, as `--mapper global` makes them", largest, n, other_largest)
    return other, "global", fallback


def _map_globally(corr, config, choose_lens: bool):
    """The global mapper's result; its modules load only here (the incremental mapper's runs do not hold them)."""
    from ..sfm.global_mapper import map_correspondences_globally  # noqa: PLC0415 - GTSAM, after the workers fork

    return map_correspondences_globally(corr, config, default_workers(), choose_lens=choose_lens)


def _write_models(ws: Workspace, models: list, image_dir, text: bool, keypoint_colors) -> None:
    """sparse/N/ and points.ply of `models`. The new models go to sparse.new/ and replace sparse/ only once
    made: a failed re-map keeps the old model; with no model at all the earlier one stays too."""
    sparse, new = ws.path / "sparse", ws.path / "sparse.new"
    shutil.rmtree(new, ignore_errors=True)
    recs = write_models(models, new, image_dir=image_dir, text=text, keypoint_colors=keypoint_colors)
    if recs:
        old = ws.path / "sparse.old"
        shutil.rmtree(old, ignore_errors=True)
        if sparse.exists():
            sparse.rename(old)
        new.rename(sparse)
        shutil.rmtree(old, ignore_errors=True)
        write_points_ply(recs[0], ws.path / "points.ply")
        if text:
            warn_text_names([r.names for r in recs], sparse)
    else:
        shutil.rmtree(new, ignore_errors=True)
        if sparse.exists():
            log.warning("%s: no new model; the earlier model in sparse/ and points.ply is kept", ws.path)


def camera_entries(model: Reconstruction) -> list[dict]:
    """The cameras of a model's registered images with their final parameters (COLMAP's order), as report.json
    lists them: the refined intrinsics were only in sparse/N/cameras.bin."""
    cams = [(int(cid), model.cameras[int(cid)]) for cid in np.unique(model.camera_of[model.registered])]
    out = [report_entry(cid, cam.model, cam.width, cam.height, cam.params) for cid, cam in cams]
    for entry, (cid, _) in zip(out, cams):
        if cid in model.lens_trials:  # the model was chosen from the data: the errors that chose it
            entry["model_choice"] = model.lens_trials[cid]
    return out


class NoVerifiedPairs(InputError):
    """The database gives the mapper no verified pair; `reason` is why, without the path the error names (the
    database, or the images of a `reconstruct` that removed the folder it made, database included)."""

    def __init__(self, path: Path | str, reason: str):
        super().__init__(f"{path}: {reason}")
        self.reason = reason


def _no_verified_pairs(ws: Workspace, corr, *, matched_by_mvrecon: bool) -> str:
    """Why a database gives the mapper no pair: none matched yet, or what the database marked the matched pairs,
    with COLMAP's fisheye rule when that is the likely cause (COLMAP matched a fisheye camera without a focal
    prior: it marks every such pair DEGENERATE, which looked like images without overlap)."""
    head = f"no verified image pairs among {len(corr.images)} images; "
    configs = dbmod.pair_configurations(ws.database_path)
    if not configs:
        with dbmod.open_database(ws.database_path) as db:
            matched = dbmod.num_matched_pairs(db)
        return head + (f"run `mvrecon match -o {ws.path}` first" if not matched else
                       "the images do not overlap or have too little texture (nothing to reconstruct)")
    total = sum(configs.values())
    head += (f"its one matched pair is {next(iter(configs))}" if total == 1 else
             f"all {total} matched pairs are {next(iter(configs))}" if len(configs) == 1 else
             f"the {total} matched pairs are " + ", ".join(f"{n} {name}" for name, n in configs.items())) \
        + ("" if matched_by_mvrecon else " in the database")
    blind = dbmod.colmap_blind_cameras(corr.cameras)
    if blind and not matched_by_mvrecon:
        cid, model = blind[0], corr.cameras[blind[0]].model
        return head + (f"; likely cause: {dbmod.COLMAP_FISHEYE_NOTE} and marks its pairs DEGENERATE (camera {cid} is "
                       f"{model} without one): give it a focal prior when extracting (COLMAP's camera_params) and "
                       f"match again, or run `mvrecon reconstruct IMAGES -o OUT --camera-model {model}`, whose "
                       "verifier needs none")
    if matched_by_mvrecon and _mostly_fixed(corr):
        return head + (": most features stay on the same pixels of every image, whose matches are left out "
                       "(matching/overlay.py): the camera did not move between the images (nothing to reconstruct)")
    return head + ": the images do not overlap or have too little texture (nothing to reconstruct)"


def _warn_same_views(ws: Workspace, corr) -> None:
    """A warning naming the images that show one view (`overlay.same_view`: copies of one photo, or shots from a
    camera that did not move), which the mapper registers at one pose without adding a viewpoint; from the
    verified matches the mapper reads anyway (opensfm_lund's 238 pairs: 27 ms, beside the 63 ms of reading them)."""
    group = {i: {i} for i in corr.images}
    for p in corr.pairs:
        a, b = group[p.image_id1], group[p.image_id2]
        if a is not b and same_view(corr.keypoints[p.image_id1], corr.keypoints[p.image_id2], p.inliers):
            a |= b
            for i in b:
                group[i] = a
    groups = sorted({id(g): sorted(corr.images[i].name for i in g) for g in group.values() if len(g) > 1}.values())
    if groups:
        shown = "; ".join(" = ".join(names) for names in groups[:5]) + (
            f"; and {len(groups) - 5} more groups" if len(groups) > 5 else "")
        log.warning("%s: images that show one view (their matches stay on their pixels: copies of one photo, or "
                    "shots from a camera that did not move), which a model places at one pose: %s", ws.path, shown)


def _mostly_fixed(corr) -> bool:
    """Whether most keypoints sit where half the images of their size have one: a camera that never moved."""
    sizes = {i: (corr.cameras[info.camera_id].width, corr.cameras[info.camera_id].height)
             for i, info in corr.images.items()}
    fixed = fixed_keypoints(corr.keypoints, sizes)
    return sum(int(m.sum()) for m in fixed.values()) > 0.5 * sum(len(m) for m in fixed.values())


def _recorded_images(stages: dict):
    """The image folder the workspace's features were extracted from, for the points' colours, when it still
    exists; else None, with a warning that the colours are not sampled."""
    folder = ((stages.get("features") or {}).get("config") or {}).get("images")
    if isinstance(folder, str) and Path(folder).is_dir():
        return folder
    log.warning("point colours are not sampled (black): no image folder %s; pass --image-dir IMAGES to colour "
                "them", "recorded for this workspace" if folder is None else f"at the recorded {folder}")
    return None
