"""The reconstruction pipeline as stage functions: `stage(config, inputs, workspace) -> summary`.

Each stage is callable from Python, the CLI and tests alike, records its config in the workspace, and skips the
work already in the database, committing per unit of work (one image, one batch of pairs), so an interrupted run
loses at most the unit in progress and a rerun of the same command resumes.

- `extract_features(config, image_dir, workspace)`: images -> cameras, keypoints, descriptors.
- `match(config, workspace)`: pairs -> putative matches -> verified two-view geometries.
"""

import functools
import hashlib
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import database as dbmod
from .cameras import CameraConfig, group_cameras, report_entry
from .config import bounded, config_hash, to_dict
from .errors import DiskFull, InputError
from .executor import StageClock, WorkerPool, blas_threads, default_workers
from .features.sift import SiftConfig, extraction_memory_mb
from .io.files import read_json_object, some_names, write_json
from .io.images import IMAGE_EXTENSIONS, decoding_for_detection, image_metadata, list_images, visible_files
from .io.masks import check_masks, find_masks, mask_path
from .matching.matcher import MatcherConfig, match_descriptors, prepare_descriptors
from .matching.overlay import drop_static, fixed_keypoints, same_view
from .matching.pairs import check_spec, select_pairs
from .matching.verify import VerifyConfig, verify_pair
from .progress import progress
from .sfm.config import MapperConfig
from .workspace import Workspace

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrontendConfig:
    """Everything that decides the features and matches of a run (see each part's own defaults)."""

    camera: CameraConfig = CameraConfig()
    sift: SiftConfig = SiftConfig()
    pairs: str = "exhaustive"  # exhaustive | sequential:K | retrieval:K | path of a pairs file
    matcher: MatcherConfig = MatcherConfig()
    verify: VerifyConfig = VerifyConfig()
    workers: int = bounded(0, 0, hash=False)  # processes/threads; 0 = all cores
    # folder of masks (io/masks.py); out of the hash, so that runs without masks keep their records, and
    # recorded by the features stage and reconstruct's hash when given
    masks: str = field(default="", metadata={"hash": False})


def _workers(config: FrontendConfig) -> int:
    return config.workers if config.workers > 0 else default_workers()


def _workspace(workspace) -> Workspace:
    return workspace if isinstance(workspace, Workspace) else Workspace(workspace)


def _holding_workspace(func):
    """`func(config, workspace, ...)` run with the workspace locked against other processes (Workspace.lock)."""
    @functools.wraps(func)
    def run(config, workspace, *args, **kwargs):
        with _workspace(workspace).lock():
            return func(config, workspace, *args, **kwargs)
    return run


def _stats(values) -> str:
    v = np.asarray(values, dtype=float)
    if not v.size:
        return "none"
    return f"{v.mean():.0f} on average (min {v.min():.0f}, max {v.max():.0f})"


# ---------------------------------------------------------------- features

@dataclass(kw_only=True)
class FeatureSummary:
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
                 f"{self.num_cameras} camera(s); keypoints per image: {_stats(list(self.keypoints.values()))}."]
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
    from .features.sift import extract_sift
    from .io.images import colors_at, read_image_for_detection

    path, name, sift_config, mask, threads = job
    try:
        if threads is not None:
            import cv2

            if cv2.getNumThreads() != threads:
                cv2.setNumThreads(threads)
        # a large JPEG decoded at 1/2-1/8 of its size (bounded memory); its colours are sampled there too
        image, reduced = read_image_for_detection(path, sift_config.max_image_size)
        keypoints, descriptors = extract_sift(image, sift_config, reduced)
        if mask is not None:
            from .io.masks import keypoints_outside_mask

            full_shape = (image.shape[0] * reduced, image.shape[1] * reduced)
            keep = keypoints_outside_mask(mask, path, keypoints, full_shape)
            keypoints, descriptors = keypoints[keep], descriptors[keep]
        return name, (keypoints, descriptors, colors_at(image, keypoints[:, :2] / reduced))
    except InputError as exc:
        return name, str(exc)
    except Exception as exc:  # OpenCV or memory errors on one image must not stop the run
        return name, f"{path}: {type(exc).__name__}: {exc}"


