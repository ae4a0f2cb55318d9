"""mvrecon against COLMAP on the same images: run the engines, align each model to one reference, measure.

The reference is the ground truth when there is one, else COLMAP's largest model (then COLMAP's own accuracy cells
are "reference", not numbers), as long as it is trustworthy: a COLMAP run that failed, or whose model holds fewer
images than another engine's or under half of them, is not (`choose_reference`), and the report says so at its
top. Every model is aligned to it by our robust Sim3 of camera centres (`metrics.align_and_compare`), and that
alignment is cross-checked against pycolmap's `align_reconstructions_via_proj_centers`: the largest distance
between the centres placed by the two, as % of the scene's extent, is reported, so a bad alignment cannot hide
behind good-looking numbers.

Everything the report shows comes out of one dict (`Comparison.metrics`), which is also written as metrics.json:
the page and the files cannot disagree.
"""

import logging
import math
import os
import platform
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import psutil
import pycolmap

from ..database import database_counts
from ..errors import InputError
from ..io.files import printable_name
from ..io.images import IMAGE_EXTENSIONS, list_images
from ..progress import progress
from . import metrics as M
from .dense import workspace_summary
from .ground_truth import load_ground_truth_for
from .models import load_reconstruction, model_stats, reconstruction_from_poses, sparse_models
from .runners import (
    RunOptions,
    RunResult,
    load_run,
    refuse_other_settings,
    run_colmap,
    run_colmap_on_database,
    run_mvrecon,
)

log = logging.getLogger("mvrecon.eval.compare")

DIAGNOSTIC_ENGINES = ("colmap-same-matches",)  # shown, but not in the race for a row's winner
STAGES = ("features", "matching", "mapping")


@dataclass(frozen=True)
class CompareConfig:
    options: RunOptions = RunOptions()  # camera settings and seed, the same for every engine
    colmap_global: bool = False  # also run pycolmap's global mapper (GLOMAP)
    mvrecon_global: bool = False  # also run mvrecon's global mapper (`--mapper global`)
    same_matches: bool = True  # also run COLMAP's incremental mapper on mvrecon's database
    inlier_fraction: float = 0.05  # Sim3 RANSAC inlier threshold, as a fraction of the reference's extent
    timeout_s: float | None = None  # per run; a run over time is reported as failed, with that reason
    max_points_3d: int = 20000  # points per model drawn in the 3D view (a seeded subsample); metrics use all


# (metric key, label, unit, which way is better: "higher", "lower" or None for no winner)
ROWS = (
    ("registered", "registered images", "", "higher"),
    ("registered_pct", "registered", "%", "higher"),
    ("components", "components (models)", "", "lower"),
    ("points", "points (largest model)", "", "higher"),
    ("mean_track_length", "mean track length", "", "higher"),
    ("mean_reprojection_error_px", "mean reprojection error", "px", "lower"),
    ("auc@0.5", "relative-pose AUC@0.5", "", "higher"),
    ("auc@1", "relative-pose AUC@1", "", "higher"),
    ("auc@5", "relative-pose AUC@5", "", "higher"),
    ("auc@10", "relative-pose AUC@10", "", "higher"),
    ("misplaced", "images at a wrong pose (largest model)", "", "lower"),
    ("median_rotation_error_deg", "median rotation error", "deg", "lower"),
    ("max_rotation_error_deg", "max rotation error", "deg", "lower"),
    ("median_center_error", "median centre error", "units", "lower"),
    ("median_center_error_pct", "median centre error", "% extent", "lower"),
    ("alignment_inliers", "Sim3 alignment inliers", "", "higher"),
    ("alignment_pycolmap_disagreement_pct", "our Sim3 vs pycolmap's", "% extent", None),
    ("keypoints_per_image", "keypoints per image", "", None),
    ("verified_pairs", "verified pairs", "", "higher"),
    ("mean_inliers_per_pair", "mean inliers per pair", "", "higher"),
    ("features_wall_s", "features wall time", "s", "lower"),
    ("matching_wall_s", "matching wall time", "s", "lower"),
    ("mapping_wall_s", "mapping wall time", "s", "lower"),
    ("wall_s", "total wall time", "s", "lower"),
    ("time_ratio_vs_colmap", "wall time / COLMAP's", "x", None),
    ("peak_mem_mb", "peak memory", "MB", "lower"),
)
ACCURACY_KEYS = ("auc@0.5", "auc@1", "auc@5", "auc@10", "misplaced", "median_rotation_error_deg",
                 "max_rotation_error_deg", "median_center_error", "median_center_error_pct", "alignment_inliers",
                 "alignment_pycolmap_disagreement_pct")


