"""The matching stage: the selected pairs of images -> putative matches -> verified two-view geometries.

`match(config, workspace)` matches and verifies every selected pair not yet in the database, committing one
batch of pairs at a time, so an interrupted run loses at most the batch in progress. The pairs run on a thread
pool (`_match_all`), or on a Dask cluster in batches of pairs (`_match_on_cluster`, `--cluster`).
"""

import hashlib
import logging
import time
import uuid
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import database as dbmod
from ..cluster import Cluster
from ..config import to_dict
from ..executor import blas_threads
from ..io.gps import read_gps
from ..matching.matcher import match_descriptors, prepare_descriptors
from ..matching.overlay import drop_static, fixed_keypoints
from ..matching.pairs import PairPlan, check_spec, plan_pairs
from ..matching.verify import verify_pair
from ..progress import progress
from ..workspace import Workspace
from .common import FrontendConfig, as_workspace, holding_workspace, stats_text, worker_count

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class MatchSummary:
    """What the matching stage did: the pairs selected and matched, the verified ones and their kinds."""

    num_images: int
    num_pairs: int  # pairs selected
    num_matched: int  # of which matched in this run (the rest were already there)
    inliers: dict[tuple[str, str], int]  # verified pairs -> inlier count
    configs: dict[str, int]  # configuration name -> number of pairs
    seconds: float = 0.0
    fixed_dropped: int = 0  # matches left out in this run as features printed on the images (matching/overlay.py)
    strategy: str = ""  # the pair selection used (`auto` resolved), and why it was chosen
    strategy_reason: str = ""

    def pairs_record(self) -> dict:
        """What report.json says of the pair selection."""
        return {"strategy": self.strategy, "reason": self.strategy_reason, "pairs": self.num_pairs}

    @property
    def num_verified(self) -> int:
        return len(self.inliers)

    def text(self) -> str:
        kinds = ", ".join(f"{n} {k.lower()}" for k, n in sorted(self.configs.items(), key=lambda kv: -kv[1]))
        why = f" ({self.strategy_reason})" if self.strategy_reason != "given" else ""
        return (f"Matching: {self.num_images} images, {self.num_pairs} pairs ({self.num_matched} matched now, "
                f"{self.num_pairs - self.num_matched} already done) in {self.seconds:.1f} s, selected by "
                f"{self.strategy or 'a pairs file'}{why}; "
                f"{self.num_verified} verified pairs ({kinds or 'none'}); "
                f"inliers per verified pair: {stats_text(list(self.inliers.values()))}."
                + (f" {self.fixed_dropped} matches that stay on a pixel where half the images have a feature were "
                   "left out (a logo or timestamp printed on the images, or a camera that did not move)."
                   if self.fixed_dropped else ""))


def _match_one(task):
    """Worker: ((keypoints, prepared descriptors, camera, fixed) of both images, config) -> (matches, verified
    geometry, number of matches left out as features printed on the images)."""
    (kp1, d1, cam1, fixed1), (kp2, d2, cam2, fixed2), config = task
    putative = match_descriptors(d1, d2, config.matcher)
    matches = drop_static(putative, kp1, kp2, fixed1, fixed2)
    return matches, verify_pair(kp1, kp2, matches, cam1, cam2, config.verify), len(putative) - len(matches)


def _image_features(keypoints: np.ndarray, descriptors: np.ndarray, camera, fixed: np.ndarray) -> tuple:
    """Worker of a cluster: an image as `_match_one` takes it. The client sends the descriptors as stored (128
    bytes a feature) and the worker prepares them, once for all the pairs of the image it runs."""
    return keypoints.astype(np.float64), prepare_descriptors(descriptors), camera, fixed


def _match_batch(task) -> list[tuple]:
    """Worker of a cluster: (pairs, image id -> `_image_features`, config) -> [(pair, `_match_one`'s result)]."""
    pairs, features, config = task
    return [(pair, _match_one((features[pair[0]], features[pair[1]], config))) for pair in pairs]


# more images than this matched exhaustively get the advice of a pair selection that grows linearly (COLMAP's
# guide gives exhaustive matching "up to several hundreds" of images; 200 are 19,900 pairs)
_MANY_FOR_EXHAUSTIVE = 200


