"""Our `sfm.model.Reconstruction` written as COLMAP binary `sparse/N` folders, with numpy rather than pycolmap.

Only registered images go into a model (each with a trivial rig and frame, as COLMAP 3.12+ stores them), with
all their keypoints as 2D points so point2D indices stay the database's keypoint indices. The five .bin files are
byte for byte what pycolmap's `write_binary` wrote for the same model (tests/io/test_formats.py holds them to
it): importing pycolmap cost about 110 ms of CPU in every run, and building its reconstruction point by point
11 ms for 1700 points. Only the text files (--text) still come from pycolmap, which reads the binary folder back.
Point colours come from the colours at the keypoints that feature extraction sampled, or else from the images
when the image folder is given.
"""

import logging
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ..errors import InputError
from ..geometry import camera as cammodel
from ..geometry.rotation import eigen_quaternions, eigen_rotate
from .files import require_room, some_names
from .images import colors_at, read_image
from .ply import write_ply

if TYPE_CHECKING:
    import pycolmap

log = logging.getLogger("mvrecon.io")

# COLMAP's id of a 2D point without a 3D point (kInvalidPoint3DId)
_INVALID_POINT3D = np.iinfo(np.uint64).max
_SENSOR_CAMERA = 0  # COLMAP's SensorType::CAMERA
# a 3D point's record before its track (packed: 51 bytes), a 2D point's, a track element's
_POINT3D = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("length", "<u8")])
_POINT2D = np.dtype([("xy", "<f8", 2), ("point3d", "<u8")])
_TRACK_ELEMENT = np.dtype([("image", "<u4"), ("point2d", "<u4")])
# a point behind its camera: COLMAP counts its squared error as the largest double
_BEHIND_ERROR = float(np.sqrt(np.finfo(np.float64).max))


class SparseModel(Protocol):
    """What writing a model reads of it: the parts of `sfm.model.Reconstruction` used here. io/ sits below sfm/,
    so this module names the contract instead of importing the class."""

    image_ids: np.ndarray
    names: list[str]
    camera_of: np.ndarray
    cameras: dict
    keypoints: list[np.ndarray]
    R: np.ndarray
    t: np.ndarray
    registered: np.ndarray
    registration_order: list[int]
    xyz: Any  # growable arrays (sfm.model's buffers): `.data` is the array
    obs_image: Any
    obs_kp: Any
    obs_point: Any

    def alive_observations(self) -> np.ndarray: ...

    def camera(self, i: int) -> Any: ...


@dataclass
class WrittenModel:
    """What write_models wrote of one model, for points.ply and the text-name warning: image names (in the
    file's order), and point positions and colours in point3D-id order (ids 1, 2, ...)."""

    names: list[str]
    xyz: np.ndarray
    rgb: np.ndarray


def point_colors(model: SparseModel, keypoint_colors: dict) -> np.ndarray | None:
    """RGB (uint8) of every point id: the mean of the colours at its alive observations' keypoints (from
    `keypoint_colors`: image name -> io.images.colors_at of its keypoints), rounded, as COLMAP's
    `extract_colors_for_all_images` averages its samples (but half to even: an exact half, one point in 2000
    on templeSparseRing, rounds down where COLMAP rounds up); black without any. None when an image of the model
    has no keypoint colours."""
    means = _mean_colors(model, keypoint_colors)
    return None if means is None else np.round(means).clip(0, 255).astype(np.uint8)


