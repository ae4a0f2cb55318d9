"""report.json: the record of a finished `reconstruct` run, written at its end and read by a rerun, which
returns it instead of redoing a run with the same config and images (`finished_report`)."""

from dataclasses import asdict
from pathlib import Path

from .. import __version__
from .. import database as dbmod
from ..errors import InputError
from ..io.files import read_json_object, write_json
from ..io.images import IMAGE_EXTENSIONS, visible_files
from ..workspace import Workspace
from .features import STAMPS, image_stamps
from .mapping import MapSummary


def write_report(out_dir: Path | str, *, config_hash: str, seed: int, summary: MapSummary, stages: dict,
                 total: dict, counts: dict, skipped: dict | None = None,
                 database: dict | None = None, pairs: dict | None = None) -> dict:
    """OUT/report.json in the schema the compare and study tools read (see docs/sfm.md). `database`: where
    database.db came from ({"made_by": "mvrecon"} or another tool's); `pairs`: the pair selection used
    (MatchSummary.pairs_record)."""
    images = {name: dict(s) for name, s in summary.status.items()}
    for name, reason in (skipped or {}).items():
        images[name] = {"status": "skipped", "model": None, "reason": reason}
    report = {"engine": "mvrecon", "version": __version__, "config_hash": config_hash, "seed": seed,
              "images": dict(sorted(images.items())),
              "models": [{"index": k, **s} for k, s in enumerate(summary.model_stats)],
              "mapper": summary.mapper, "stages": stages, "total": total, "counts": counts,
              "database": database or {"made_by": "mvrecon"}}
    if pairs is not None:
        report["pairs"] = pairs
    if summary.georef is not None:
        report["georef"] = summary.georef
    if summary.fallback is not None:
        report["global_fallback"] = asdict(summary.fallback)
    write_json(Path(out_dir) / "report.json", report, indent=1)
    return report


def finished_report(out: Path, full_hash: str, image_dir: Path) -> dict | None:
    """report.json of a finished run in `out` with this config, of these very images (the same folder, and
    every image file in it has a status in the report: none added or removed since, and none changed in size or
    time), else None. A run whose database.db was damaged since is refused (dbmod.database_damage): it was
    reported finished, and its database could serve neither a rerun nor `map` or `compare`."""
    report = read_json_object(out / "report.json")
    if report is None or report.get("config_hash") != full_hash or not (out / "sparse").is_dir():
        return None
    try:
        recorded = Workspace(out).stage_config("features") or {}
    except InputError:
        return None
    if recorded.get("images") != str(image_dir.resolve()) or not image_dir.is_dir():
        return None
    names = {n for n in visible_files(image_dir) if Path(n).suffix.lower() in IMAGE_EXTENSIONS}
    if names != set(report.get("images") or ()):
        return None
    stamps = read_json_object(out / STAMPS)  # none in a workspace of an older version: names decide there
    if stamps is not None and stamps != image_stamps(image_dir, names):
        return None
    database = out / "database.db"  # one deleted since (to save space, say) leaves the model as it was
    damage = dbmod.database_damage(database) if database.is_file() else None
    if damage is not None:
        raise InputError(f"{database}: damaged since its run finished ({damage}); rerun with --overwrite to "
                         "start over")
    return report