@holding_workspace
def match(config: FrontendConfig, workspace: Workspace | Path | str, *, overwrite: bool = False,
          on_batch: Callable[[int], None] | None = None, batch_size: int = 16,
          max_cached_images: int = 256, cluster: Cluster | None = None) -> MatchSummary:
    """Match and verify every selected pair not yet in the workspace; `on_batch(pairs_done)` after each commit.

    Descriptors are read once per image and kept (at most `max_cached_images`, least recently used dropped;
    re-reading one costs far less than the matrix product of a pair). With `cluster` the pairs are matched
    there, `batch_size` pairs a task (`_match_on_cluster`)."""
    start = time.perf_counter()
    ws = as_workspace(workspace)
    check_spec(config.pairs)
    ws.require_stage("features", "run `mvrecon features IMAGES -o WORKSPACE` first")
    record = {"pairs": config.pairs, "matcher": to_dict(config.matcher), "verify": to_dict(config.verify)}
    with dbmod.open_database(ws.database_path) as db:
        images = {i.image_id: i for i in dbmod.read_images(db).values() if dbmod.has_features(db, i.image_id)}
        cameras = dbmod.read_cameras(db)
        # the pairs first: a pairs file naming an unknown image is refused before the stage is recorded
        plan = _plan(config.pairs, db, images, ws.stage_config("features") or {})
        pairs = plan.pairs
        if config.pairs != "exhaustive" and Path(config.pairs).is_file():
            record["pairs_file_sha256"] = _pairs_file_sha256(images, pairs)
        else:  # `auto` as what it chose: a workspace matched exhaustively goes on under `auto`, and back
            record["pairs"] = plan.spec
        if ws.begin_stage("matching", record, overwrite):
            dbmod.clear_matches(db)
        todo = [p for p in pairs if not dbmod.has_two_view_geometry(db, *p)]
        if config.pairs == "exhaustive" and len(images) > _MANY_FOR_EXHAUSTIVE and len(todo) > len(pairs) // 2:
            log.warning("exhaustive matching of %d images: %d pairs, growing with the square of the images; "
                        "--pairs auto chooses pairs that grow linearly (retrieval, GPS positions or a video's "
                        "sequence)", len(images), len(pairs))
        # Every image's keypoint positions are read once, as float32 (COLMAP stores them so: exact, and 64 KB for
        # 8192 keypoints): features printed on the images (a logo, a timestamp) are found among all of them, not
        # only those of the pairs left, so that a resumed run decides as an uninterrupted one.
        every = sorted(images) if todo else []
        positions = {i: dbmod.read_keypoints(db, i)[:, :2].astype(np.float32) for i in every}
        fixed = fixed_keypoints(positions, {i: (cameras[images[i].camera_id].width,
                                                cameras[images[i].camera_id].height) for i in every})
        cache = _PairFeatures(db, todo, positions, fixed, {i: cameras[images[i].camera_id] for i in every},
                              max_cached_images)
        if cluster is not None:
            dropped = _match_on_cluster(config, ws.database_path, todo, cache, cluster, batch_size, on_batch)
        else:
            dropped = _match_all(config, ws.database_path, db, todo, cache, batch_size, on_batch)
        verified, configs = _verified_pairs(db, images, pairs)
    return MatchSummary(num_images=len(images), num_pairs=len(pairs), num_matched=len(todo), inliers=verified,
                        configs=configs, seconds=time.perf_counter() - start, fixed_dropped=dropped,
                        strategy=plan.spec if not Path(plan.spec).is_file() else "", strategy_reason=plan.reason)


def _plan(spec: str, db, images: dict, features_record: dict) -> PairPlan:
    """The pair selection `spec` among `images`, pairs as image ids (smaller id first). GPS positions are read
    from the image files (the features stage's folder) only when the selection asks for them."""
    by_name = {i.name: i.image_id for i in images.values()}
    folder = Path(features_record["images"]) if features_record.get("images") else None

    def descriptors(name):
        return dbmod.read_descriptors(db, by_name[name])

    def positions(name):
        return read_gps(folder / name) if folder is not None else None

    plan = plan_pairs(spec, sorted(by_name), descriptors=descriptors, positions=positions)
    return PairPlan(plan.spec, plan.reason, [tuple(sorted((by_name[a], by_name[b]))) for a, b in plan.pairs])


def _pairs_file_sha256(images: dict, pairs: list[tuple[int, int]]) -> str:
    """A pairs file as recorded: by what it selects, not only its name, so that an edited or another file of
    the same name is a different config."""
    listed = "\n".join(sorted(" ".join(sorted((images[i].name, images[j].name))) for i, j in pairs))
    return hashlib.sha256(listed.encode()).hexdigest()


class _PairFeatures:
    """What `_match_one` needs of each image, read from the database once and kept while pairs still need
    it: bounded memory (~2 MB per 8192-feature image, at most `max_cached` images, least recently used
    dropped)."""

    def __init__(self, db, todo: list[tuple[int, int]], positions: dict, fixed: dict, cameras: dict,
                 max_cached: int):
        self.db, self.positions, self.fixed, self.cameras = db, positions, fixed, cameras
        self.max_cached = max_cached
        # image -> (keypoints, prepared descriptors, camera, fixed), least recently used first
        self.cache = OrderedDict()
        self.remaining = {}  # image -> number of pairs still needing it, to free its descriptors early
        for p in todo:
            for i in p:
                self.remaining[i] = self.remaining.get(i, 0) + 1

    def get(self, image_id: int) -> tuple:
        """(keypoints as float64, prepared descriptors, camera, fixed-feature mask) of an image."""
        cache = self.cache
        if image_id in cache:
            cache.move_to_end(image_id)
        else:
            cache[image_id] = (self.positions[image_id].astype(np.float64),
                               prepare_descriptors(dbmod.read_descriptors(self.db, image_id)),
                               self.cameras[image_id], self.fixed[image_id])
            while len(cache) > self.max_cached:
                cache.popitem(last=False)
        return cache[image_id]

    def done(self, pair: tuple[int, int]) -> None:
        """`pair` is matched: an image no pair needs any more is dropped."""
        for k in pair:
            self.remaining[k] -= 1
            if self.remaining[k] == 0:
                self.cache.pop(k, None)