@dataclass(kw_only=True)
class Geometry:
    """What the 3D view draws of one model, already in the reference frame."""

    cameras: dict = field(default_factory=dict)  # name -> (R world-to-camera, centre, width/height, fov_x in rad)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass(kw_only=True)
class Comparison:
    metrics: dict  # every number of the report (written as metrics.json)
    geometry: dict  # engine or "ground truth" -> Geometry, for the 3D view


def compare_images(image_dir: Path | str, report_dir: Path | str, gt: Path | str | None = None,
                   config: CompareConfig = CompareConfig(), *,
                   listing: tuple[list[str], dict[str, str]] | None = None) -> Comparison:
    """Run mvrecon, pycolmap (and the same-matches run) on IMAGE_DIR into REPORT_DIR/runs/ and measure them.

    `listing`: what `io.images.list_images(image_dir)` returned, when the caller has listed the folder already
    (its warnings are then printed once). Image files that cannot be read are named, with the reason, in the
    metrics' "skipped_images": no engine sees them, and a report that left them out would look complete.
    """
    image_dir, report_dir = Path(image_dir), Path(report_dir)
    names, skipped = listing if listing is not None else list_images(image_dir)
    skipped = {n: r for n, r in skipped.items() if Path(n).suffix.lower() in IMAGE_EXTENSIONS}
    gt_poses = load_ground_truth_for(gt, names) if gt else None
    runs_dir = report_dir / "runs"
    steps = ["mvrecon", "colmap"] + (["mvrecon-global"] if config.mvrecon_global else []) \
        + (["colmap-global"] if config.colmap_global else []) \
        + (["colmap-same-matches"] if config.same_matches else [])
    mvrecon_db = runs_dir / "mvrecon" / "database.db"  # what the same-matches run maps
    for step in steps:  # a folder of a run with other settings is refused before any engine spends time
        refuse_other_settings(step, mvrecon_db if step == "colmap-same-matches" else image_dir, runs_dir / step,
                              config.options)
    runs = []
    bar = progress(total=len(steps), desc="compare", unit="run")
    for step in steps:
        bar.set_postfix_str(step)
        timeout, opts = config.timeout_s, config.options
        if step in ("mvrecon", "mvrecon-global"):
            runs.append(run_mvrecon(image_dir, runs_dir / step, opts, timeout, global_mapper=step != "mvrecon"))
        elif step == "colmap":
            runs.append(run_colmap(image_dir, runs_dir / step, opts, False, timeout))
        elif step == "colmap-global":
            runs.append(run_colmap(image_dir, runs_dir / step, opts, True, timeout))
        else:
            if mvrecon_db.is_file():
                runs.append(run_colmap_on_database(mvrecon_db, runs_dir / step, image_dir, opts, timeout))
            else:
                runs.append(RunResult(engine=step, out_dir=runs_dir / step,
                                      error="mvrecon wrote no database.db, so there were no matches to map"))
        if runs[-1].error:
            log.warning("%s failed: %s", step, runs[-1].error)
        bar.update(1)
    bar.close()
    title = image_dir.resolve().name if image_dir.name != "images" else image_dir.resolve().parent.name
    return evaluate(runs, names, gt_poses, config, title=title, source=str(image_dir),
                    gt_source=str(gt) if gt else None, skipped=skipped)


