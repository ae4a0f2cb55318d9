"""One part of a partitioned mapping, mapped on its own: `map_part(database, image_ids, config) -> PartResult`.

`map_part` is a plain module-level function of picklable arguments with a picklable result, so that the same
call runs in the calling process, in a worker of the local process pool (executor.WorkerPool) or as a task on
a Dask cluster: it reads only its images and the pairs between them from the COLMAP database, runs the mapper
the config names (incremental or global) on them, and returns each model it made as plain arrays (`PartModel`,
keyed by database image ids, so that the merge needs nothing of the part's internal numbering).
"""

import time
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..database import read_correspondences
from ..progress import hidden
from .config import MapperConfig
from .global_mapper import map_correspondences_globally
from .incremental import map_correspondences
from .model import Reconstruction


@dataclass
class PartModel:
    """One model of a part, in its own frame: the registered images (database ids) with their poses
    (cam_from_world: x_cam = R X + t) and camera parameters, and the points with their observations
    (point row, database image id, keypoint index)."""

    image_ids: np.ndarray  # (k,) int64
    R: np.ndarray  # (k, 3, 3)
    t: np.ndarray  # (k, 3)
    cameras: dict  # camera id -> params (np.ndarray), for the cameras of the registered images
    xyz: np.ndarray  # (p, 3)
    obs_point: np.ndarray  # (o,) rows of xyz
    obs_image: np.ndarray  # (o,) database image ids
    obs_kp: np.ndarray  # (o,) keypoint indices

    def centers(self) -> np.ndarray:
        return -np.einsum("nji,nj->ni", self.R, self.t)

    def observations_per_image(self) -> dict[int, int]:
        ids, counts = np.unique(self.obs_image, return_counts=True)
        return dict(zip(ids.tolist(), counts.tolist()))


@dataclass
class PartResult:
    """What one part gave: its models (largest first), each of its images' status as report.json lists it
    (model numbers are the part's own), and the seconds its mapping took."""

    image_ids: np.ndarray
    models: list[PartModel]
    status: dict
    seconds: float


def map_part(database: str | Path, image_ids: Iterable[int], config: MapperConfig) -> PartResult:
    """Map the images `image_ids` (database ids) of the COLMAP database at `database` with the mapper
    `config.mapper`, using only the verified pairs between them; no snapshot, no bar of its own."""
    start = time.perf_counter()
    ids = np.asarray(sorted(int(i) for i in image_ids), np.int64)
    corr = read_correspondences(database, image_ids=ids.tolist())
    config = replace(config, partition_size=0)
    with hidden():
        if config.mapper == "global":
            result = map_correspondences_globally(corr, config)
        else:
            result = map_correspondences(corr, config)
    return PartResult(ids, [part_model(m) for m in result.models], result.status, time.perf_counter() - start)


def part_model(m: Reconstruction) -> PartModel:
    """A model's registered images and alive points as plain arrays (points renumbered from 0)."""
    reg = m.registered_images()
    pts = m.alive_points()
    row = np.full(m.xyz.n, -1, np.int64)
    row[pts] = np.arange(len(pts))
    obs = m.alive_observations()
    cams = {int(c): m.cameras[int(c)].params.copy() for c in np.unique(m.camera_of[reg]).tolist()}
    return PartModel(image_ids=m.image_ids[reg].copy(), R=m.R[reg].copy(), t=m.t[reg].copy(), cameras=cams,
                     xyz=m.xyz.data[pts].copy(), obs_point=row[m.obs_point.data[obs]],
                     obs_image=m.image_ids[m.obs_image.data[obs]], obs_kp=m.obs_kp.data[obs].copy())
