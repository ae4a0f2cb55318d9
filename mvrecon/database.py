"""The workspace's COLMAP SQLite database, read and written with Python's sqlite3 in COLMAP's schema.

Because the schema and the blobs are COLMAP's own (pycolmap 4.2's: rigs and frames tables, a descriptor type),
`pycolmap.incremental_mapping` can map our matches and our mapper can map COLMAP's. Coordinates stored here use
COLMAP's pixel convention (top-left pixel centre at (0.5, 0.5)). The rest of mvrecon sees plain dataclasses and
numpy arrays.

pycolmap is not imported for any of this: its import took 0.11 s of CPU in every run, beside the feature workers on
the cores they need. It is still what tests read our databases with, and what
tells which of COLMAP's cameras it cannot verify without a focal length (`colmap_needs_focal`).
"""

import os
import sqlite3
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .geometry.camera import CAMERA_MODEL_IDS, MODELS
from .interrupts import ctrl_c_deferred
from .io.files import require_room
from .io.pose_priors import COORDINATE_SYSTEMS, PosePrior, default_covariance
from .io.sqlite import connect_readonly

# COLMAP's two-view configurations as pycolmap 4.2 numbers them (tests/io/test_formats.py checks them)
TWO_VIEW_CONFIGS = {"UNDEFINED": 0, "DEGENERATE": 1, "CALIBRATED": 2, "UNCALIBRATED": 3, "PLANAR": 4,
                    "PANORAMIC": 5, "PLANAR_OR_PANORAMIC": 6, "WATERMARK": 7, "MULTIPLE": 8, "CALIBRATED_RIG": 9}
_MODEL_NAMES = {v: k for k, v in CAMERA_MODEL_IDS.items()}
_CONFIG_NAMES = {v: k for k, v in TWO_VIEW_CONFIGS.items()}
_SIFT = 0  # the descriptors' type: COLMAP's FeatureExtractorType.SIFT
_MAX_IMAGE_ID = 2147483647  # pair_id = image_id1 * this + image_id2, with image_id1 < image_id2
_USER_VERSION = 4020100  # what pycolmap 4.2.1 stamps on the databases it makes (its version)
_SCHEMA = """
CREATE TABLE IF NOT EXISTS rigs (
    rig_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, ref_sensor_id INTEGER NOT NULL,
    ref_sensor_type INTEGER NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS rig_ref_sensor_assignment ON rigs(ref_sensor_id, ref_sensor_type);
CREATE TABLE IF NOT EXISTS rig_sensors (
    rig_id INTEGER NOT NULL, sensor_id INTEGER NOT NULL, sensor_type INTEGER NOT NULL, sensor_from_rig BLOB,
    FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE);
CREATE UNIQUE INDEX IF NOT EXISTS rig_sensor_assignment ON rig_sensors(sensor_id, sensor_type);
CREATE TABLE IF NOT EXISTS cameras (
    camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, model INTEGER NOT NULL, width INTEGER NOT NULL,
    height INTEGER NOT NULL, params BLOB, prior_focal_length INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS frames (
    frame_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, rig_id INTEGER NOT NULL,
    FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS frame_data (
    frame_id INTEGER NOT NULL, data_id INTEGER NOT NULL, sensor_id INTEGER NOT NULL, sensor_type INTEGER NOT NULL,
    FOREIGN KEY(frame_id) REFERENCES frames(frame_id) ON DELETE CASCADE);
CREATE UNIQUE INDEX IF NOT EXISTS frame_sensor_assignment ON frame_data(data_id, sensor_type);
CREATE TABLE IF NOT EXISTS images (
    image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, name TEXT NOT NULL UNIQUE, camera_id INTEGER NOT NULL,
    CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647),
    FOREIGN KEY(camera_id) REFERENCES cameras(camera_id));
CREATE UNIQUE INDEX IF NOT EXISTS index_name ON images(name);
CREATE TABLE IF NOT EXISTS pose_priors (
    pose_prior_id INTEGER PRIMARY KEY NOT NULL, corr_data_id INTEGER NOT NULL, corr_sensor_id INTEGER NOT NULL,
    corr_sensor_type INTEGER NOT NULL, position BLOB, position_covariance BLOB, gravity BLOB,
    coordinate_system INTEGER NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS pose_prior_data_assignment ON
    pose_priors(corr_data_id, corr_sensor_id, corr_sensor_type);
CREATE TABLE IF NOT EXISTS keypoints (
    image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB,
    FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS descriptors (
    image_id INTEGER PRIMARY KEY NOT NULL, type INTEGER NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL,
    data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS matches (
    pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB);
CREATE TABLE IF NOT EXISTS two_view_geometries (
    pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB,
    config INTEGER NOT NULL, F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB, camera1 BLOB, camera2 BLOB);
"""