def _hand_out(pool: WorkerPool, jobs: list[tuple]):
    """`_extract_job`'s results for `jobs`, computed by `pool`: as many images at a time as the memory
    available holds (`_extraction_memory_mb`), and an image whose worker died twice skipped with the
    reason."""
    return pool.map(_extract_job, jobs, name=lambda job: str(job[0]), cost=_extraction_memory_mb,
                    died=lambda job, why: (job[1], f"{job[0]}: the worker extracting it died twice: {why}"))


def _extraction_memory_mb(job) -> float:
    """The memory a worker needs for `_extract_job(job)` (MB), from the image's header."""
    path, _, sift_config, _, _ = job
    width, height, reduced, _ = decoding_for_detection(path, sift_config.max_image_size)
    return extraction_memory_mb(width, height, sift_config, reduced)


def _extraction_jobs(folder: Path, names, config: FrontendConfig, masks: dict, workers: int) -> list[tuple]:
    """`_extract_job`'s jobs. In a pool, each image runs on one OpenCV thread (a worker per core), except the
    last `workers` images, which run on `workers` threads each: when a worker takes one of them no image is left
    for the others, whose cores would stand idle until it ends (templeSparseRing: 20-65 ms of a core). OpenCV's
    SIFT gives the same keypoints and descriptors on any number of threads (it sorts them). In-process
    (`workers <= 1`) the threads are left as they are."""
    tail = len(names) - workers
    return [(folder / n, n, config.sift, masks.get(n), None if workers <= 1 else workers if k >= tail else 1)
            for k, n in enumerate(names)]


def require_images(folder) -> tuple[list[str], dict[str, str]]:
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


def _stamps(folder: Path, names) -> dict[str, list[int]]:
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


def _masks_folder(config: FrontendConfig) -> str:
    """The masks folder as recorded (the features stage's record, reconstruct's hash): `masks` is out of the
    config's hash, so that runs without masks keep their records."""
    return str(Path(config.masks).resolve())


def _too_few(folder: Path, usable: int, failed: dict[str, str]):
    why = f" (skipped {'; '.join(failed.values())})" if failed else ""
    raise InputError(f"{folder}: only {usable} usable image(s), need at least 2{why}")


def extract_features(config: FrontendConfig, image_dir, workspace, *, overwrite: bool = False,
                     on_image: Callable[[str], None] | None = None,
                     before_changes: Callable[[], None] | None = None,
                     alongside: Callable[[], None] | None = None) -> FeatureSummary:
    """Detect SIFT in every image of `image_dir` not yet in the workspace; `on_image(name)` after each commit.
    Refused settings or input raise InputError before anything in the workspace changes; `before_changes()` is
    called just before the first change. `alongside()` runs in a thread of this process while the workers
    extract (see load_later_stages)."""
    start = time.perf_counter()
    ws = _workspace(workspace)
    # the pool starts first: its start overlaps the set-up in _extract_all
    with ws.lock(), WorkerPool(_workers(config)) as pool:
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


def load_later_stages() -> None:
    """Import what matching and mapping need, and make the matcher's onnxruntime session, while the feature
    workers run. Between the stages, on one core, this took 0.15-0.2 s of a 2.1 s templeSparseRing run; beside
    the workers, on a core they share, it costs them half of that (docs/frontend.md). A library that fails to
    load here fails again where it is needed, with its error reported there."""
    import importlib

    try:
        # numpy.ma: the initial pair's np.median imports it (8 ms of the mapping, on its one core)
        for name in ("cv2", "gtsam", "numpy.ma", "mvrecon.io.colmap_model", "mvrecon.sfm.incremental"):
            importlib.import_module(name)
        from .matching.int_product import int_product

        int_product(np.zeros((1, 128), np.uint8), np.zeros((128, 1), np.int8))  # makes its session
    except Exception:  # noqa: BLE001
        pass