def compare_models(paths: list[Path | str], gt: Path | str | None = None, labels: list[str] | None = None,
                   config: CompareConfig = CompareConfig()) -> Comparison:
    """Compare models that already exist: run folders (report.json + sparse/), sparse/ folders or model folders.

    Without ground truth the LAST model is the reference, so two are needed; with it one model is scored
    against it. The images counted are those any model or report lists (an image no model holds and no report
    names cannot be known).
    """
    paths = [Path(p) for p in paths]
    if len(paths) < 2 and gt is None:
        raise InputError("--models: give at least two models to compare, or one with --gt")
    if labels and len(labels) != len(paths):
        raise InputError(f"--labels: {len(labels)} labels for {len(paths)} models")
    runs, used = [], set()
    for k, path in enumerate(paths):
        if (path / "report.json").is_file():
            run = load_run(path)
        elif (path / "images.bin").exists() or (path / "images.txt").exists():
            run = RunResult(engine=path.name, out_dir=path, models=[load_reconstruction(path)])
        elif (path / "sparse").is_dir() or path.name == "sparse":
            sparse = path if path.name == "sparse" else path / "sparse"
            run = RunResult(engine=path.name, out_dir=path, models=sparse_models(sparse))
            if not run.models:
                raise InputError(f"{path}: no COLMAP model under {sparse}")
        elif not path.exists():
            raise InputError(f"{path}: no such folder")
        else:
            raise InputError(f"{path}: not a COLMAP model, a sparse/ folder or a run folder with report.json")
        # the label names the engine in the table, the plots and the CSV: in printable text
        label = printable_name(labels[k] if labels else (run.engine if run.report else _folder_label(path)))
        while label in used:
            label += "'"
        used.add(label)
        run.engine = label
        runs.append(run)
    names = set()
    for run in runs:
        names |= set(run.report.get("images", {}))
        for rec in run.models:
            names |= {im.name for im in rec.images.values()}
    names = sorted(names)
    gt_poses = load_ground_truth_for(gt, names) if gt else None
    return evaluate(runs, names, gt_poses, config, title=" vs ".join(r.engine for r in runs),
                    source=", ".join(str(p) for p in paths), gt_source=str(gt) if gt else None,
                    reference_engine=None if gt_poses is not None else runs[-1].engine)


def _folder_label(path: Path) -> str:
    parts = [p for p in path.resolve().parts if p not in ("sparse",) and not p.isdigit()]
    return parts[-1] if parts else str(path)


def evaluate(runs: list[RunResult], image_names: Iterable[str], gt_poses: dict | None = None,
             config: CompareConfig = CompareConfig(), *,
             title: str = "", source: str = "", gt_source: str | None = None,
             reference_engine: str | None = "colmap", skipped: dict[str, str] | None = None) -> Comparison:
    """Metrics of every run against the reference (ground truth, else `reference_engine`'s largest model).
    `skipped`: image files of the source that no engine could read, name -> reason (listed, not counted)."""
    image_names = sorted(image_names)
    if gt_poses is not None:
        ref_poses, ref_name, reference_engine, note = dict(gt_poses), "ground truth", None, ""
    else:
        reference_engine, note = choose_reference(runs, image_names, reference_engine)
        ref_run = next((r for r in runs if r.engine == reference_engine), None)
        ref_poses = ref_run.poses[0] if ref_run is not None and ref_run.models else {}
        ref_name = reference_engine
    engines, geometry = {}, {}
    for run in runs:
        role = "reference" if run.engine == reference_engine else (
            "diagnostic" if run.engine in DIAGNOSTIC_ENGINES else "engine")
        engines[run.engine], geometry[run.engine] = _evaluate_run(run, role, image_names, ref_poses, config)
    colmap_wall = engines.get("colmap", {}).get("summary", {}).get("wall_s")
    for e in engines.values():
        wall = e["summary"]["wall_s"]
        ok = _finite(wall) and _finite(colmap_wall) and colmap_wall > 0 and e["role"] != "diagnostic"
        e["summary"]["time_ratio_vs_colmap"] = wall / colmap_wall if ok else None
    if gt_poses is not None:
        geometry["ground truth"] = _reference_geometry(gt_poses, config)
    metrics = {
        "title": title, "source": source,
        "created": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "machine": machine_info(),
        "reference": {"name": ref_name, "source": gt_source if gt_poses is not None else ref_name,
                      "images": len(ref_poses), "note": note},
        "images": image_names, "skipped_images": dict(sorted((skipped or {}).items())),
        "engines": engines, "rows": summary_rows(engines),
    }
    return Comparison(metrics=jsonable(metrics), geometry=geometry)


