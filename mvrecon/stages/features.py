"""The features stage: images -> cameras, keypoints and descriptors in the workspace's database.

`extract_features(config, image_dir, workspace)` detects SIFT in every image not yet in the database,
committing one image at a time, so an interrupted run loses at most the images in progress. The images are
handed to an `executor.WorkerPool`, or to a Dask cluster (`--cluster`, mvrecon/cluster.py), at `_hand_out`.
"""

import contextlib
import logging
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import database as dbmod
from ..cameras import GIVEN_KEY, CameraConfig, group_cameras
from ..cluster import Cluster
from ..config import to_dict
from ..errors import InputError
from ..executor import WorkerPool
from ..features.sift import extract_sift, extraction_memory_mb
from ..io.files import read_json_object, some_names, write_json
from ..io.images import (
    IMAGE_EXTENSIONS,
    colors_at,
    decoding_for_detection,
    image_metadata,
    list_images,
    read_image_for_detection,
)
from ..io.masks import check_masks, find_masks, keypoints_outside_mask, mask_path
from ..io.pose_priors import exif_priors, read_priors_csv
from ..progress import progress
from ..workspace import Workspace
from .common import FrontendConfig, as_workspace, stats_text, worker_count

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class FeatureSummary:
    """What the features stage did: the images with features, their keypoint counts, the ones skipped."""

    num_images: int  # images of the folder with features in the database
    num_extracted: int  # of which extracted in this run (the rest were already there)
    keypoints: dict[str, int]  # name -> keypoint count
    failed: dict[str, str] = field(default_factory=dict)  # images unreadable or not extracted: name -> reason
    skipped: dict[str, str] = field(default_factory=dict)  # every file left out (not an image, unreadable)
    num_cameras: int = 0
    seconds: float = 0.0
    # name -> colours at its keypoints (io.images.colors_at), for the images extracted in this run: the
    # models' point colours come from them instead of decoding the images again (see map_workspace)
    keypoint_colors: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def text(self) -> str:
        parts = [f"Features: {self.num_images} images ({self.num_extracted} extracted now, "
                 f"{self.num_images - self.num_extracted} already done) in {self.seconds:.1f} s, "
                 f"{self.num_cameras} camera(s); keypoints per image: "
                 f"{stats_text(list(self.keypoints.values()))}."]
        if self.failed:
            parts.append(f"{len(self.failed)} image(s) unreadable or not extracted, skipped: "
                         f"{', '.join(sorted(self.failed))}.")
        others = len(set(self.skipped) - set(self.failed))
        if others:
            parts.append(f"{others} non-image file(s) skipped.")
        return " ".join(parts)


def _extract_job(job):
    """Worker: (path, name, sift config, mask path or None, OpenCV threads or None to leave them) -> (name,
    (keypoints, descriptors, keypoint colours)) or (name, error message)."""
    path, name, sift_config, mask, threads = job
    try:
        if threads is not None:
            import cv2  # noqa: PLC0415 - in the worker: the parent forks its workers before loading OpenCV

            if cv2.getNumThreads() != threads:
                cv2.setNumThreads(threads)
        # a large JPEG decoded at 1/2-1/8 of its size (bounded memory); its colours are sampled there too
        image, reduced = read_image_for_detection(path, sift_config.max_image_size)
        keypoints, descriptors = extract_sift(image, sift_config, reduced)
        if mask is not None:
            full_shape = (image.shape[0] * reduced, image.shape[1] * reduced)
            keep = keypoints_outside_mask(mask, path, keypoints, full_shape)
            keypoints, descriptors = keypoints[keep], descriptors[keep]
        return name, (keypoints, descriptors, colors_at(image, keypoints[:, :2] / reduced))
    except InputError as exc:
        return name, str(exc)
    except Exception as exc:  # OpenCV or memory errors on one image must not stop the run
        return name, f"{path}: {type(exc).__name__}: {exc}"


def _extract_sent(sent):
    """Worker of a cluster that does not see the image folder: (`_extract_job`'s job, the image's bytes, the
    mask's bytes or None) -> `_extract_job`'s result, the bytes written to a temporary folder of the worker
    under the file's own name (its format is told by its suffix)."""
    job, image_bytes, mask_bytes = sent
    path, name, sift_config, mask, threads = job
    folder = Path(tempfile.mkdtemp(prefix="mvrecon-image-"))
    try:
        local = folder / Path(path).name
        local.write_bytes(image_bytes)
        local_mask = None
        if mask_bytes is not None:
            local_mask = folder / ("mask-" + Path(mask).name)
            local_mask.write_bytes(mask_bytes)
        result = _extract_job((local, name, sift_config, local_mask, threads))
        if isinstance(result[1], str):  # a message names the user's file, not the worker's copy
            result = (result[0], result[1].replace(str(local), str(path)))
        return result
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _with_bytes(jobs: list[tuple]):
    """`_extract_sent`'s items for `jobs`, each file read when its item is handed out."""
    for job in jobs:
        mask = job[3]
        yield job, Path(job[0]).read_bytes(), None if mask is None else Path(mask).read_bytes()