def _mean_colors(model, samples: dict) -> np.ndarray | None:
    """(n,3) mean of the colours `samples` (as point_colors takes them) of each point id's alive observations;
    0 without any, None when an image of the model has no samples."""
    obs = model.alive_observations()
    img, kp, pt = model.obs_image.data[obs], model.obs_kp.data[obs], model.obs_point.data[obs]
    rgb = np.empty((len(obs), 3))
    for i in np.unique(img):
        colors = samples.get(model.names[i])
        if colors is None:
            return None
        m = img == i
        rgb[m] = colors[kp[m]]
    valid = np.isfinite(rgb).all(axis=1)  # keypoints at the border have no colour (NaN), as in COLMAP
    n = len(model.xyz.data)
    counts = np.bincount(pt[valid], minlength=n)
    sums = np.stack([np.bincount(pt[valid], weights=rgb[valid, c], minlength=n) for c in range(3)], axis=1)
    return sums / np.maximum(counts, 1)[:, None]


def image_colors(model: SparseModel, image_dir: Path | str) -> np.ndarray:
    """RGB (uint8) of every point id sampled in the registered images in image_dir, what pycolmap's
    `extract_colors_for_all_images` gave (bilinear at each observation, averaged per point). An image that
    cannot be read is left out with a warning, as COLMAP does. The keypoints are in the upright frame our
    feature extraction works in; those of a COLMAP database are in the stored one, told by the camera's size."""
    samples = {}
    for i in model.registration_order:
        name, cam, kp = model.names[i], model.camera(i), model.keypoints[i]
        path = Path(image_dir) / name
        try:
            image = read_image(path)
            if image.shape[:2] != (cam.height, cam.width):
                stored = read_image(path, upright=False)
                image = stored if stored.shape[:2] == (cam.height, cam.width) else image
        except InputError as exc:
            log.warning("%s; the colours of its points come from the other images", exc)
            samples[name] = np.full((len(kp), 3), np.nan, np.float32)
            continue
        samples[name] = colors_at(image, kp)
    return np.floor(_mean_colors(model, samples) + 0.5).clip(0, 255).astype(np.uint8)  # COLMAP's std::round


def _tracks(model):
    """The alive observations in registered images, ordered by point (and by observation id within one, the
    order the tracks were added to pycolmap in): (obs, their point ids, the points in order, track lengths)."""
    obs = model.alive_observations()
    obs = obs[model.registered[model.obs_image.data[obs]]]
    op = model.obs_point.data[obs]
    order = np.argsort(op, kind="stable")
    obs, op = obs[order], op[order]
    points, lengths = np.unique(op, return_counts=True)
    return obs, op, points, lengths


def _point_errors(model, obs, poses, kp_xy, lengths) -> np.ndarray:
    """Each point's mean reprojection error over its track (`obs`, grouped by point; `poses`: their images'
    written poses; `kp_xy`: their keypoints), computed and summed as pycolmap's `update_point_3d_errors`."""
    Xc = eigen_rotate(poses[:, :4], model.xyz.data[model.obs_point.data[obs]]) + poses[:, 4:]
    cams = model.camera_of[model.obs_image.data[obs]]
    uv = np.empty((len(obs), 2))
    for cid in np.unique(cams):
        m = cams == cid
        cam = model.cameras[int(cid)]
        uv[m] = cammodel.project(cam.model, cam.params, Xc[m])
    d = uv - kp_xy
    err = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    err[~(Xc[:, 2] >= np.finfo(np.float64).eps) | ~np.isfinite(err)] = _BEHIND_ERROR
    point_index = np.repeat(np.arange(len(lengths)), lengths)
    return np.bincount(point_index, weights=err, minlength=len(lengths)) / np.maximum(lengths, 1)


