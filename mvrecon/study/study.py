"""Run a degradation study: degrade the images per cell, run every engine per cell, measure, tabulate.

STUDY layout (everything is cached, so an interrupted study resumes and a wider grid reuses what exists):

    .stages/study.json       the study's record (`io.record.Record`): "settings", those every cell was made
                             with (a study refuses to mix settings), and "images/<cell>", recorded once the
                             cell's images are complete, with the image names it was made from
    images/<cell>/           degraded copies of the images (same names and sub-folders, EXIF kept); the clean
                             cell uses IMAGES
    runs/<engine>/<cell>/    each engine's workspace (report.json, sparse/), cached by eval.runners
    study.csv                one row per engine x degradation x level (the clean row repeated per degradation)

The study's images are the ones `reconstruct` takes from IMAGES (`io.images.list_images`: sub-folders searched,
run outputs and unreadable files left out), listed once: every cell is made from them and registered % counts
them, so every engine sees the same image set in every cell. The files left out are named in study.html.

Accuracy is measured against the ground truth when given; otherwise against each engine's own reconstruction of
the clean images (so the clean cell scores itself perfectly and the degraded cells show what was lost).
"""

import csv
import importlib.util
import logging
import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

from ..config import config_hash
from ..errors import InputError
from ..eval.ground_truth import GroundTruth, load_ground_truth
from ..eval.metrics import accuracy_summary
from ..eval.runners import RunResult, forget_if_failed, run_colmap, run_mvrecon
from ..io.images import list_images
from ..io.record import Record, digest
from ..progress import progress
from .config import StudyConfig
from .degrade import degrade_folder
from .grid import AXES, CLEAN, Cell, Grid
from .plots import contact_sheet, metric_plots
from .report import write_report

log = logging.getLogger(__name__)

ENGINES = ("mvrecon", "colmap", "colmap-global")
COLUMNS = ("engine", "degradation", "level", "registered_pct", "registered", "images", "components", "points",
           "mean_track_length", "mean_reprojection_error_px", "auc@1", "auc@5", "auc@10", "keypoints_per_image",
           "mean_inliers_per_pair", "verified_pairs", "wall_s", "peak_mem_mb", "reference", "error")


def _runner(engine: str):
    """run(image_dir, out_dir, options, timeout) -> RunResult for an engine name."""
    if engine == "mvrecon":
        return lambda images, out, options, timeout: run_mvrecon(images, out, options, timeout=timeout)
    if engine in ("colmap", "colmap-global"):
        return lambda images, out, options, timeout: run_colmap(images, out, options,
                                                                global_mapper=engine == "colmap-global",
                                                                timeout=timeout)
    raise InputError(f"engine {engine!r}: expected one of {', '.join(ENGINES)}")


def check_engines(engines: Sequence[str]) -> None:
    """Refuse unknown engines, and mvrecon while its `reconstruct` command is not installed."""
    if not engines:
        raise InputError("--engines: no engine given (mvrecon, colmap or both, comma-separated)")
    for engine in engines:
        _runner(engine)
    if "mvrecon" in engines and importlib.util.find_spec("mvrecon.commands.reconstruct") is None:
        raise InputError("engine mvrecon: the `mvrecon reconstruct` command is not available in this install; "
                         "use --engines colmap")


RECORD = "study.json"  # STUDY/.stages/RECORD
SETTINGS = "settings"  # the record's piece of the settings every cell was made with
LEGACY = "study.json"  # at the top of a study made by an older mvrecon version (with images/<cell>.json markers)


def claim_study_dir(study_dir: Path, config: StudyConfig) -> Record:
    """The study's record, made or checked to hold the same settings (results from different settings never
    mix). A study folder of an older mvrecon version (STUDY/study.json) is refused: its cells' markers are not
    read any more."""
    study_dir.mkdir(parents=True, exist_ok=True)
    record = Record(study_dir, RECORD)
    legacy = study_dir / LEGACY
    if legacy.is_file() and not record.path.exists():
        raise InputError(f"{legacy}: a study of an older mvrecon version, whose record is not read any more; use "
                         "another STUDY folder, or delete this one to start over")
    if record.damaged or (record.names() and record.config(SETTINGS) is None):
        # the cells were made under settings it no longer says: cannot be mixed
        raise InputError(f"{record.path}: damaged (not a record of the study's settings); use another STUDY "
                         "folder, or delete this one to start over")
    identity = config.identity()
    changes = record.differences(SETTINGS, identity)
    if changes:
        fields = sorted({change.split(":")[0].split(".")[0] for change in changes})
        raise InputError(f"{study_dir}: made with a different {', '.join(fields)} ({'; '.join(changes)}); use "
                         "another STUDY folder")
    if record.config(SETTINGS) is None:
        record.put(SETTINGS, config_hash(identity), config=identity)
    return record