def _extract_all(config: FrontendConfig, folder: Path, ws: Workspace, overwrite: bool,
                 on_image: Callable[[str], None] | None, pool: WorkerPool,
                 before_changes: Callable[[], None] | None = None,
                 alongside: Callable[[], None] | None = None) -> FeatureSummary:
    names, skipped = require_images(folder)
    config.camera.validate()
    failed = _unreadable(folder, skipped)
    stamps = _stamps(folder, [*names, *failed])
    record = {"images": str(folder.resolve()), "camera": to_dict(config.camera), "sift": to_dict(config.sift)}
    masks = _masks(config, names, stamps)
    if config.masks:
        record["masks"] = _masks_folder(config)
    # Everything that can refuse the run is checked before anything in the workspace is deleted or rewritten:
    # the stage's config, a database this workspace has no record of (Workspace.check_stage), the cameras.
    redo = bool(ws.check_stage("features", record, overwrite))
    jobs = _extraction_jobs(folder, names, config, masks, pool.workers)
    # Without a database nothing is extracted yet: every image goes to the workers now, so that probing the
    # images and creating the database (which imports pycolmap) overlap SIFT instead of delaying it.
    results = _hand_out(pool, jobs) if redo or not ws.database_path.exists() else None
    metas = {}
    for name in names:
        try:
            metas[name] = image_metadata(folder / name)
        except InputError as exc:
            log.warning("skipping %s", exc)
            failed[name] = str(exc)
    names = [n for n in names if n in metas]
    check_masks(masks, folder, metas)
    groups = group_cameras(names, metas, config.camera)
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
            jobs = _extraction_jobs(folder, [n for n in names if n in wanted], config, masks, pool.workers)
            results = _hand_out(pool, jobs)
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
                    image_id = existing[name].image_id if name in existing else \
                        dbmod.write_image(db, name, camera_ids[gi])
                    dbmod.write_features(db, image_id, keypoints, descriptors)
                existing[name] = dbmod.ImageInfo(image_id=image_id, name=name, camera_id=camera_ids[gi])
                extracted += 1
                if on_image is not None:
                    on_image(name)
        counts = {n: dbmod.num_keypoints(db, existing[n].image_id) for n in names if n in existing}
        counts = {n: c for n, c in counts.items() if n not in failed}
        num_cameras = len({existing[n].camera_id for n in counts})
    write_json(ws.path / STAMPS, stamps)
    if len(counts) < 2:
        _too_few(folder, len(counts), failed)
    return FeatureSummary(num_images=len(counts), num_extracted=extracted, keypoints=counts, failed=failed,
                          skipped=skipped, num_cameras=num_cameras, keypoint_colors=colors)


# ---------------------------------------------------------------- matching

@dataclass(kw_only=True)
class MatchSummary:
    num_images: int
    num_pairs: int  # pairs selected
    num_matched: int  # of which matched in this run (the rest were already there)
    inliers: dict[tuple[str, str], int]  # verified pairs -> inlier count
    configs: dict[str, int]  # configuration name -> number of pairs
    seconds: float = 0.0
    fixed_dropped: int = 0  # matches left out in this run as features printed on the images (matching/overlay.py)

    @property
    def num_verified(self) -> int:
        return len(self.inliers)

    def text(self) -> str:
        kinds = ", ".join(f"{n} {k.lower()}" for k, n in sorted(self.configs.items(), key=lambda kv: -kv[1]))
        return (f"Matching: {self.num_images} images, {self.num_pairs} pairs ({self.num_matched} matched now, "
                f"{self.num_pairs - self.num_matched} already done) in {self.seconds:.1f} s; "
                f"{self.num_verified} verified pairs ({kinds or 'none'}); "
                f"inliers per verified pair: {_stats(list(self.inliers.values()))}."
                + (f" {self.fixed_dropped} matches that stay on a pixel where half the images have a feature were "
                   "left out (a logo or timestamp printed on the images, or a camera that did not move)."
                   if self.fixed_dropped else ""))


def _match_one(task):
    (kp1, d1, cam1, fixed1), (kp2, d2, cam2, fixed2), config = task
    putative = match_descriptors(d1, d2, config.matcher)
    matches = drop_static(putative, kp1, kp2, fixed1, fixed2)
    return matches, verify_pair(kp1, kp2, matches, cam1, cam2, config.verify), len(putative) - len(matches)


# more images than this matched exhaustively get the advice of a pair selection that grows linearly (COLMAP's
# guide gives exhaustive matching "up to several hundreds" of images; 200 are 19,900 pairs)
_MANY_FOR_EXHAUSTIVE = 200


