"""The reconstruction pipeline: `reconstruct(config, image_dir, out_dir)` runs the stages in mvrecon/stages/
(features, matching, mapping) on one workspace and writes report.json; a finished run is not redone and an
interrupted one resumes (each stage skips the work already in the database).

Each stage is callable from Python, the CLI and tests alike, `stage(config, inputs, workspace) -> summary`:

- `extract_features(config, image_dir, workspace)`: images -> cameras, keypoints, descriptors
  (stages/features.py).
- `match(config, workspace)`: pairs -> putative matches -> verified two-view geometries (stages/matching.py).
- `map_workspace(config, workspace)`: verified pairs -> models (stages/mapping.py).
"""

import hashlib
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

from . import database as dbmod
from .cluster import Cluster
from .config import config_hash, to_dict
from .errors import DiskFull, InputError
from .executor import StageClock
from .io.colmap_model import write_text_models
from .sfm.config import MapperConfig
from .stages.common import FrontendConfig
from .stages.features import extract_features, masks_folder
from .stages.mapping import NoVerifiedPairs, map_workspace
from .stages.matching import match
from .stages.report import finished_report, write_report
from .startup import load_later_stages
from .workspace import Workspace

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReconstructConfig:
    """Front end and mapper settings of one `reconstruct` run."""

    frontend: FrontendConfig = FrontendConfig()
    mapper: MapperConfig = MapperConfig()


def _file_hash(path: str) -> str:
    """The content of a settings file as a run's hash records it (an edited file is another config)."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the pose priors: {exc}") from None


def reconstruct(config: ReconstructConfig, image_dir: Path | str, out_dir: Path | str, *, text: bool = False,
                resume: bool = False, overwrite: bool = False, cluster: Cluster | None = None) -> dict:
    """Images -> features -> matches -> models: OUT/database.db, sparse/N/, points.ply, report.json.
    With `cluster` (mvrecon/cluster.py) the features and matches are computed there and written here.

    A finished run with the same config is not redone (its report is returned); an interrupted one resumes:
    features and matches already in the database are kept, and mapping continues from its snapshot when
    `resume` is set. Returns the report dict.
    """
    out = Path(out_dir)
    mapper = config.mapper
    full = {"frontend": to_dict(config.frontend), "mapper": to_dict(mapper)}
    if config.frontend.masks:
        full["masks"] = masks_folder(config.frontend)
    if config.frontend.pose_priors:
        full["pose_priors"] = _file_hash(config.frontend.pose_priors)
    full_hash = config_hash(full)
    report_path = out / "report.json"
    finished = None if overwrite else finished_report(out, full_hash, Path(image_dir))
    if finished is not None:
        log.info("%s: finished run with the same config and images found; not redone", out)
        if text:
            log.info("%s: wrote the text model of %d model(s)", out, write_text_models(out / "sparse"))
        return finished
    kept = report_path.read_bytes() if report_path.is_file() and not overwrite else None
    fresh = not out.exists()
    ws = Workspace(out).create()
    with ws.lock():  # another run writing this folder is refused
        clock = StageClock()

        def before_changes():  # until this run ends, the folder holds no finished run
            report_path.unlink(missing_ok=True)

        try:
            features = extract_features(config.frontend, image_dir, ws, overwrite=overwrite,
                                        before_changes=before_changes, alongside=load_later_stages,
                                        cluster=cluster)
            log.info("%s", features.text())
            clock.done("features")
            matches = match(config.frontend, ws, overwrite=overwrite, cluster=cluster)
            log.info("%s", matches.text())
            clock.done("matching")
            summary = map_workspace(mapper, ws, image_dir=image_dir, text=text, resume=resume,
                                    overwrite=overwrite, keypoint_colors=features.keypoint_colors,
                                    cluster=cluster)
        except DiskFull:  # the features and matches written so far are kept for the rerun
            raise
        except InputError as exc:  # rejected input (no verified pairs, say), or refused settings
            if fresh:  # a folder this call made holds nothing worth keeping
                shutil.rmtree(out, ignore_errors=True)
                if isinstance(exc, NoVerifiedPairs):  # the database it names went with the folder
                    raise NoVerifiedPairs(image_dir, exc.reason) from None
            elif kept is not None:  # refused (another config, say) without --overwrite: the earlier run stands
                report_path.write_bytes(kept)
            raise
        clock.done("mapping")
        log.info("%s", summary.text())
        skipped = dict(features.failed)
        return write_report(out, config_hash=full_hash, seed=mapper.seed, summary=summary, stages=clock.stages,
                            total=clock.total(), counts=dbmod.database_counts(ws.database_path), skipped=skipped,
                            pairs=matches.pairs_record())