def prepare_images(study_dir: Path, config: StudyConfig, cells: list[Cell], names: list[str],
                   record: Record | None = None) -> dict[str, Path]:
    """The image folder of each cell, degrading the ones not complete yet (the clean cell is IMAGES itself).

    `names`: the study's images (`io.images.list_images` of IMAGES); a cell made earlier from other names is
    refused (its runs would count other images). `record`: the study's (`claim_study_dir`); a cell is complete
    when its piece "images/<cell>" is recorded under the same degradation, seed and names and its images are all
    there; it is dropped before the cell's folder is written again."""
    record = record if record is not None else Record(study_dir, RECORD)
    folders = {}
    todo = []
    for cell in cells:
        if cell.is_clean:
            folders[cell.key] = Path(config.images).resolve()
            continue
        folders[cell.key] = study_dir / "images" / cell.key
        if record.get(_piece(cell), _cell_key(cell, config, names), _cell_files(cell, names)) is None:
            _check_cell_images(folders[cell.key], record.report(_piece(cell)), names, config.images)
            todo.append(cell)
    for cell in progress(todo, desc="degrade cells", unit="cell"):
        deg = cell.degradation(config.base)
        record.drop(_piece(cell))
        degrade_folder(config.images, folders[cell.key], deg, seed=config.seed, progress_desc=cell.key, names=names)
        record.put(_piece(cell), _cell_key(cell, config, names),
                   {"degradation": deg.to_dict(), "order": deg.active(), "seed": config.seed, "images": names})
    return folders


def _piece(cell: Cell) -> str:
    return f"images/{cell.key}"


def _cell_key(cell: Cell, config: StudyConfig, names: list[str]) -> str:
    return digest(cell.degradation(config.base).to_dict(), config.seed, names)


def _cell_files(cell: Cell, names: list[str]) -> list[str]:
    return [f"images/{cell.key}/{name}" for name in names]


def _check_cell_images(folder: Path, made: dict | None, names: list[str], images) -> None:
    """InputError when a finished cell (its record's report `made`, None when not recorded) was made from other
    images than IMAGES gives now (added or removed files)."""
    recorded = (made or {}).get("images")
    if not isinstance(recorded, list):
        return
    known, current = set(recorded), set(names)
    missing, extra = [n for n in names if n not in known], [n for n in recorded if n not in current]
    if missing or extra:
        what = "; ".join(f"{label} {', '.join(group[:3])}{' ...' if len(group) > 3 else ''}"
                         for label, group in (("without", missing), ("with", extra)) if group)
        raise InputError(f"{folder}: made from other images than {images} holds now ({what}); use another STUDY "
                         "folder, or delete this one to start over")


def forget_failed_runs(study_dir: Path, engines: Sequence[str], cells: list[Cell]) -> list[str]:
    """Delete the cached runs that failed (crash, timeout), so they run again; returns their 'engine/cell' names."""
    return [f"{engine}/{cell.key}" for engine in engines for cell in cells
            if forget_if_failed(study_dir / "runs" / engine / cell.key)]


def run_cells(study_dir: Path, config: StudyConfig, folders: dict[str, Path], cells: list[Cell]) -> dict:
    """(engine, cell key) -> RunResult; the clean cells first, cells in parallel, finished runs read back."""
    jobs = config.jobs or os.cpu_count() or 1
    tasks = [(engine, cell.key) for cell in cells for engine in config.engines]
    results = {}
    bar = progress(total=len(tasks), desc="study cells", unit="cell")
    pool = ThreadPoolExecutor(max_workers=jobs)  # the work is in the engines' subprocesses
    try:
        futures = {pool.submit(_runner(engine), folders[key], study_dir / "runs" / engine / key,
                               config.run_options, config.timeout_s): (engine, key) for engine, key in tasks}
        for future in as_completed(futures):
            engine, key = futures[future]
            results[(engine, key)] = future.result()
            if results[(engine, key)].error:
                log.warning("%s on %s failed: %s", engine, key, results[(engine, key)].error)
            bar.update(1)
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        log.warning("stopping once the runs in progress finish (they are kept); rerun the same command to resume")
        raise
    finally:
        bar.close()
    pool.shutdown()
    return results


def load_reference(config: StudyConfig, image_names: list[str]) -> GroundTruth | None:
    """The ground truth restricted to the study's images, or None (then each engine's clean model is used)."""
    if config.gt is None:
        return None
    gt = load_ground_truth(config.gt).subset(image_names)
    if len(gt) < 2:
        raise InputError(f"{config.gt}: ground truth for {len(gt)} of the {len(image_names)} images in "
                         f"{config.images}; the names must match")
    return gt