@_holding_workspace
def match(config: FrontendConfig, workspace, *, overwrite: bool = False,
          on_batch: Callable[[int], None] | None = None, batch_size: int = 16,
          max_cached_images: int = 256) -> MatchSummary:
    """Match and verify every selected pair not yet in the workspace; `on_batch(pairs_done)` after each commit.

    Descriptors are read once per image and kept (at most `max_cached_images`, least recently used dropped;
    re-reading one costs far less than the matrix product of a pair)."""
    start = time.perf_counter()
    ws = _workspace(workspace)
    check_spec(config.pairs)
    ws.require_stage("features", "run `mvrecon features IMAGES -o WORKSPACE` first")
    record = {"pairs": config.pairs, "matcher": to_dict(config.matcher), "verify": to_dict(config.verify)}
    with dbmod.open_database(ws.database_path) as db:
        images = {i.image_id: i for i in dbmod.read_images(db).values() if dbmod.has_features(db, i.image_id)}
        cameras = dbmod.read_cameras(db)
        by_name = {i.name: i.image_id for i in images.values()}
        pairs = []
        # the pairs first: a pairs file naming an unknown image is refused before the stage is recorded
        for a, b in select_pairs(config.pairs, sorted(by_name),
                                 descriptors=lambda name: dbmod.read_descriptors(db, by_name[name])):
            id1, id2 = sorted((by_name[a], by_name[b]))
            pairs.append((id1, id2))
        if config.pairs != "exhaustive" and Path(config.pairs).is_file():
            # a pairs file is recorded by what it selects, not only its name: an edited or another file of the
            # same name is a different config
            listed = "\n".join(sorted(" ".join(sorted((images[i].name, images[j].name))) for i, j in pairs))
            record["pairs_file_sha256"] = hashlib.sha256(listed.encode()).hexdigest()
        if ws.begin_stage("matching", record, overwrite):
            dbmod.clear_matches(db)
        todo = [p for p in pairs if not dbmod.has_two_view_geometry(db, *p)]
        if config.pairs == "exhaustive" and len(images) > _MANY_FOR_EXHAUSTIVE and len(todo) > len(pairs) // 2:
            log.warning("exhaustive matching of %d images: %d pairs, growing with the square of the images; "
                        "--pairs retrieval:20 matches each image with its 20 most similar ones (a photo "
                        "collection), --pairs sequential:10 with the next 10 (a video)", len(images), len(pairs))
        remaining = {}  # image -> number of todo pairs still needing it, to free its descriptors early
        for p in todo:
            for i in p:
                remaining[i] = remaining.get(i, 0) + 1
        # Every image's keypoint positions are read once, as float32 (COLMAP stores them so: exact, and 64 KB for
        # 8192 keypoints): features printed on the images (a logo, a timestamp) are found among all of them, not
        # only those of the pairs left, so that a resumed run decides as an uninterrupted one.
        every = sorted(images) if todo else []
        positions = {i: dbmod.read_keypoints(db, i)[:, :2].astype(np.float32) for i in every}
        fixed = fixed_keypoints(positions, {i: (cameras[images[i].camera_id].width,
                                                cameras[images[i].camera_id].height) for i in every})
        dropped = 0
        cache = OrderedDict()  # image -> (keypoints, prepared descriptors, camera, fixed), least recently used first

        def features(image_id):
            if image_id in cache:
                cache.move_to_end(image_id)
            else:
                cache[image_id] = (positions[image_id].astype(np.float64),
                                   prepare_descriptors(dbmod.read_descriptors(db, image_id)),
                                   cameras[images[image_id].camera_id], fixed[image_id])
                while len(cache) > max_cached_images:  # bounded memory: ~2 MB per 8192-feature image
                    cache.popitem(last=False)
            return cache[image_id]

        bar = progress(total=len(todo), desc="matching", unit="pair")
        workers = _workers(config)
        in_flight, upcoming, done = deque(), iter(todo), 0

        def submit(pool) -> None:
            pair = next(upcoming, None)
            if pair is not None:
                in_flight.append((pair, pool.submit(_match_one, (features(pair[0]), features(pair[1]), config))))

        with ThreadPoolExecutor(max_workers=workers) as pool, blas_threads(1):
            # A sliding window of pairs in flight, not one batch at a time: the workers keep going while this
            # thread writes a batch (waiting for each batch's slowest pair left ~8% of opensfm_lund's cores idle).
            try:
                for _ in range(batch_size + 2 * workers):
                    submit(pool)
                while in_flight:
                    batch = []
                    while in_flight and len(batch) < batch_size:
                        pair, future = in_flight.popleft()
                        batch.append((pair, future.result()))
                        submit(pool)
                    size = sum(found[0].nbytes + found[1].inliers.nbytes for _, found in batch)
                    with dbmod.transaction(db, ws.database_path, size):
                        for (i, j), (matches, geometry, left_out) in batch:
                            dropped += left_out
                            dbmod.write_matches(db, i, j, matches)
                            dbmod.write_two_view_geometry(db, dbmod.PairGeometry(
                                image_id1=i, image_id2=j, config=geometry.config, inliers=geometry.inliers,
                                F=geometry.F, E=geometry.E, H=geometry.H))
                    for (i, j), _ in batch:
                        for k in (i, j):
                            remaining[k] -= 1
                            if remaining[k] == 0:
                                cache.pop(k, None)
                    done += len(batch)
                    bar.update(len(batch))
                    if on_batch is not None:
                        on_batch(done)
            except BaseException:
                for _, future in in_flight:  # an interrupt waits only for the pairs already running
                    future.cancel()
                raise
        bar.close()
        selected = set(pairs)
        verified, configs = {}, {}
        for id1, id2, kind, n in dbmod.read_verified_pairs(db):
            if (id1, id2) in selected:
                verified[(images[id1].name, images[id2].name)] = n
                configs[kind] = configs.get(kind, 0) + 1
    return MatchSummary(num_images=len(images), num_pairs=len(pairs), num_matched=len(todo), inliers=verified,
                        configs=configs, seconds=time.perf_counter() - start, fixed_dropped=dropped)


