"""Is a scene usable? Run COLMAP's own pipeline on its images and compare the result with the ground truth.

This is the acceptance check of the catalog: pycolmap extracts SIFT, matches exhaustively and maps
incrementally; every image should register and, after a Sim3 alignment of camera centres, each rotation
should agree with the ground truth within half a degree.
"""

import time
from pathlib import Path

import pycolmap

from ..eval.metrics import accuracy_summary, align_and_compare
from ..eval.models import load_reconstruction, model_stats, poses


def colmap_reconstruct(
    scene_dir: Path | str, work_dir: Path | str, camera_model: str | None = None, num_threads: int = -1
) -> dict:
    """pycolmap's extract -> exhaustive match -> incremental mapping on scene_dir/images, one shared camera.

    camera_model defaults to the ground truth's model (the focal length is not given: COLMAP guesses it).
    Returns {"models": [Reconstruction, ...] largest first, "seconds": {stage: wall time}}.
    """
    scene_dir, work_dir = Path(scene_dir), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if database.exists():
        database.unlink()
    gt = load_reconstruction(scene_dir / "gt" / "sparse")
    model = camera_model or next(iter(gt.cameras.values())).model.name
    reader = pycolmap.ImageReaderOptions(camera_model=model)
    extraction = pycolmap.FeatureExtractionOptions(num_threads=num_threads, use_gpu=False)
    seconds = {}
    start = time.perf_counter()
    pycolmap.extract_features(
        database,
        scene_dir / "images",
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    seconds["extract"] = time.perf_counter() - start
    start = time.perf_counter()
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    seconds["match"] = time.perf_counter() - start
    start = time.perf_counter()
    options = pycolmap.IncrementalPipelineOptions(num_threads=num_threads)
    models = pycolmap.incremental_mapping(
        database, scene_dir / "images", work_dir / "sparse", options=options
    )
    seconds["map"] = time.perf_counter() - start
    ordered = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    return {"models": ordered, "seconds": seconds}


def compare_with_ground_truth(scene_dir: Path | str, models: list) -> dict:
    """Headline accuracy of estimated models against gt/sparse (metric names as in eval.metrics)."""
    gt = poses(load_reconstruction(Path(scene_dir) / "gt" / "sparse"))
    est = [poses(m) for m in models]
    summary = accuracy_summary(est, gt)
    summary["images"] = len(gt)
    if models:
        summary.update(model_stats(models[0]))
        alignment = align_and_compare(est[0], gt)
        summary["registered_in_largest"] = models[0].num_reg_images()
        if alignment is not None:
            summary["rotation_errors_deg"] = alignment.rotation_errors_deg
            centre = max(alignment.center_errors.values())
            summary["max_center_error_pct"] = 100.0 * centre / max(alignment.scene_extent, 1e-12)
    return summary