def model_sizes(run: RunResult, image_names: Iterable[str]) -> list[int]:
    """How many of `image_names` each model of the run holds, largest model first ([] for a run without one)."""
    names = set(image_names)
    return [len(names.intersection(m)) for m in run.poses]


def choose_reference(runs: list[RunResult], image_names: list[str],
                     default: str | None) -> tuple[str | None, str]:
    """Without ground truth: the engine whose largest model every other is scored against, and the note the
    report shows at its top when that is not `default` (COLMAP's, or the last of --models) or there is none.

    `default` is trusted while its largest model holds at least as many images as any other engine's and at
    least half of them. Otherwise the engine whose model holds the most images is, when that is half of them or
    more; else there is no trustworthy reference and nothing is scored. Against a reference of 2 images (COLMAP's
    on opensfm_lund, of 29, where mvrecon registers all 29) every other model scores AUC 0.000, which says
    nothing about it. Diagnostic runs (COLMAP's mapper on mvrecon's matches) are never the reference.
    """
    n = len(image_names)
    enough = max(2, math.ceil(n / 2))
    sizes = {r.engine: (model_sizes(r, image_names) or [0])[0] for r in runs
             if r.engine not in DIAGNOSTIC_ENGINES or r.engine == default}
    if not sizes:
        return None, "no trustworthy reference: no ground truth was given and no engine ran"
    best = max(sizes, key=lambda e: (sizes[e], e == default))  # the most images; `default` wins a tie
    own = sizes.get(default, 0)
    if default in sizes and own >= max(sizes[best], enough):
        return default, ""
    run = next((r for r in runs if r.engine == default), None)
    if run is None:
        why = f"no {default} run"
    elif run.error:
        why = f"{default}'s run failed ({run.error})"
    elif not run.models:
        why = f"{default} made no model"
    else:
        why = f"{default}'s largest model holds {own} of the {n} images" + (
            f", fewer than {best}'s {sizes[best]}" if sizes[best] > own else ", under half of them")
    if sizes[best] >= enough:
        return best, (f"{why}: not a trustworthy reference, so every model is scored against {best}'s largest "
                      f"model ({sizes[best]} of {n} images), the one with the most images")
    return None, (f"no trustworthy reference: no ground truth was given, {why}, and no model holds half of the "
                  f"{n} images; accuracy is not scored")