# ---------------------------------------------------------------- mapping (the SfM engine)


@dataclass(frozen=True)
class ReconstructConfig:
    """Front end and mapper settings of one `reconstruct` run."""

    frontend: FrontendConfig = FrontendConfig()
    mapper: MapperConfig = MapperConfig()


@dataclass(kw_only=True)
class MapSummary:
    models: list  # sfm.model.Reconstruction, largest first
    status: dict  # image name -> {"status", "model", "reason"}
    model_stats: list  # per model: registered, points, mean_track_length, mean_reprojection_error_px, cameras
    seconds: float = 0.0

    def text(self) -> str:
        n = sum(1 for s in self.status.values() if s["status"] == "registered")
        parts = [f"Mapping: {n} of {len(self.status)} images registered in {len(self.models)} model(s) "
                 f"in {self.seconds:.1f} s."]
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


@_holding_workspace
def map_workspace(config, workspace, *, image_dir=None, text: bool = False, resume: bool = False,
                  overwrite: bool = False, keypoint_colors=None) -> MapSummary:
    """Run the incremental mapper on the workspace's database and write `sparse/N/` and `points.ply`.

    `config` is a MapperConfig. With `resume`, mapping continues from the last snapshot in the workspace
    (`snapshots/mapper.pkl`); without it mapping starts over. The points are coloured from `keypoint_colors`
    (FeatureSummary's) when it covers a model's images, otherwise from the images in `image_dir`.
    """
    import shutil

    from .io.colmap_model import warn_text_names, write_models, write_points_ply
    from .sfm.incremental import map_correspondences

    start = time.perf_counter()
    ws = _workspace(workspace)
    if not ws.database_path.is_file():
        raise InputError(f"{ws.path}: no database.db here; run `mvrecon reconstruct IMAGES -o {ws.path}` "
                         "first")
    record, sparse, snapshot = to_dict(config), ws.path / "sparse", ws.snapshot_path
    ws.check_stage("mapping", record, overwrite, hint=f"rerun with --overwrite to map again (`mvrecon map -o "
                   f"{ws.path} --overwrite` redoes only the mapping), or use another workspace")
    try:
        stages = ws.stages()
    except InputError:  # an unreadable config.json, which check_stage lets --overwrite map past
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
    result = map_correspondences(corr, config, snapshot_path=snapshot, resume=resume)
    # the new models go to sparse.new/ and replace sparse/ only once made: a failed re-map keeps the old model
    new = ws.path / "sparse.new"
    shutil.rmtree(new, ignore_errors=True)
    recs = write_models(result.models, new, image_dir=image_dir, text=text, keypoint_colors=keypoint_colors)
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
    stats = []
    for m in result.models:
        s = m.stats()
        stats.append({**{k: s[k] for k in ("registered", "points", "mean_track_length",
                                           "mean_reprojection_error_px")}, "cameras": camera_entries(m)})
    return MapSummary(models=result.models, status=result.status, model_stats=stats,
                      seconds=time.perf_counter() - start)