def _match_all(config: FrontendConfig, path, db, todo: list[tuple[int, int]], cache: _PairFeatures,
               batch_size: int, on_batch: Callable[[int], None] | None) -> int:
    """Match and verify the pairs `todo` on a pool of threads, writing them to the database `db` (at `path`) a
    batch at a time; the number of matches left out as features printed on the images. The pool is where
    another backend (a cluster) would take the pairs."""
    bar = progress(total=len(todo), desc="matching", unit="pair")
    workers = worker_count(config)
    in_flight, upcoming, done, dropped = deque(), iter(todo), 0, 0

    def submit(pool) -> None:
        pair = next(upcoming, None)
        if pair is not None:
            task = (cache.get(pair[0]), cache.get(pair[1]), config)
            in_flight.append((pair, pool.submit(_match_one, task)))

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
                dropped += _write_batch(db, path, batch)
                for pair, _ in batch:
                    cache.done(pair)
                done += len(batch)
                bar.update(len(batch))
                if on_batch is not None:
                    on_batch(done)
        except BaseException:
            for _, future in in_flight:  # an interrupt waits only for the pairs already running
                future.cancel()
            raise
    bar.close()
    return dropped


def _match_on_cluster(config: FrontendConfig, path, todo: list[tuple[int, int]], cache: _PairFeatures,
                      cluster: Cluster, batch_size: int, on_batch: Callable[[int], None] | None) -> int:
    """`_match_all` on a Dask cluster: tasks of up to `batch_size` consecutive pairs (neighbours share images), a
    few per worker in flight, each batch written to the database as it comes back, and each pair once (a task that
    Dask ran again after its worker died may come back twice). An image's keypoints and descriptors go to the
    cluster once, as a task of their own (`Cluster.keep`): its pairs' tasks use them from the worker that holds
    them, or a copy fetched once per worker, and they are released when the image's last pair is written."""
    bar = progress(total=len(todo), desc="matching", unit="pair")
    remaining = Counter(i for pair in todo for i in pair)
    held = {}  # image id -> future of `_image_features`
    run = uuid.uuid4().hex[:8]  # keys of this run's data, apart from another client's on the same scheduler

    def image(i: int):
        if i not in held:
            held[i] = cluster.keep(_image_features, cache.positions[i], dbmod.read_descriptors(cache.db, i),
                                   cache.cameras[i], cache.fixed[i], key=f"mvrecon-image-{run}-{i}")
        return held[i]

    # at least 4 tasks per worker thread, so that the last ones do not leave workers idle
    size = max(1, min(batch_size, len(todo) // (4 * cluster.workers)))

    def tasks():
        for k in range(0, len(todo), size):
            pairs = todo[k:k + size]
            yield pairs, {i: image(i) for pair in pairs for i in pair}, config

    written, dropped = set(), 0
    try:
        for (pairs, _, _), results in cluster.unordered(_match_batch, tasks()):
            batch = [(pair, found) for pair, found in results if pair not in written]
            dropped += _write_batch(cache.db, path, batch)
            written.update(pair for pair, _ in batch)
            for pair, _ in batch:
                for i in pair:
                    remaining[i] -= 1
                    if remaining[i] == 0:
                        cluster.release([held.pop(i)])
            bar.update(len(batch))
            if on_batch is not None:
                on_batch(len(written))
    finally:
        cluster.release(held.values())
    bar.close()
    return dropped


def _write_batch(db, path, batch: list) -> int:
    """The matches and geometries of a batch of `_match_one` results in one transaction; the number of matches
    left out as features printed on the images."""
    dropped = 0
    size = sum(found[0].nbytes + found[1].inliers.nbytes for _, found in batch)
    with dbmod.transaction(db, path, size):
        for (i, j), (matches, geometry, left_out) in batch:
            dropped += left_out
            dbmod.write_matches(db, i, j, matches)
            dbmod.write_two_view_geometry(db, dbmod.PairGeometry(
                image_id1=i, image_id2=j, config=geometry.config, inliers=geometry.inliers,
                F=geometry.F, E=geometry.E, H=geometry.H))
    return dropped


def _verified_pairs(db, images: dict, pairs: list[tuple[int, int]]) -> tuple[dict, dict]:
    """The verified pairs among `pairs`: (name, name) -> inlier count; configuration name -> pair count."""
    selected = set(pairs)
    verified, configs = {}, {}
    for id1, id2, kind, n in dbmod.read_verified_pairs(db):
        if (id1, id2) in selected:
            verified[(images[id1].name, images[id2].name)] = n
            configs[kind] = configs.get(kind, 0) + 1
    return verified, configs