def _config_name(value: int) -> str:
    return _CONFIG_NAMES.get(int(value), "UNDEFINED")


COLMAP_FISHEYE_NOTE = "COLMAP verifies no pair of a fisheye camera without a known focal length"


def colmap_needs_focal(model: str) -> bool:
    """Whether COLMAP marks every pair of a `model` camera without a focal-length prior DEGENERATE (pycolmap 4.2
    does so for its fisheye models, whose focal length a fundamental matrix cannot give, when it matches and again
    when its mapper loads a database), so that its runs register no image of such a camera."""
    import pycolmap  # noqa: PLC0415 - 0.11 s of CPU that a whole run never spends (tests/stages)

    if model not in pycolmap.CameraModelId.__members__:
        return False
    return bool(pycolmap.Camera(model=model, width=1, height=1).is_perspective_fisheye())


def colmap_blind_cameras(cameras: dict) -> list[int]:
    """The ids of the cameras (id -> CameraInfo) whose pairs COLMAP verifies none of: fisheyes without a trusted
    focal length (`colmap_needs_focal`)."""
    return [cid for cid, cam in sorted(cameras.items()) if not cam.prior_trusted and colmap_needs_focal(cam.model)]


def pair_configurations(path: Path | str) -> dict[str, int]:
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
    keypoint_scales: dict[int, np.ndarray] = field(default_factory=dict)  # image_id -> (N,) detection scale, px
    pairs: list[PairGeometry] = field(default_factory=list)
    priors: dict[int, PosePrior] = field(default_factory=dict)  # image_id -> camera position prior

    def paired_images(self) -> set[int]:
        """The ids of the images in at least one verified pair: the images a mapper can place."""
        return {i for p in self.pairs for i in (p.image_id1, p.image_id2)}


@contextmanager
def open_database(path: Path | str) -> Iterator[sqlite3.Connection]:
    """Open (creating if needed, in COLMAP's schema) a COLMAP database and close it however the block ends. A
    file that is not a readable SQLite database is an InputError naming it, and so is a folder that cannot be
    written (SQLite makes its journal next to the database)."""
    path = Path(path)
    _check_sqlite(path)
    folder = path.resolve().parent
    try:
        db = sqlite3.connect(path, isolation_level=None)  # autocommit; `transaction` groups a unit's writes
    except sqlite3.OperationalError:
        _not_writable(folder)
        raise
    try:
        try:
            _create_schema(db)
        except sqlite3.OperationalError:
            _not_writable(folder)
            raise
        yield db
    finally:
        db.close()


def _not_writable(folder: Path) -> None:
    if not os.access(folder, os.W_OK):
        raise InputError(f"{folder}: cannot write in this folder (read-only, or another user's), which opening "
                         "its database needs; copy the folder, or choose another one") from None


def _create_schema(db) -> None:
    """COLMAP's tables where they are missing; a new database gets COLMAP's WAL journal and version stamp."""
    if db.execute("SELECT COUNT(*) FROM sqlite_master WHERE type = 'table' AND name = 'two_view_geometries'"
                  ).fetchone()[0]:
        return
    db.execute("PRAGMA journal_mode = WAL")
    db.executescript(f"BEGIN; {_SCHEMA} PRAGMA user_version = {_USER_VERSION}; COMMIT;")


