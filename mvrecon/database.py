"""The workspace's COLMAP SQLite database, read and written through `pycolmap.Database`.

Because the schema is COLMAP's own, `pycolmap.incremental_mapping` can map our matches and our mapper can map
COLMAP's. Coordinates stored here use COLMAP's pixel convention (top-left pixel centre at (0.5, 0.5)).
The rest of mvrecon sees plain dataclasses and numpy arrays, never pycolmap objects.

pycolmap is imported on first use, not with this module: its import (0.1 s) then overlaps the feature workers'
start instead of delaying it, and `mvrecon --help` does not pay it.
"""

import functools
import os
from contextlib import closing, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .interrupts import ctrl_c_deferred
from .io.files import require_room


def _pycolmap():
    import pycolmap

    return pycolmap


@functools.cache
def _configs() -> dict[str, int]:
    """COLMAP's two-view configurations, by name (pycolmap.TwoViewGeometryConfiguration)."""
    return {m.name: int(m.value) for m in _pycolmap().TwoViewGeometryConfiguration.__members__.values()}


@functools.cache
def _config_name(value: int) -> str:
    return next((name for name, v in _configs().items() if v == value), "UNDEFINED")


COLMAP_FISHEYE_NOTE = "COLMAP verifies no pair of a fisheye camera without a known focal length"


def colmap_needs_focal(model: str) -> bool:
    """Whether COLMAP marks every pair of a `model` camera without a focal-length prior DEGENERATE (pycolmap 4.2
    does so for its fisheye models, whose focal length a fundamental matrix cannot give, when it matches and again
    when its mapper loads a database), so that its runs register no image of such a camera."""
    pycolmap = _pycolmap()
    if model not in pycolmap.CameraModelId.__members__:
        return False
    return bool(pycolmap.Camera(model=model, width=1, height=1).is_perspective_fisheye())


def colmap_blind_cameras(cameras: dict) -> list[int]:
    """The ids of the cameras (id -> CameraInfo) whose pairs COLMAP verifies none of: fisheyes without a trusted
    focal length (`colmap_needs_focal`)."""
    return [cid for cid, cam in sorted(cameras.items()) if not cam.prior_trusted and colmap_needs_focal(cam.model)]


def connect_readonly(path):
    """A read-only sqlite3 connection to the database file `path`, closed on leaving the `with` block; the
    plain-SQL reads below need what pycolmap's reader skips or refuses."""
    import sqlite3

    path = Path(path).resolve()
    uri = path.as_uri() + "?mode=ro"
    if not os.access(path.parent, os.W_OK):
        # a WAL database is read through a shared-memory file made next to it; in a folder that cannot be
        # written (a read-only mount, another user's run) SQLite cannot make it, and nothing can change the file
        wal = Path(f"{path}-wal")
        if wal.is_file() and wal.stat().st_size > 0:
            raise InputError(f"{path}: its last changes are still in {wal.name}, and its folder cannot be written "
                             "to merge them; copy the folder to a writable place and run again")
        uri += "&immutable=1"
    return closing(sqlite3.connect(uri, uri=True))


def pair_configurations(path) -> dict[str, int]:
    """Matched pairs per two-view configuration in the database, most first; read with SQL, as pycolmap's
    reader skips the pairs without inliers, which are the ones that tell why none is verified."""
    with connect_readonly(path) as con:
        rows = con.execute("SELECT config, COUNT(*) FROM two_view_geometries GROUP BY config "
                           "ORDER BY COUNT(*) DESC").fetchall()
    return {_config_name(int(c)): int(n) for c, n in rows}


@dataclass(kw_only=True)
class CameraInfo:
    camera_id: int = -1
    model: str
    width: int
    height: int
    params: np.ndarray
    prior_trusted: bool = False  # COLMAP's has_prior_focal_length: the focal length is known, not guessed


@dataclass(kw_only=True)
class ImageInfo:
    image_id: int
    name: str
    camera_id: int


@dataclass(kw_only=True)
class PairGeometry:
    """A verified image pair: inlier matches as (N,2) keypoint indices, and the geometry that explains them."""

    image_id1: int
    image_id2: int
    config: str  # COLMAP's name: CALIBRATED, UNCALIBRATED, PLANAR, PANORAMIC, PLANAR_OR_PANORAMIC, DEGENERATE...
    inliers: np.ndarray
    F: np.ndarray | None = None
    E: np.ndarray | None = None
    H: np.ndarray | None = None


@dataclass(kw_only=True)
class Correspondences:
    """Everything the mapper needs from a database: cameras, images, keypoints and verified pairs."""

    cameras: dict[int, CameraInfo] = field(default_factory=dict)
    images: dict[int, ImageInfo] = field(default_factory=dict)
    keypoints: dict[int, np.ndarray] = field(default_factory=dict)  # image_id -> (N,2) pixels, COLMAP convention
    pairs: list[PairGeometry] = field(default_factory=list)