def _evaluate_run(run: RunResult, role: str, image_names, ref_poses: dict, config: CompareConfig):
    models = run.poses
    largest_rec = run.models[0] if run.models else None
    stats = model_stats(largest_rec) if largest_rec is not None else {}
    model_of = {}
    for k, m in enumerate(models):
        for n in m:
            model_of.setdefault(n, k)
    # the largest model's images are the headline, the other models' shown beside them ("13 + 3"): their sum is
    # no one model (templeSparseRing: 13 + 3 images in mvrecon's models, 13 in COLMAP's one)
    sizes = model_sizes(run, image_names)
    largest = sizes[0] if sizes else 0
    summary = {"registered": largest, "registered_pct": 100.0 * largest / max(len(image_names), 1),
               "registered_other_models": [k for k in sizes[1:] if k], "components": len(models),
               "points": stats.get("points"),
               "mean_track_length": stats.get("mean_track_length"),
               "mean_reprojection_error_px": stats.get("mean_reprojection_error_px")}
    counts = _counts(run)
    summary.update({k: counts.get(k) for k in ("keypoints_per_image", "verified_pairs", "mean_inliers_per_pair")})
    stages = {k: dict(v) for k, v in run.report.get("stages", {}).items()}
    for stage in STAGES:
        summary[f"{stage}_wall_s"] = stages.get(stage, {}).get("wall_s")
    summary["wall_s"] = run.wall_s if _finite(run.wall_s) else None
    summary["peak_mem_mb"] = run.peak_mem_mb if _finite(run.peak_mem_mb) else None

    reasons = {n: v.get("reason") for n, v in run.report.get("images", {}).items()}
    per_image = {}
    for n in image_names:
        if n in model_of:
            per_image[n] = {"status": "registered", "model": model_of[n], "reason": None}
        else:
            reason = run.error and f"run failed: {run.error}" or reasons.get(n) or "not in any model"
            per_image[n] = {"status": "unregistered", "model": None, "reason": reason}

    relative, alignment, geometry = [], None, Geometry()
    if len(ref_poses) >= 2 and role != "reference":
        errors = M.relative_pose_errors(models, ref_poses)
        relative = errors.tolist()
        summary.update({f"auc@{t:g}": v for t, v in M.pose_auc(errors).items()})
        misplaced = M.misplaced_images(models[0], ref_poses) if models else []
        summary["misplaced"] = len(misplaced)
        for n in misplaced:  # images of the largest model: per_image says model 0 for each
            per_image[n]["misplaced"] = True
        al = M.align_and_compare(models[0] if models else {}, ref_poses, config.inlier_fraction)
        if al is not None:
            rot, cen = np.array(list(al.rotation_errors_deg.values())), np.array(list(al.center_errors.values()))
            extent = max(al.scene_extent, 1e-12)
            summary.update({"median_rotation_error_deg": float(np.median(rot)),
                            "max_rotation_error_deg": float(rot.max()),
                            "median_center_error": float(np.median(cen)),
                            "median_center_error_pct": float(100 * np.median(cen) / extent),
                            "alignment_inliers": len(al.inliers),
                            "alignment_pycolmap_disagreement_pct":
                                _pycolmap_disagreement(models[0], ref_poses, al, config.inlier_fraction)})
            for n in al.rotation_errors_deg:
                if per_image.get(n, {}).get("model") == 0:
                    per_image[n].update({"rotation_error_deg": al.rotation_errors_deg[n],
                                         "center_error": al.center_errors[n],
                                         "center_error_pct": 100 * al.center_errors[n] / extent,
                                         "alignment_inlier": n in al.inliers})
            alignment = {"scale": al.sim3.scale, "R": al.sim3.R.tolist(), "t": al.sim3.t.tolist(),
                         "scene_extent": al.scene_extent, "inliers": len(al.inliers)}
            geometry = _aligned_geometry(largest_rec, al.sim3, config)
    elif role == "reference" and largest_rec is not None:
        geometry = _aligned_geometry(largest_rec, None, config)
    for key in ACCURACY_KEYS:
        summary.setdefault(key, None)
    return ({"role": role, "error": run.error, "out_dir": str(run.out_dir), "summary": summary, "stages": stages,
             "per_image": per_image, "relative_pose_errors_deg": relative, "alignment": alignment,
             "dense": workspace_summary(run.out_dir / "dense")}, geometry)


def _counts(run: RunResult) -> dict:
    """Front-end counts from the run's database when it has one (the same counting for every engine)."""
    db = run.out_dir / "database.db"
    if db.is_file():
        return database_counts(db)
    return run.report.get("counts", {})