def model_files(model: SparseModel, colors: np.ndarray | None = None) -> tuple[dict[str, bytes], WrittenModel]:
    """The five .bin files of the registered images, their cameras and the points with observations (coloured
    by `colors`, indexed by point id, when given; else black), and what they hold for points.ply."""
    reg = np.asarray(model.registration_order, dtype=np.int64)  # pycolmap keeps the images in this order
    obs, op, points, lengths = _tracks(model)
    new_id = np.zeros(len(model.xyz.data), np.uint64)
    new_id[points] = np.arange(1, len(points) + 1, dtype=np.uint64)  # pycolmap numbers them as added
    # the registered images' keypoints in one array, in file order; image k's begin at first[k]
    slot = np.full(len(model.image_ids), -1)
    slot[reg] = np.arange(len(reg))
    counts = np.array([len(model.keypoints[i]) for i in reg], dtype=np.int64)
    first = np.cumsum(counts) - counts
    keypoints = np.concatenate([model.keypoints[i] for i in reg] or [np.zeros((0, 2))]).reshape(-1, 2)
    obs_slot = slot[model.obs_image.data[obs]]
    where = first[obs_slot] + model.obs_kp.data[obs]
    points2d = np.empty(len(keypoints), _POINT2D)
    points2d["xy"] = keypoints
    points2d["point3d"] = _INVALID_POINT3D
    points2d["point3d"][where] = new_id[op]
    poses = np.concatenate([eigen_quaternions(model.R[reg]), model.t[reg]], axis=1)

    images = [struct.pack("<Q", len(reg))]
    for k, i in enumerate(reg):
        images += [struct.pack("<I7dI", model.image_ids[i], *poses[k], model.camera_of[i]),
                   model.names[i].encode() + b"\0", struct.pack("<Q", counts[k]),
                   points2d[first[k]:first[k] + counts[k]].tobytes()]
    rgb = np.zeros((len(points), 3), np.uint8) if colors is None else np.asarray(colors, np.uint8)[points]
    xyz = model.xyz.data[points]
    head = np.empty(len(points), _POINT3D)
    head["id"], head["xyz"], head["rgb"], head["length"] = new_id[points], xyz, rgb, lengths
    head["error"] = _point_errors(model, obs, poses[obs_slot], keypoints[where], lengths)
    track = np.empty(len(obs), _TRACK_ELEMENT)
    track["image"], track["point2d"] = model.image_ids[model.obs_image.data[obs]], model.obs_kp.data[obs]
    files = {**_cameras_rigs_frames(model, reg, poses), "images.bin": b"".join(images),
             "points3D.bin": _points_file(head, track, lengths)}
    return files, WrittenModel([model.names[i] for i in reg], xyz, rgb)


def _cameras_rigs_frames(model, reg, poses) -> dict[str, bytes]:
    """cameras.bin, and rigs.bin and frames.bin with the trivial rig of each camera (its only sensor) and the
    trivial frame of each registered image (numbered as the image), by id as pycolmap writes them."""
    cam_ids = np.unique(model.camera_of[reg])
    cameras = [struct.pack("<Q", len(cam_ids))]
    for cid in cam_ids:
        cam = model.cameras[int(cid)]
        cameras += [struct.pack("<IiQQ", cid, cammodel.CAMERA_MODEL_IDS[cam.model], cam.width, cam.height),
                    np.asarray(cam.params, "<f8").tobytes()]
    rigs = np.zeros(len(cam_ids), [("rig", "<u4"), ("sensors", "<u4"), ("type", "<i4"), ("sensor", "<u4")])
    rigs["rig"] = rigs["sensor"] = cam_ids
    rigs["sensors"], rigs["type"] = 1, _SENSOR_CAMERA
    frames = np.zeros(len(reg), [("frame", "<u4"), ("rig", "<u4"), ("pose", "<f8", 7), ("data", "<u4"),
                                 ("type", "<i4"), ("sensor", "<u4"), ("image", "<u8")])
    frames["frame"] = frames["image"] = model.image_ids[reg]
    frames["rig"] = frames["sensor"] = model.camera_of[reg]
    frames["pose"], frames["data"], frames["type"] = poses, 1, _SENSOR_CAMERA
    frames = frames[np.argsort(model.image_ids[reg], kind="stable")]
    return {"cameras.bin": b"".join(cameras), "rigs.bin": struct.pack("<Q", len(rigs)) + rigs.tobytes(),
            "frames.bin": struct.pack("<Q", len(frames)) + frames.tobytes()}