@contextmanager
def open_database(path):
    """Open (creating if needed) a COLMAP database and close it however the block ends. A file that is not a
    readable SQLite database is an InputError naming it (pycolmap would log a warning and raise a bare
    RuntimeError)."""
    _check_sqlite(Path(path))
    folder = Path(path).resolve().parent
    writable = os.access(folder, os.W_OK)
    pycolmap = _pycolmap()
    saved = pycolmap.logging.minloglevel
    if not writable:  # pycolmap would log a warning, then raise "No registered database factory succeeded"
        pycolmap.logging.minloglevel = pycolmap.logging.ERROR
    try:
        db = pycolmap.Database.open(str(path))
    except RuntimeError:
        if writable:
            raise
        raise InputError(f"{folder}: cannot write in this folder (read-only, or another user's), which opening "
                         "its database needs; copy the folder, or choose another one") from None
    finally:
        pycolmap.logging.minloglevel = saved
    try:
        yield db
    finally:
        db.close()


def write_camera(db, cam: CameraInfo) -> int:
    c = _pycolmap().Camera(model=cam.model, width=int(cam.width), height=int(cam.height),
                           params=np.asarray(cam.params, dtype=float), has_prior_focal_length=bool(cam.prior_trusted))
    if cam.camera_id > 0:
        c.camera_id = cam.camera_id
        return db.write_camera(c, use_camera_id=True)
    return db.write_camera(c)


def write_image(db, name: str, camera_id: int) -> int:
    return db.write_image(_pycolmap().Image(name=name, camera_id=int(camera_id)))


def write_features(db, image_id: int, keypoints: np.ndarray, descriptors: np.ndarray) -> None:
    """Keypoints (N,4): x, y (COLMAP convention), scale, orientation in radians; descriptors (N,128) uint8."""
    kp = np.ascontiguousarray(keypoints, dtype=np.float32).reshape(-1, 4)
    desc = np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(len(kp), -1 if len(kp) else 128)
    db.write_keypoints(int(image_id), kp)
    pycolmap = _pycolmap()
    db.write_descriptors(int(image_id), pycolmap.FeatureDescriptors(type=pycolmap.FeatureExtractorType.SIFT,
                                                                    data=desc))


def write_matches(db, image_id1: int, image_id2: int, matches: np.ndarray) -> None:
    """Raw (putative) matches, (N,2) keypoint indices of image 1 and image 2."""
    db.write_matches(int(image_id1), int(image_id2), np.ascontiguousarray(matches, dtype=np.uint32).reshape(-1, 2))


def write_two_view_geometry(db, pair: PairGeometry) -> None:
    kwargs = {"config": _configs()[pair.config],
              "inlier_matches": np.ascontiguousarray(pair.inliers, dtype=np.uint32).reshape(-1, 2)}
    for name in ("F", "E", "H"):
        value = getattr(pair, name)
        if value is not None:
            kwargs[name] = np.asarray(value, dtype=float)
    db.write_two_view_geometry(int(pair.image_id1), int(pair.image_id2), _pycolmap().TwoViewGeometry(**kwargs))


def _camera_info(c) -> CameraInfo:
    return CameraInfo(camera_id=int(c.camera_id), model=c.model.name, width=int(c.width), height=int(c.height),
                      params=np.asarray(c.params, dtype=float), prior_trusted=bool(c.has_prior_focal_length))


def read_cameras(db) -> dict[int, CameraInfo]:
    return {int(c.camera_id): _camera_info(c) for c in db.read_all_cameras()}


def read_images(db) -> dict[int, ImageInfo]:
    return {int(i.image_id): ImageInfo(image_id=int(i.image_id), name=i.name, camera_id=int(i.camera_id))
            for i in db.read_all_images()}