def _blob(array, dtype):
    """A matrix as COLMAP stores it: (rows, cols, row-major bytes), NULL for an empty one."""
    a = np.ascontiguousarray(array, dtype=dtype)
    return a.shape[0], a.shape[1], (a.tobytes() if a.size else None)


def _array(data, rows: int, cols: int, dtype) -> np.ndarray:
    if data is None or rows == 0:
        return np.zeros((int(rows), int(cols)), dtype)
    return np.frombuffer(data, dtype=dtype).reshape(int(rows), -1)


def pair_id(image_id1: int, image_id2: int) -> int:
    """COLMAP's id of an unordered image pair."""
    i, j = sorted((int(image_id1), int(image_id2)))
    return i * _MAX_IMAGE_ID + j


def pair_images(pair: int) -> tuple[int, int]:
    """The (smaller, larger) image ids of a COLMAP pair id."""
    return int(pair) // _MAX_IMAGE_ID, int(pair) % _MAX_IMAGE_ID


def write_camera(db: sqlite3.Connection, cam: CameraInfo) -> int:
    if cam.model not in CAMERA_MODEL_IDS:
        raise ValueError(f"unknown COLMAP camera model {cam.model!r}")
    row = (CAMERA_MODEL_IDS[cam.model], int(cam.width), int(cam.height),
           np.asarray(cam.params, dtype=np.float64).tobytes(), int(bool(cam.prior_trusted)))
    if cam.camera_id > 0:
        db.execute("INSERT INTO cameras (camera_id, model, width, height, params, prior_focal_length) "
                   "VALUES (?, ?, ?, ?, ?, ?)", (int(cam.camera_id), *row))
        return int(cam.camera_id)
    return int(db.execute("INSERT INTO cameras (model, width, height, params, prior_focal_length) "
                          "VALUES (?, ?, ?, ?, ?)", row).lastrowid)


def write_image(db: sqlite3.Connection, name: str, camera_id: int) -> int:
    return int(db.execute("INSERT INTO images (name, camera_id) VALUES (?, ?)", (name, int(camera_id))).lastrowid)


def write_features(db: sqlite3.Connection, image_id: int, keypoints: np.ndarray,
                   descriptors: np.ndarray) -> None:
    """Keypoints (N,4): x, y (COLMAP convention), scale, orientation in radians; descriptors (N,128) uint8."""
    kp = np.asarray(keypoints, dtype=np.float32).reshape(-1, 4)
    desc = np.asarray(descriptors, dtype=np.uint8).reshape(len(kp), -1 if len(kp) else 128)
    db.execute("INSERT INTO keypoints (image_id, rows, cols, data) VALUES (?, ?, ?, ?)",
               (int(image_id), *_blob(kp, np.float32)))
    db.execute("INSERT INTO descriptors (image_id, type, rows, cols, data) VALUES (?, ?, ?, ?, ?)",
               (int(image_id), _SIFT, *_blob(desc, np.uint8)))


def write_matches(db: sqlite3.Connection, image_id1: int, image_id2: int, matches: np.ndarray) -> None:
    """Raw (putative) matches, (N,2) keypoint indices of image 1 and image 2."""
    m = np.asarray(matches, dtype=np.uint32).reshape(-1, 2)
    if int(image_id1) > int(image_id2):
        m = m[:, ::-1]
    db.execute("INSERT INTO matches (pair_id, rows, cols, data) VALUES (?, ?, ?, ?)",
               (pair_id(image_id1, image_id2), *_blob(m, np.uint32)))