def _points_file(head, track, lengths) -> bytes:
    """points3D.bin: each point's record followed by its track. The records have different lengths, so the
    bytes are placed column by column (51 + 8 assignments, not one per point)."""
    n, m = len(head), len(track)
    before = np.cumsum(lengths) - lengths  # track elements of the earlier points
    starts = 8 + _POINT3D.itemsize * np.arange(n) + _TRACK_ELEMENT.itemsize * before
    # element e of point p follows p + 1 point records and e earlier elements
    elem_starts = 8 + _POINT3D.itemsize * (np.repeat(np.arange(n), lengths) + 1) + _TRACK_ELEMENT.itemsize * \
        np.arange(m)
    out = np.empty(8 + _POINT3D.itemsize * n + _TRACK_ELEMENT.itemsize * m, np.uint8)
    out[:8] = np.array([n], "<u8").view(np.uint8)
    for records, at in ((head, starts), (track, elem_starts)):
        raw = records.view(np.uint8).reshape(len(records), records.dtype.itemsize)
        for b in range(raw.shape[1]):
            out[at + b] = raw[:, b]
    return out.tobytes()


def write_models(models: list[SparseModel], sparse_dir: Path | str, image_dir: Path | str | None = None,
                 text: bool = False,
                 keypoint_colors: dict[str, np.ndarray] | None = None) -> list[WrittenModel]:
    """Write models (largest first) to sparse_dir/0, 1, ...; point colours from `keypoint_colors` (see
    point_colors) when it covers a model's images, otherwise from the images in image_dir when given."""
    sparse_dir = Path(sparse_dir)
    out = []
    for k, model in enumerate(models):
        colors = point_colors(model, keypoint_colors) if keypoint_colors else None
        if colors is None and image_dir is not None:
            colors = image_colors(model, image_dir)
        files, written = model_files(model, colors)
        d = sparse_dir / str(k)
        # the text files take up to three times the binary ones
        require_room(d, sum(map(len, files.values())) * (4 if text else 1))
        d.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            (d / name).write_bytes(data)
        if text:
            _write_text(d)
        out.append(written)
    return out


def _write_text(folder) -> None:
    """The COLMAP text files beside a binary model, written by pycolmap (imported only for --text)."""
    import pycolmap  # noqa: PLC0415 - 0.11 s of CPU that a whole run never spends (tests/io)

    pycolmap.Reconstruction(str(folder)).write_text(str(folder))


def model_bytes(rec: "pycolmap.Reconstruction") -> int:
    """About the size of a pycolmap reconstruction's binary files (the text ones take up to three times as
    much), for a room check before pycolmap writes them: it does not report a failed write (on a full disk it
    left points3D.bin empty). Every keypoint of an image is a 2D point of 24 bytes, a 3D point 51 bytes and 8
    per observation."""
    num_points2d = sum(im.num_points2D() for im in rec.images.values())
    return 24 * num_points2d + 256 * rec.num_images() + 64 * rec.num_points3D() + 8 * rec.compute_num_observations()


def write_text_models(sparse_dir: Path | str) -> int:
    """Add the COLMAP text files to every binary model sparse_dir/N (a finished run asked for --text again);
    returns the number of models."""
    import pycolmap  # noqa: PLC0415 - 0.11 s of CPU that a whole run never spends (tests/io)

    dirs = [d for d in sorted(Path(sparse_dir).iterdir()) if (d / "cameras.bin").is_file()]
    recs = [pycolmap.Reconstruction(str(d)) for d in dirs]
    require_room(sparse_dir, 3 * sum(model_bytes(rec) for rec in recs))
    for rec, d in zip(recs, dirs):
        rec.write_text(str(d))
    warn_text_names([[im.name for im in rec.images.values()] for rec in recs], sparse_dir)
    return len(dirs)