def measure(result: RunResult, reference: dict, image_names: list[str]) -> dict:
    """The study's metrics for one run (failed runs: 0 registered, AUC 0, the rest NaN, with the error).

    Registered % is of `image_names`, the study's images: an image a model holds that is not one of them (a stale
    run) is not counted, so it can never pass 100."""
    nan = float("nan")
    n_images = len(image_names)
    report = result.report or {}
    models = result.poses if not result.error else []
    summary = accuracy_summary(models, reference) if reference else {}
    registered = len(set(image_names).intersection(set().union(*models))) if models else 0
    largest = (report.get("models") or [{}])[0]
    counts = report.get("counts", {})
    return {
        "registered_pct": 100.0 * registered / max(n_images, 1), "registered": registered, "images": n_images,
        "components": len(models), "points": largest.get("points", 0),
        "mean_track_length": largest.get("mean_track_length", nan),
        "mean_reprojection_error_px": largest.get("mean_reprojection_error_px", nan),
        "auc@1": summary.get("auc@1", 0.0), "auc@5": summary.get("auc@5", 0.0),
        "auc@10": summary.get("auc@10", 0.0),
        "keypoints_per_image": counts.get("keypoints_per_image", nan),
        "mean_inliers_per_pair": counts.get("mean_inliers_per_pair", nan),
        "verified_pairs": counts.get("verified_pairs", nan), "wall_s": result.wall_s,
        "peak_mem_mb": result.peak_mem_mb, "error": result.error or "",
    }


def tabulate(config: StudyConfig, grid: Grid, results: dict, image_names: list[str]) -> list[dict]:
    """One row per engine x degradation x level; the clean row appears once per degradation at its identity."""
    gt = load_reference(config, image_names)
    rows = []
    for engine in config.engines:
        clean = results[(engine, CLEAN)]
        reference = gt if gt is not None else (clean.poses[0] if clean.poses and not clean.error else None)
        ref_name = "ground truth" if gt is not None else f"{engine} on the clean images"
        measured = {}
        for (eng, key), result in results.items():
            if eng == engine:
                measured[key] = measure(result, reference, image_names)
        for axis in grid.axes():
            levels = [AXES[axis].identity] + grid.degraded_levels(axis)
            for level in levels:
                key = CLEAN if level == AXES[axis].identity else Cell(axis, level).key
                rows.append({"engine": engine, "degradation": axis, "level": level, **measured[key],
                             "reference": ref_name})
    return rows


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) and not math.isnan(v) else
                                 ("" if isinstance(v, float) else v)) for k, v in row.items() if k in COLUMNS})


def read_csv(path: Path) -> list[dict]:
    """study.csv back as rows with numbers as floats (empty cells as NaN)."""
    text_columns = {"engine", "degradation", "reference", "error"}
    with open(path, newline="") as f:
        return [{k: (v if k in text_columns else (float(v) if v != "" else float("nan"))) for k, v in row.items()}
                for row in csv.DictReader(f)]


def breaking_points(rows: list[dict], fraction: float = 0.5) -> dict:
    """(engine, degradation) -> the first level (in the order given) where registered % or AUC@5 falls below
    `fraction` of the clean value, with which metric broke; level None when it holds at every level tested.

    The first row of each (engine, degradation) is the clean one (tabulate's order).
    """
    groups = {}
    for row in rows:
        groups.setdefault((row["engine"], row["degradation"]), []).append(row)
    out = {}
    for key, group in groups.items():
        clean, degraded = group[0], group[1:]
        verdict = {"level": None, "metric": None, "clean_registered_pct": clean["registered_pct"],
                   "clean_auc@5": clean["auc@5"], "tested": [r["level"] for r in degraded]}
        if clean["registered_pct"] == 0:
            verdict["metric"] = "clean run failed"
        for row in degraded if clean["registered_pct"] > 0 else []:
            broke = [m for m in ("registered_pct", "auc@5")
                     if clean[m] > 0 and not row[m] >= fraction * clean[m]]
            if broke:
                verdict.update(level=row["level"], metric=" and ".join(
                    {"registered_pct": "registered %", "auc@5": "AUC@5"}[m] for m in broke))
                break
        out[key] = verdict
    return out


def run_study(config: StudyConfig, grid: Grid, study_dir: Path | str, command: str | None = None,
              retry_failed: bool = False, listing: tuple[list[str], dict[str, str]] | None = None) -> list[dict]:
    """Everything `mvrecon study` does: cells, runs, study.csv, plots, contact sheet and study.html.

    `retry_failed` reruns the cells whose engine run failed before (otherwise a failure is a cached result).
    `listing`: `io.images.list_images(config.images)` when the caller has it already (its warnings are not
    repeated).
    """
    study_dir = Path(study_dir)
    check_engines(config.engines)
    image_names, skipped = listing if listing is not None else list_images(config.images)
    load_reference(config, image_names)  # fail on a bad ground truth before hours of runs
    record = claim_study_dir(study_dir, config)
    cells = grid.cells()
    folders = prepare_images(study_dir, config, cells, image_names, record)
    if retry_failed:
        for name in forget_failed_runs(study_dir, config.engines, cells):
            log.info("retrying %s (it failed before)", name)
    results = run_cells(study_dir, config, folders, cells)
    rows = tabulate(config, grid, results, image_names)
    write_csv(rows, study_dir / "study.csv")
    plots = metric_plots(rows, grid, study_dir / "plots")
    sheet = contact_sheet(folders, grid, study_dir / "contact_sheet.png", names=image_names)
    write_report(study_dir / "study.html", config, grid, rows, breaking_points(rows), plots, sheet, command,
                 skipped=skipped)
    return rows