def read_correspondences(path, min_inliers: int = 0, *, mapped: bool = True) -> Correspondences:
    """Load cameras, images, keypoint positions and verified pairs (with at least `min_inliers` inliers).

    `mapped`: the correspondences are for mvrecon's mapper, so a camera of a model it does not model is an
    InputError here, before any work (COLMAP has more models: FULL_OPENCV, FOV, the radial fisheyes...);
    False reads any COLMAP database (the counts of a report)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such database")
    out = Correspondences()
    with open_database(path) as db:
        out.cameras = read_cameras(db)
        if mapped:
            _check_camera_models(path, out.cameras)
        out.images = read_images(db)
        for image_id in out.images:
            out.keypoints[image_id] = read_keypoints(db, image_id)[:, :2].copy()
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, g in zip(pair_ids, geometries):
            inliers = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
            if len(inliers) == 0 or len(inliers) < min_inliers:
                continue
            id1, id2 = _pycolmap().pair_id_to_image_pair(int(pair_id))
            out.pairs.append(PairGeometry(
                image_id1=int(id1), image_id2=int(id2), config=_config_name(int(g.config)),
                inliers=inliers, F=_matrix_or_none(g.F), E=_matrix_or_none(g.E), H=_matrix_or_none(g.H)))
    return out


def _check_camera_models(path: Path, cameras: dict[int, CameraInfo]) -> None:
    from .geometry.camera import MODELS

    for camera_id, cam in sorted(cameras.items()):
        if cam.model not in MODELS:
            raise InputError(f"{path}: camera {camera_id} is {cam.model}, which mvrecon's mapper does not model; "
                             f"supported: {', '.join(MODELS)}")


def _check_sqlite(path: Path) -> None:
    if not path.is_file() or path.stat().st_size == 0:
        return  # a new database, created by pycolmap
    import sqlite3

    try:
        with connect_readonly(path) as con:
            # the schema and one row of every table: cheap, and what a cut-off or foreign file fails on
            for (table,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall():
                con.execute(f'SELECT * FROM "{table}" LIMIT 1').fetchall()
    except sqlite3.DatabaseError as exc:
        raise InputError(f"{path}: not a readable COLMAP database ({exc}); delete it, or the workspace, and "
                         "run again") from None


def _matrix_or_none(m):
    m = np.asarray(m, dtype=float)
    return None if m.shape != (3, 3) or not np.any(m) else m


# --- resumable stages (features, matching): what is done, one transaction per unit of work ---

@contextmanager
def transaction(db, path, nbytes: int):
    """One unit of work (an image's features, a batch of pairs) written at once. pycolmap's transaction commits
    whatever the block wrote however it ends, so Ctrl-C is held back until the block's end; and a commit that
    fails (a full disk) aborts the process from inside pycolmap, so the disk must have room for twice the block's
    `nbytes` (the WAL, then the database) first, or the run stops with one line, its earlier units kept."""
    require_room(path, 2 * nbytes)
    with ctrl_c_deferred(), _pycolmap().DatabaseTransaction(db):
        yield db


def has_features(db, image_id: int) -> bool:
    return bool(db.exists_keypoints(int(image_id)) and db.exists_descriptors(int(image_id)))


def num_keypoints(db, image_id: int) -> int:
    return int(db.num_keypoints_for_image(int(image_id))) if db.exists_keypoints(int(image_id)) else 0


def read_features(db, image_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,4+) float keypoints (x, y in COLMAP pixels first) and (N,128) uint8 descriptors of one image."""
    return read_keypoints(db, image_id), read_descriptors(db, image_id)


def read_keypoints(db, image_id: int) -> np.ndarray:
    """(N,4+) float keypoints of one image, x, y in COLMAP pixels first."""
    kp = np.asarray(db.read_keypoints(int(image_id)), dtype=float)
    if len(kp) == 0:  # a featureless image (a blank frame, sky): reshape(0, -1) would raise
        return kp.reshape(0, 4)
    return kp.reshape(len(kp), -1)


def read_descriptors(db, image_id: int) -> np.ndarray:
    """(N,128) uint8 descriptors of one image, without its keypoints (retrieval needs only these)."""
    desc = np.asarray(db.read_descriptors(int(image_id)).data, dtype=np.uint8)
    return desc if desc.ndim == 2 and desc.shape[1] else desc.reshape(-1, 128)


def has_two_view_geometry(db, image_id1: int, image_id2: int) -> bool:
    return bool(db.exists_two_view_geometry(int(image_id1), int(image_id2)))


def clear_matches(db) -> None:
    """Drop raw matches and verified geometries (when the matching config changes)."""
    db.clear_matches()
    db.clear_two_view_geometries()


def read_verified_pairs(db) -> list[tuple[int, int, str, int]]:
    """(image_id1, image_id2, configuration name, inlier count) of every pair with at least one inlier."""
    out = []
    pair_ids, geometries = db.read_two_view_geometries()
    for pair_id, g in zip(pair_ids, geometries):
        n = len(np.asarray(g.inlier_matches).reshape(-1, 2))
        if n:
            id1, id2 = _pycolmap().pair_id_to_image_pair(int(pair_id))
            out.append((int(id1), int(id2), _config_name(int(g.config)), n))
    return out


def database_counts(path) -> dict:
    """Images, keypoints per image, verified pairs and mean inliers per pair of a COLMAP database.

    One definition for every engine's report: a pair is verified when its two-view geometry is neither
    undefined, degenerate nor a watermark and keeps inlier matches.
    """
    corr = read_correspondences(path, mapped=False)
    pairs = [p for p in corr.pairs if p.config not in ("UNDEFINED", "DEGENERATE", "WATERMARK")]
    n_kp = [len(corr.keypoints.get(i, ())) for i in corr.images]
    return {"images": len(corr.images), "keypoints_per_image": float(sum(n_kp) / max(len(n_kp), 1)),
            "verified_pairs": len(pairs),
            "mean_inliers_per_pair": float(sum(len(p.inliers) for p in pairs) / max(len(pairs), 1))}