def warn_text_names(models_names: list[list[str]], sparse_dir: Path | str) -> None:
    """Warn when an image name of the text models sparse_dir/N (`models_names[N]`: its image names) holds white
    space: the text format ends a name at its first space, so COLMAP's reader (pycolmap read 'photo 2.png' back
    as 'photo') and nerfstudio's lose those names; the binary files next to them keep them whole."""
    for k, names in enumerate(models_names):
        spaced = sorted(name for name in names if any(c.isspace() for c in name))
        if spaced:
            log.warning("%s: image names with spaces (%s) cannot be read back from images.txt, which ends a "
                        "name at its first space; read the binary model in the same folder, or rename the images",
                        Path(sparse_dir) / str(k) / "images.txt", some_names(map(repr, spaced)))


def write_points_ply(written: WrittenModel, path: Path | str) -> int:
    """Coloured PLY of a written model's points (in point3D-id order); returns the number of points."""
    write_ply(path, written.xyz, written.rgb)
    return len(written.xyz)


def load_reconstruction(path: Path | str) -> "pycolmap.Reconstruction":
    """A COLMAP model folder (binary or text); an InputError names the folder when it holds no model or one
    that pycolmap cannot read (a cut-off images.bin raises IndexError there, a garbled cameras.bin ValueError)."""
    import pycolmap  # noqa: PLC0415 - 0.11 s of CPU that a whole run never spends (tests/io)

    path = Path(path)
    if not (path / "images.bin").exists() and not (path / "images.txt").exists():
        raise InputError(f"{path}: no COLMAP model (images.bin or images.txt) here")
    for name, check in (("points3D.bin", _points_problem), ("images.bin", _images_problem)):
        if (path / name).is_file():
            problem = check((path / name).read_bytes())
            if problem:
                raise InputError(f"{path}: cannot read this COLMAP model ({name}: {problem})")
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:
        raise InputError(f"{path}: cannot read this COLMAP model ({type(exc).__name__}: {exc})") from None
    for cam in rec.cameras.values():  # a cut-off cameras.bin reads as zeros
        params = np.asarray(cam.params, float)
        if not len(params) or not np.isfinite(params).all() or min(cam.focal_length_x, cam.focal_length_y) <= 0:
            raise InputError(f"{path}: cannot read this COLMAP model (camera {cam.camera_id}: parameters "
                             f"{params.tolist()})")
    return rec


def _points_problem(data: bytes) -> str | None:
    """Whether points3D.bin's records add up to its size. pycolmap reads a file cut off mid-record as garbage
    lengths and may allocate without end (a compare run hung for minutes), so the sizes are walked first:
    count, then per point id, xyz, rgb, error (43 bytes), a track length and 8 bytes per track element."""
    n, offset = struct.unpack_from("<Q", data, 0)[0] if len(data) >= 8 else 0, 8
    for k in range(n):
        if offset + 51 > len(data):
            return f"cut off after {k} of {n} points"
        offset += 51 + 8 * struct.unpack_from("<Q", data, offset + 43)[0]
    return _ending(offset, len(data), n, "points")


def _images_problem(data: bytes) -> str | None:
    """The same for images.bin: per image id, rotation, translation, camera id (64 bytes), a name ending in a
    zero byte, a count of 2D points and 24 bytes per point."""
    n, offset = struct.unpack_from("<Q", data, 0)[0] if len(data) >= 8 else 0, 8
    for k in range(n):
        end = data.find(b"\0", offset + 64)
        if end < 0 or end + 9 > len(data):
            return f"cut off after {k} of {n} images"
        offset = end + 9 + 24 * struct.unpack_from("<Q", data, end + 1)[0]
    return _ending(offset, len(data), n, "images")


def _ending(offset: int, size: int, n: int, what: str) -> str | None:
    if offset > size:
        return f"cut off in the last of its {n} {what}"
    return f"{size - offset} bytes after its {n} {what}" if offset < size else None