def _hand_out(pool: WorkerPool | Cluster, jobs: list[tuple], folder: Path | None = None):
    """`_extract_job`'s results for `jobs`, in their order, computed by `pool`: as many images at a time as the
    memory available holds (`_extraction_memory_mb`), and an image whose worker died twice skipped with the
    reason. On a cluster whose workers do not all see `folder` at the same path, the client reads each image
    and sends its bytes (`_extract_sent`)."""
    def died(job, why):
        return job[1], f"{job[0]}: the worker extracting it died twice: {why}"

    if isinstance(pool, Cluster):
        per_task = images_per_task(len(jobs), pool.workers)
        if folder is not None and not pool.workers_see(folder):
            log.info("%s: not seen by every worker of the cluster; the images are sent to them", folder)
            return pool.map(_extract_sent, _with_bytes(jobs), name=lambda sent: str(sent[0][0]),
                            died=lambda sent, why: died(sent[0], why), per_task=per_task)
        return pool.map(_extract_job, jobs, name=lambda job: str(job[0]), died=died, per_task=per_task)
    return pool.map(_extract_job, jobs, name=lambda job: str(job[0]), cost=_extraction_memory_mb, died=died)


def images_per_task(count: int, workers: int) -> int:
    """Images in one task of a cluster for `count` images on `workers` worker threads: up to 4, so that what a
    task costs the client and the scheduler whatever it holds is paid once for several images, but at least 8
    tasks per worker thread, so that the workers' last tasks end close together."""
    return max(1, min(4, count // (8 * max(1, workers))))


def _extraction_memory_mb(job) -> float:
    """The memory a worker needs for `_extract_job(job)` (MB), from the image's header."""
    path, _, sift_config, _, _ = job
    width, height, reduced, _ = decoding_for_detection(path, sift_config.max_image_size)
    return extraction_memory_mb(width, height, sift_config, reduced)


def _extraction_jobs(folder: Path, names, config: FrontendConfig, masks: dict, workers: int, *,
                     one_thread: bool = False) -> list[tuple]:
    """`_extract_job`'s jobs. In a pool, each image runs on one OpenCV thread (a worker per core), except the
    last `workers` images, which run on `workers` threads each: when a worker takes one of them no image is left
    for the others, whose cores would stand idle until it ends (templeSparseRing: 20-65 ms of a core). OpenCV's
    SIFT gives the same keypoints and descriptors on any number of threads (it sorts them). In-process
    (`workers <= 1`) the threads are left as they are. With `one_thread` (a cluster) every image runs on one
    thread: a worker thread per core, and the cores of one machine are not those of the whole cluster."""
    if one_thread:
        return [(folder / n, n, config.sift, masks.get(n), 1) for n in names]
    tail = len(names) - workers
    return [(folder / n, n, config.sift, masks.get(n), None if workers <= 1 else workers if k >= tail else 1)
            for k, n in enumerate(names)]


def require_images(folder: Path | str) -> tuple[list[str], dict[str, str]]:
    """`list_images(folder)`, or an InputError when fewer than 2 images are readable: checked before any work
    (extraction here, the engines in compare and study)."""
    names, skipped = list_images(folder)
    if len(names) < 2:
        _too_few(Path(folder), len(names), _unreadable(Path(folder), skipped))
    return names, skipped


def _unreadable(folder: Path, skipped: dict[str, str]) -> dict[str, str]:
    """The image files among the skipped ones (not the other files), name -> "path: why"."""
    return {n: f"{folder / n}: {r}" for n, r in skipped.items() if Path(n).suffix.lower() in IMAGE_EXTENSIONS}


STAMPS = "images.json"  # in the workspace: name -> [size, mtime_ns] of every image file when features were read


def image_stamps(folder: Path, names: Iterable[str]) -> dict[str, list[int]]:
    """Size and modification time of each file: what tells a rerun that an image changed since it was read."""
    out = {}
    for name in names:
        try:
            st = (folder / name).stat()
        except OSError:
            continue
        out[name] = [st.st_size, st.st_mtime_ns]
    return out


def _check_unchanged(folder: Path, ws: Workspace, extracted, now: dict[str, list[int]], masked=False) -> None:
    """Refuse a workspace whose images (or masks) were replaced or removed since their features were extracted:
    their keypoints would stand for pixels that are no longer there, and the model for images that are gone."""
    before = read_json_object(ws.path / STAMPS) or {}
    for name in sorted(extracted):
        if name not in now:
            raise InputError(f"{folder / name}: in the workspace {ws.path} but no longer in the folder; rerun "
                             "with --overwrite to start over without it")
        if name in before and before[name] != now[name]:
            what = "the image or its mask" if masked else "size or time"
            raise InputError(f"{folder / name}: changed since its features were extracted ({what}); rerun "
                             "with --overwrite to start over")


def _masks(config: FrontendConfig, names, stamps: dict) -> dict:
    """name -> mask file of the images that have one in `config.masks` (io/masks.py), each mask's size and time
    added to its image's stamp; a warning names the images without one."""
    if not config.masks:
        return {}
    masks, missing = find_masks(config.masks, names)
    for name, path in masks.items():
        st = path.stat()
        stamps[name] = stamps.get(name, []) + [st.st_size, st.st_mtime_ns]
    if missing:
        log.warning("%s: no mask for %d of %d images (%s, looked for %s): their features are taken everywhere",
                    config.masks, len(missing), len(names), some_names(missing), mask_path(config.masks, missing[0]))
    return masks


def masks_folder(config: FrontendConfig) -> str:
    """The masks folder as recorded (the features stage's record, reconstruct's hash): `masks` is out of the
    config's hash, so that runs without masks keep their records."""
    return str(Path(config.masks).resolve())


def _too_few(folder: Path, usable: int, failed: dict[str, str]):
    why = f" (skipped {'; '.join(failed.values())})" if failed else ""
    raise InputError(f"{folder}: only {usable} usable image(s), need at least 2{why}")


def extract_features(config: FrontendConfig, image_dir: Path | str, workspace: Workspace | Path | str, *,
                     overwrite: bool = False, on_image: Callable[[str], None] | None = None,
                     before_changes: Callable[[], None] | None = None,
                     alongside: Callable[[], None] | None = None, cluster: Cluster | None = None) -> FeatureSummary:
    """Detect SIFT in every image of `image_dir` not yet in the workspace; `on_image(name)` after each commit.
    Refused settings or input raise InputError before anything in the workspace changes; `before_changes()` is
    called just before the first change. `alongside()` runs in a thread of this process while the workers
    extract (see startup.load_later_stages). With `cluster` the images are extracted there, one task per image
    (mvrecon/cluster.py), and written here as they come back, in the images' order, as with the local pool."""
    start = time.perf_counter()
    ws = as_workspace(workspace)
    # the pool starts first: its start overlaps the set-up in _extract_all
    with ws.lock(), (contextlib.nullcontext(cluster) if cluster is not None else WorkerPool(worker_count(config))) \
            as pool:
        summary = _extract_all(config, Path(image_dir), ws, overwrite, on_image, pool, before_changes, alongside)
    summary.seconds = time.perf_counter() - start
    return summary


@contextmanager
def _in_thread(func: Callable[[], None] | None):
    """`func()` in a thread for the duration of the block, which waits for it at its end."""
    thread = None if func is None else threading.Thread(target=func, name=getattr(func, "__name__", None))
    if thread is not None:
        thread.start()
    try:
        yield
    finally:
        if thread is not None:
            thread.join()


def _extract_all(config: FrontendConfig, folder: Path, ws: Workspace, overwrite: bool,
                 on_image: Callable[[str], None] | None, pool: WorkerPool | Cluster,
                 before_changes: Callable[[], None] | None = None,
                 alongside: Callable[[], None] | None = None) -> FeatureSummary:
    names, skipped = require_images(folder)
    config.camera.validate()
    failed = _unreadable(folder, skipped)
    stamps = image_stamps(folder, [*names, *failed])
    record = {"images": str(folder.resolve()), "camera": to_dict(config.camera), "sift": to_dict(config.sift)}
    if config.camera.model_given and config.camera.model == CameraConfig.model:
        record[GIVEN_KEY] = True  # the default named: kept by the mapper (cameras.recorded_model_left_open)
    masks = _masks(config, names, stamps)
    if config.masks:
        record["masks"] = masks_folder(config)
    # Everything that can refuse the run is checked before anything in the workspace is deleted or rewritten:
    # the stage's config, a database this workspace has no record of (Workspace.check_stage), the cameras.
    redo = bool(ws.check_stage("features", record, overwrite))
    jobs = _extraction_jobs(folder, names, config, masks, pool.workers,
                            one_thread=isinstance(pool, Cluster))
    # Without a database nothing is extracted yet: every image goes to the workers now, so that probing the
    # images and creating the database (which imports pycolmap) overlap SIFT instead of delaying it.
    results = _hand_out(pool, jobs, folder) if redo or not ws.database_path.exists() else None
    metas = _probe(folder, names, failed)
    names = [n for n in names if n in metas]
    check_masks(masks, folder, metas)
    groups = group_cameras(names, metas, config.camera)
    priors = _pose_priors(config, folder, names)
    if before_changes is not None:
        before_changes()
    if ws.begin_stage("features", record, overwrite):
        for suffix in ("", "-wal", "-shm", "-journal"):
            Path(f"{ws.database_path}{suffix}").unlink(missing_ok=True)
    group_of = {name: gi for gi, (_, members) in enumerate(groups) for name in members}
    extracted, colors = 0, {}
    with dbmod.open_database(ws.database_path) as db:
        existing = {info.name: info for info in dbmod.read_images(db).values()}
        _check_unchanged(folder, ws, [n for n, info in existing.items() if dbmod.has_features(db, info.image_id)],
                         stamps, masked=bool(masks))
        camera_ids: dict[int, int] = {}
        for name, info in existing.items():
            if name in group_of:
                camera_ids.setdefault(group_of[name], info.camera_id)
        todo = [n for n in names if n not in existing or not dbmod.has_features(db, existing[n].image_id)]
        wanted = set(todo)  # an image handed over early may have failed its probe since
        if results is None:
            jobs = _extraction_jobs(folder, [n for n in names if n in wanted], config, masks, pool.workers,
                                    one_thread=isinstance(pool, Cluster))
            results = _hand_out(pool, jobs, folder)
        # started once the workers have their jobs and this thread has done its set-up: an import holds the
        # GIL, which the pool's threads need to hand out the jobs
        with _in_thread(alongside):
            for name, result in progress(results, total=len(jobs), desc="features", unit="image"):
                if name not in wanted:
                    continue
                if isinstance(result, str):
                    log.warning("skipping %s", result)
                    failed[name] = result
                    continue
                keypoints, descriptors, colors[name] = result
                gi = group_of[name]
                with dbmod.transaction(db, ws.database_path, keypoints.nbytes + descriptors.nbytes):
                    if gi not in camera_ids:
                        camera_ids[gi] = dbmod.write_camera(db, groups[gi][0])
                    info = _store(db, name, existing.get(name), camera_ids[gi], keypoints, descriptors)
                existing[name] = info
                extracted += 1
                if on_image is not None:
                    on_image(name)
        counts = {n: dbmod.num_keypoints(db, existing[n].image_id) for n in names if n in existing}
        counts = {n: c for n, c in counts.items() if n not in failed}
        dbmod.write_pose_priors(db, {existing[n].image_id: p for n, p in priors.items() if n in counts})
        if priors:
            log.info("pose priors: %d of %d images (%s)", len(priors), len(counts), config.pose_priors or "EXIF GPS")
        num_cameras = len({existing[n].camera_id for n in counts})
    write_json(ws.path / STAMPS, stamps)
    if len(counts) < 2:
        _too_few(folder, len(counts), failed)
    return FeatureSummary(num_images=len(counts), num_extracted=extracted, keypoints=counts, failed=failed,
                          skipped=skipped, num_cameras=num_cameras, keypoint_colors=colors)


def _pose_priors(config: FrontendConfig, folder: Path, names: list[str]) -> dict:
    """name -> pose prior for the database (COLMAP's pose_priors table): the camera positions of the
    `pose_priors` CSV file when given (a bad file refused here, before any change), else those of the images'
    EXIF GPS (io/pose_priors.py). Rewritten on every run, so that they follow the file."""
    return read_priors_csv(config.pose_priors, names) if config.pose_priors else exif_priors(folder, names)


def _probe(folder: Path, names: list[str], failed: dict[str, str]) -> dict:
    """name -> image_metadata of each image whose header reads; the others added to `failed` with a warning."""
    metas = {}
    for name in names:
        try:
            metas[name] = image_metadata(folder / name)
        except InputError as exc:
            log.warning("skipping %s", exc)
            failed[name] = str(exc)
    return metas


def _store(db, name: str, info: dbmod.ImageInfo | None, camera_id: int, keypoints: np.ndarray,
           descriptors: np.ndarray) -> dbmod.ImageInfo:
    """An image's keypoints and descriptors written to `db`, its row too when it has none (`info` None); its
    row as it now is."""
    image_id = info.image_id if info is not None else dbmod.write_image(db, name, camera_id)
    dbmod.write_features(db, image_id, keypoints, descriptors)
    return dbmod.ImageInfo(image_id=image_id, name=name, camera_id=camera_id)