def _pycolmap_disagreement(est_poses: dict, ref_poses: dict, al, inlier_fraction: float) -> float | None:
    """Largest distance (% of extent) between camera centres placed by our Sim3 and by pycolmap's."""
    src, tgt = reconstruction_from_poses(est_poses), reconstruction_from_poses(ref_poses)
    sim = pycolmap.align_reconstructions_via_proj_centers(src, tgt, inlier_fraction * al.scene_extent)
    if sim is None:
        return None
    names = sorted(set(est_poses) & set(ref_poses))
    centres = np.array([M.camera_center(*est_poses[n]) for n in names])
    theirs = float(sim.scale) * centres @ np.asarray(sim.rotation.matrix()).T + np.asarray(sim.translation)
    return float(100 * np.max(np.linalg.norm(al.sim3.apply(centres) - theirs, axis=1)) / max(al.scene_extent, 1e-12))


def _aligned_geometry(rec, sim3, config: CompareConfig) -> Geometry:
    cameras = {}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        T = im.cam_from_world()
        R, t = np.asarray(T.rotation.matrix()), np.asarray(T.translation)
        C = M.camera_center(R, t)
        if sim3 is not None:
            C, R = sim3.apply(C[None])[0], R @ sim3.R.T
        cam = im.camera
        fov = 2 * math.atan(cam.width / 2 / max(cam.mean_focal_length(), 1e-9))
        cameras[im.name] = (R, C, cam.width / cam.height, fov)
    ids = list(rec.points3D)
    rng = np.random.default_rng(0)
    if len(ids) > config.max_points_3d:
        ids = [ids[i] for i in np.sort(rng.choice(len(ids), config.max_points_3d, replace=False))]
    xyz = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
    if sim3 is not None and len(xyz):
        xyz = sim3.apply(xyz)
    return Geometry(cameras=cameras, points=xyz)


def _reference_geometry(gt, config: CompareConfig) -> Geometry:
    cameras = {}
    for n, (R, t) in gt.items():
        K = getattr(gt, "intrinsics", {}).get(n)
        aspect, fov = 4 / 3, math.radians(50)
        if K is not None and K[0, 2] > 0 and K[1, 2] > 0:
            aspect, fov = K[0, 2] / K[1, 2], 2 * math.atan(K[0, 2] / K[0, 0])
        cameras[n] = (np.asarray(R), M.camera_center(R, t), aspect, fov)
    points = getattr(gt, "points", None)
    points = np.zeros((0, 3)) if points is None else np.asarray(points)
    if len(points) > config.max_points_3d:
        points = points[np.sort(np.random.default_rng(0).choice(len(points), config.max_points_3d, replace=False))]
    return Geometry(cameras=cameras, points=points)


def summary_rows(engines: dict) -> list[dict]:
    """The summary table: one row per metric, the value of each engine, and the winner(s) among the engines.

    Diagnostic runs and the reference do not compete; when every competitor ties there is no winner. Images
    registered in a model without a single point do not compete either: COLMAP's pipeline returns such a model
    for a camera turning in place (3 images 10 units apart, the catalog's panorama_small), and the star said it
    had registered the most.
    """
    rows = []
    for key, label, unit, better in ROWS:
        values = {name: e["summary"].get(key) for name, e in engines.items()}
        winners = []
        competing = {n: v for n, v in values.items() if engines[n]["role"] == "engine" and _finite(v)
                     and not (key.startswith("registered") and not engines[n]["summary"].get("points"))}
        if better and len(competing) >= 2:
            best = (max if better == "higher" else min)(competing.values())
            winners = [n for n, v in competing.items() if math.isclose(v, best, rel_tol=1e-9, abs_tol=1e-12)]
            if len(winners) == len(competing):
                winners = []
        rows.append({"metric": key, "label": label, "unit": unit, "better": better, "values": values,
                     "winners": winners})
    return rows


def machine_info() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gb": round(psutil.virtual_memory().total / 2 ** 30, 1),
            "system": f"{platform.system()} {platform.release()}", "python": platform.python_version()}


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def jsonable(obj: object) -> object:
    """Plain JSON types; NaN and inf become None (JSON has no NaN, and JavaScript would choke on it)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    return obj
