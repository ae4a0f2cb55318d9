"""Partitioned mapping (`--partition-size P`): the view graph split into overlapping parts (sfm/partition.py),
each part mapped as its own task through the process pool (sfm/parts.py's `map_part`), then merged into one
frame and refined as one model (sfm/merge.py).

Each finished part is kept in the workspace (`snapshots/parts/part-K.pkl`, recorded in
`snapshots/parts/.stages/record.json` under a key of the settings, the part's images and the database's content),
so that `--resume` after Ctrl-C maps only the parts not yet finished; without it every part is mapped again.
"""

import contextlib
import logging
import pickle
from typing import TYPE_CHECKING

import numpy as np

from ..cluster import Cluster
from ..config import config_hash
from ..database import Correspondences
from ..executor import WorkerPool, default_workers
from ..io.files import replace_whole
from ..io.record import Record, digest
from ..progress import progress
from ..sfm.config import MapperConfig
from ..workspace import Workspace

if TYPE_CHECKING:  # GTSAM: loaded only once the pool's workers have forked
    from ..sfm.incremental import MappingResult
    from ..sfm.parts import PartResult

log = logging.getLogger(__name__)


def map_in_parts(corr: Correspondences, config: MapperConfig, ws: Workspace, resume: bool,
                 workers: int | None = None, cluster: Cluster | None = None) -> "MappingResult":
    """The mapping of `corr` (read from `ws`'s database) in parts of at most `config.partition_size` images, as
    `MappingResult` (sfm/incremental.py); the parts run in `workers` processes (default: one per core), or as
    tasks of `cluster` (mvrecon/cluster.py), whose workers read the parts' images and pairs from the workspace's
    database: they must see the workspace at the same path."""
    workers = default_workers() if workers is None else workers
    runner = contextlib.nullcontext(cluster) if cluster is not None else WorkerPool(workers)
    with runner as pool:  # forked before GTSAM loads
        from ..sfm.merge import merge_parts  # noqa: PLC0415 - GTSAM, after the workers fork
        from ..sfm.partition import pair_weights, partition_view_graph  # noqa: PLC0415 - OpenCV, after the fork
        from ..sfm.parts import PartResult  # noqa: PLC0415

        ids = np.array(sorted(corr.images), np.int64)
        partition = partition_view_graph(pair_weights(ids, corr.pairs), config.partition_size)
        parts = [ids[p] for p in partition.parts]
        log.info("partitioned mapping: %d images in %d parts of at most %d (%s images each)", len(ids),
                 len(parts), config.partition_size, ", ".join(str(len(p)) for p in parts))
        folder = ws.path / "snapshots" / "parts"
        folder.mkdir(parents=True, exist_ok=True)
        record = Record(folder)
        if not resume:
            record.clear()
        source = _input_digest(corr)
        keys = [digest(config_hash(config), source, p) for p in parts]
        results: list = [None] * len(parts)
        for k, key in enumerate(keys):
            if record.get(f"part-{k}", key, [f"part-{k}.pkl"]) is not None:
                results[k] = _load(folder / f"part-{k}.pkl", PartResult)
        todo = [k for k in range(len(parts)) if results[k] is None]
        if len(todo) < len(parts):
            log.info("resuming: %d of %d parts already mapped", len(parts) - len(todo), len(parts))
        bar = progress(total=len(parts), desc="mapping parts", unit="part")
        bar.update(len(parts) - len(todo))
        items = [(str(ws.database_path), parts[k].tolist(), config) for k in todo]
        done = pool.map(map_part_item, items, name=lambda item: f"a part of {len(item[1])} images")
        for k, result in zip(todo, done):
            data = pickle.dumps(result)
            replace_whole(folder / f"part-{k}.pkl", lambda tmp, data=data: tmp.write_bytes(data))
            largest = max((len(m.image_ids) for m in result.models), default=0)
            record.put(f"part-{k}", keys[k], {"images": len(parts[k]), "largest_model": largest}, result.seconds)
            results[k] = result
            bar.update(1)
        bar.close()
        record.prune()
    return merge_parts(corr, config, results)


def map_part_item(item: tuple) -> "PartResult":
    """`map_part(*item)` (sfm/parts.py), the pool's task: one tuple (database path, image ids, settings)."""
    from ..sfm.parts import map_part  # noqa: PLC0415 - GTSAM, loaded in the worker

    return map_part(*item)


def _input_digest(corr: Correspondences) -> str:
    """A hash of the cameras, images, keypoints and verified pairs: parts mapped from other matches are not
    reused."""
    parts = []
    for cid in sorted(corr.cameras):
        c = corr.cameras[cid]
        parts += [[cid, c.model, c.width, c.height, bool(c.prior_trusted)], np.asarray(c.params, np.float64)]
    for iid in sorted(corr.images):
        parts += [[iid, corr.images[iid].name, corr.images[iid].camera_id],
                  np.asarray(corr.keypoints.get(iid, np.zeros((0, 2))), np.float64)]
    for p in corr.pairs:
        parts += [[p.image_id1, p.image_id2, p.config], np.asarray(p.inliers, np.int64)]
    return digest(*parts)


def _load(path, kind):
    """The pickled part result at `path`, or None when it cannot be read (mapped again)."""
    try:
        with open(path, "rb") as f:
            value = pickle.load(f)
    except Exception as exc:  # noqa: BLE001 - cut off or foreign: the part is mapped again
        log.warning("%s: unreadable part result (%s); mapping the part again", path, exc)
        return None
    return value if isinstance(value, kind) else None