def write_two_view_geometry(db: sqlite3.Connection, pair: PairGeometry) -> None:
    """Stored for the pair in COLMAP's order (smaller image id first), as COLMAP does: the inliers' columns
    swapped, F and E transposed and H inverted when the pair comes the other way round."""
    inliers = np.asarray(pair.inliers, dtype=np.uint32).reshape(-1, 2)
    F, E, H = pair.F, pair.E, pair.H
    if int(pair.image_id1) > int(pair.image_id2):
        inliers = inliers[:, ::-1]
        F, E = (None if m is None else np.asarray(m).T for m in (F, E))
        H = None if H is None else np.linalg.inv(H)
    matrices = [None if m is None else np.ascontiguousarray(m, dtype=np.float64).reshape(3, 3).tobytes()
                for m in (F, E, H)]
    db.execute("INSERT INTO two_view_geometries (pair_id, rows, cols, data, config, F, E, H) "
               "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
               (pair_id(pair.image_id1, pair.image_id2), *_blob(inliers, np.uint32), TWO_VIEW_CONFIGS[pair.config],
                *matrices))


def read_cameras(db: sqlite3.Connection) -> dict[int, CameraInfo]:
    return {int(cid): CameraInfo(camera_id=int(cid), model=_MODEL_NAMES.get(int(model), f"UNKNOWN_{model}"),
                                 width=int(w), height=int(h), params=np.frombuffer(params or b"", np.float64).copy(),
                                 prior_trusted=bool(prior))
            for cid, model, w, h, params, prior in db.execute(
                "SELECT camera_id, model, width, height, params, prior_focal_length FROM cameras ORDER BY camera_id")}


def read_images(db: sqlite3.Connection) -> dict[int, ImageInfo]:
    return {int(i): ImageInfo(image_id=int(i), name=name, camera_id=int(c))
            for i, name, c in db.execute("SELECT image_id, name, camera_id FROM images ORDER BY image_id")}


_CAMERA_SENSOR = 0  # COLMAP's SensorType.CAMERA: a pose prior belongs to an image (data id) of a camera (sensor id)
_SYSTEM_NAMES = {v: k for k, v in COORDINATE_SYSTEMS.items()}