def camera_entries(model) -> list[dict]:
    """The cameras of a model's registered images with their final parameters (COLMAP's order), as report.json
    lists them: the refined intrinsics were only in sparse/N/cameras.bin."""
    cams = [(cid, model.cameras[int(cid)]) for cid in np.unique(model.camera_of[model.registered])]
    return [report_entry(cid, cam.model, cam.width, cam.height, cam.params) for cid, cam in cams]


class NoVerifiedPairs(InputError):
    """The database gives the mapper no verified pair; `reason` is why, without the path the error names (the
    database, or the images of a `reconstruct` that removed the folder it made, database included)."""

    def __init__(self, path, reason: str):
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


def write_report(out_dir, *, config_hash: str, seed: int, summary: MapSummary, stages: dict, total: dict,
                 counts: dict, skipped: dict | None = None, database: dict | None = None) -> dict:
    """OUT/report.json in the schema the compare and study tools read (see docs/sfm.md). `database`: where
    database.db came from ({"made_by": "mvrecon"} or another tool's)."""
    from . import __version__

    images = {name: dict(s) for name, s in summary.status.items()}
    for name, reason in (skipped or {}).items():
        images[name] = {"status": "skipped", "model": None, "reason": reason}
    report = {"engine": "mvrecon", "version": __version__, "config_hash": config_hash, "seed": seed,
              "images": dict(sorted(images.items())),
              "models": [{"index": k, **s} for k, s in enumerate(summary.model_stats)],
              "stages": stages, "total": total, "counts": counts,
              "database": database or {"made_by": "mvrecon"}}
    write_json(Path(out_dir) / "report.json", report, indent=1)
    return report


def _finished_report(out: Path, full_hash: str, image_dir: Path) -> dict | None:
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
    if stamps is not None and stamps != _stamps(image_dir, names):
        return None
    database = out / "database.db"  # one deleted since (to save space, say) leaves the model as it was
    damage = dbmod.database_damage(database) if database.is_file() else None
    if damage is not None:
        raise InputError(f"{database}: damaged since its run finished ({damage}); rerun with --overwrite to "
                         "start over")
    return report


def reconstruct(config: ReconstructConfig, image_dir, out_dir, *, text: bool = False, resume: bool = False,
                overwrite: bool = False) -> dict:
    """Images -> features -> matches -> models: OUT/database.db, sparse/N/, points.ply, report.json.

    A finished run with the same config is not redone (its report is returned); an interrupted one resumes:
    features and matches already in the database are kept, and mapping continues from its snapshot when
    `resume` is set. Returns the report dict.
    """
    out = Path(out_dir)
    mapper = config.mapper
    full = {"frontend": to_dict(config.frontend), "mapper": to_dict(mapper)}
    if config.frontend.masks:
        full["masks"] = _masks_folder(config.frontend)
    full_hash = config_hash(full)
    report_path = out / "report.json"
    finished = None if overwrite else _finished_report(out, full_hash, Path(image_dir))
    if finished is not None:
        log.info("%s: finished run with the same config and images found; not redone", out)
        if text:
            from .io.colmap_model import write_text_models

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
                                        before_changes=before_changes, alongside=load_later_stages)
            log.info("%s", features.text())
            clock.done("features")
            matches = match(config.frontend, ws, overwrite=overwrite)
            log.info("%s", matches.text())
            clock.done("matching")
            summary = map_workspace(mapper, ws, image_dir=image_dir, text=text, resume=resume,
                                    overwrite=overwrite, keypoint_colors=features.keypoint_colors)
        except DiskFull:  # the features and matches written so far are kept for the rerun
            raise
        except InputError as exc:  # rejected input (no verified pairs, say), or refused settings
            if fresh:  # a folder this call made holds nothing worth keeping
                import shutil

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
                            total=clock.total(), counts=dbmod.database_counts(ws.database_path), skipped=skipped)