def write_pose_priors(db: sqlite3.Connection, priors: dict[int, PosePrior]) -> None:
    """Replace the database's pose priors by `priors` (image id -> prior), in COLMAP's layout (pycolmap's
    `Database.read_pose_prior` reads them: position and covariance as float64 blobs, no gravity)."""
    images = read_images(db)
    rows = [(i, images[i].camera_id, _CAMERA_SENSOR, np.asarray(p.position, np.float64).tobytes(),
             np.asarray(p.covariance, np.float64).tobytes(), np.full(3, np.nan).tobytes(),
             COORDINATE_SYSTEMS[p.coordinate_system]) for i, p in sorted(priors.items())]
    with ctrl_c_deferred():
        db.execute("BEGIN")
        db.execute("DELETE FROM pose_priors")
        db.executemany("INSERT INTO pose_priors (pose_prior_id, corr_data_id, corr_sensor_id, corr_sensor_type, "
                       "position, position_covariance, gravity, coordinate_system) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       [(k + 1, *row) for k, row in enumerate(rows)])
        db.execute("COMMIT")


def read_pose_priors(db: sqlite3.Connection) -> dict[int, PosePrior]:
    """image id -> prior of each image with a usable position prior (COLMAP's or ours; a missing covariance, as
    COLMAP writes from EXIF, reads as io.pose_priors' default sigmas)."""
    out = {}
    for image_id, position, cov, system in db.execute(
            "SELECT corr_data_id, position, position_covariance, coordinate_system FROM pose_priors "
            f"WHERE corr_sensor_type = {_CAMERA_SENSOR}"):
        pos = np.frombuffer(position or b"", np.float64)
        name = _SYSTEM_NAMES.get(int(system))
        if pos.shape != (3,) or not np.all(np.isfinite(pos)) or name not in ("WGS84", "CARTESIAN"):
            continue
        c = np.frombuffer(cov or b"", np.float64)
        usable = c.size == 9 and np.all(np.isfinite(c)) and np.all(np.diag(c.reshape(3, 3)) > 0)
        out[int(image_id)] = PosePrior(position=pos.copy(), coordinate_system=name,
                                       covariance=c.reshape(3, 3).copy() if usable else default_covariance())
    return out


def read_correspondences(path: Path | str, min_inliers: int = 0, *, mapped: bool = True,
                         image_ids: Iterable[int] | None = None) -> Correspondences:
    """Load cameras, images, keypoint positions and verified pairs (with at least `min_inliers` inliers);
    with `image_ids`, only those images and the pairs between them (a part of a partitioned mapping).

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
        if image_ids is not None:
            wanted = {int(i) for i in image_ids}
            out.images = {i: info for i, info in out.images.items() if i in wanted}
        out.priors = {i: p for i, p in read_pose_priors(db).items() if i in out.images}
        for image_id in out.images:
            kp = read_keypoints(db, image_id)
            out.keypoints[image_id] = kp[:, :2].copy()
            out.keypoint_scales[image_id] = keypoint_scales(kp)
        for pair, rows, cols, data, config, F, E, H in db.execute(
                "SELECT pair_id, rows, cols, data, config, F, E, H FROM two_view_geometries ORDER BY pair_id"):
            if rows == 0 or rows < min_inliers:
                continue
            id1, id2 = pair_images(pair)
            if image_ids is not None and (id1 not in out.images or id2 not in out.images):
                continue
            out.pairs.append(PairGeometry(
                image_id1=id1, image_id2=id2, config=_config_name(config),
                inliers=_array(data, rows, cols, np.uint32).astype(np.int64), F=_matrix_or_none(F),
                E=_matrix_or_none(E), H=_matrix_or_none(H)))
    return out


def _check_camera_models(path: Path, cameras: dict[int, CameraInfo]) -> None:
    for camera_id, cam in sorted(cameras.items()):
        if cam.model not in MODELS:
            raise InputError(f"{path}: camera {camera_id} is {cam.model}, which mvrecon's mapper does not model; "
                             f"supported: {', '.join(MODELS)}")


def _check_sqlite(path: Path) -> None:
    if not path.is_file() or path.stat().st_size == 0:
        return  # a new database, created by open_database
    try:
        with connect_readonly(path) as con:
            # the schema and one row of every table: cheap, and what a cut-off or foreign file fails on
            for (table,) in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall():
                con.execute(f'SELECT * FROM "{table}" LIMIT 1').fetchall()
    except sqlite3.DatabaseError as exc:
        raise InputError(f"{path}: not a readable COLMAP database ({exc}); delete it, or the workspace, and "
                         "run again") from None


def database_damage(path: Path | str) -> str | None:
    """What SQLite's `PRAGMA quick_check` finds wrong in the database file `path` (its first problem: a page cut
    off or overwritten since it was written), or None when it finds nothing. It reads every page, unlike
    `_check_sqlite`, which passed a database with 4 KB zeroed in its middle: 40 ms for a 24 MB database."""
    try:
        with connect_readonly(path) as con:
            rows = con.execute("PRAGMA quick_check").fetchall()
    except sqlite3.DatabaseError as exc:
        return str(exc)
    lines = [line for (text,) in rows for line in str(text).splitlines() if not line.startswith("***")]
    return None if lines == ["ok"] else (lines or ["quick_check found a problem"])[0]


def _matrix_or_none(blob):
    """A stored 3x3 matrix, or None for a NULL or all-zero one (no such model for the pair)."""
    if blob is None or len(blob) != 72:
        return None
    m = np.frombuffer(blob, dtype=np.float64).reshape(3, 3).copy()
    return m if np.any(m) else None


# --- resumable stages (features, matching): what is done, one transaction per unit of work ---

@contextmanager
def transaction(db: sqlite3.Connection, path: Path | str, nbytes: int) -> Iterator[sqlite3.Connection]:
    """One unit of work (an image's features, a batch of pairs) written whole or not at all: Ctrl-C is held back
    until the block's end, and an error inside it rolls the unit back. The disk must have room for twice the
    block's `nbytes` (the WAL, then the database) first, or the run stops with one line, its earlier units kept."""
    require_room(path, 2 * nbytes)
    with ctrl_c_deferred():
        db.execute("BEGIN")
        try:
            yield db
        except BaseException:
            db.execute("ROLLBACK")
            raise
        db.execute("COMMIT")


def _one(db, sql: str, *args):
    return db.execute(sql, args).fetchone()


def has_features(db: sqlite3.Connection, image_id: int) -> bool:
    return bool(_one(db, "SELECT 1 FROM keypoints WHERE image_id = ?", int(image_id)) and
                _one(db, "SELECT 1 FROM descriptors WHERE image_id = ?", int(image_id)))


def num_keypoints(db: sqlite3.Connection, image_id: int) -> int:
    row = _one(db, "SELECT rows FROM keypoints WHERE image_id = ?", int(image_id))
    return int(row[0]) if row else 0


def read_features(db: sqlite3.Connection, image_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,4+) float keypoints (x, y in COLMAP pixels first) and (N,128) uint8 descriptors of one image."""
    return read_keypoints(db, image_id), read_descriptors(db, image_id)


def read_keypoints(db: sqlite3.Connection, image_id: int) -> np.ndarray:
    """(N,4+) float keypoints of one image, x, y in COLMAP pixels first; (0,4) for an image without any (a blank
    frame, sky)."""
    row = _one(db, "SELECT rows, cols, data FROM keypoints WHERE image_id = ?", int(image_id))
    if row is None or not row[0]:
        return np.zeros((0, 4))
    return _array(row[2], row[0], row[1], np.float32).astype(np.float64)


def keypoint_scales(keypoints: np.ndarray) -> np.ndarray:
    """(N,) detection scale (the blob's sigma, pixels) of COLMAP keypoint rows: column 3 of (N,4) rows, the mean
    length of the affine frame's two columns for (N,6) (COLMAP's own scale); 0 where a (N,2) table says
    nothing."""
    if keypoints.shape[1] >= 6:
        a11, a12, a21, a22 = keypoints[:, 2], keypoints[:, 3], keypoints[:, 4], keypoints[:, 5]
        return (np.hypot(a11, a21) + np.hypot(a12, a22)) / 2
    if keypoints.shape[1] >= 3:
        return np.abs(keypoints[:, 2]).copy()
    return np.zeros(len(keypoints))


def read_descriptors(db: sqlite3.Connection, image_id: int) -> np.ndarray:
    """(N,128) uint8 descriptors of one image, without its keypoints (retrieval needs only these)."""
    row = _one(db, "SELECT rows, cols, data FROM descriptors WHERE image_id = ?", int(image_id))
    if row is None or not row[0]:
        return np.zeros((0, 128), np.uint8)
    return _array(row[2], row[0], row[1], np.uint8)


def has_two_view_geometry(db: sqlite3.Connection, image_id1: int, image_id2: int) -> bool:
    return _one(db, "SELECT 1 FROM two_view_geometries WHERE pair_id = ?", pair_id(image_id1, image_id2)) is not None


def num_matched_pairs(db: sqlite3.Connection) -> int:
    """Pairs with raw matches stored (COLMAP's NumMatchedImagePairs)."""
    return int(_one(db, "SELECT COUNT(*) FROM matches")[0])


def clear_matches(db: sqlite3.Connection) -> None:
    """Drop raw matches and verified geometries (when the matching config changes)."""
    db.execute("DELETE FROM matches")
    db.execute("DELETE FROM two_view_geometries")


def read_verified_pairs(db: sqlite3.Connection) -> list[tuple[int, int, str, int]]:
    """(image_id1, image_id2, configuration name, inlier count) of every pair with at least one inlier."""
    return [(*pair_images(pair), _config_name(config), int(rows)) for pair, config, rows in db.execute(
        "SELECT pair_id, config, rows FROM two_view_geometries WHERE rows > 0 ORDER BY pair_id")]


def database_counts(path: Path | str) -> dict:
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
