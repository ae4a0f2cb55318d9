"""Ground-truth cameras from the formats our data sets ship in, as one plain type: name -> (R, t) world-to-camera.

Supported: a COLMAP model folder (a catalog scene's `gt/sparse`, gtsfm's `colmap_ground_truth`), a Middlebury
`*_par.txt` (P = K[R t]), a Strecha `gt_dense_cameras/` folder (`*.camera`: K, distortion, R camera-to-world,
centre C; P = K[R^T | -R^T C]) and an IMC `calibration/` folder (`calibration_<stem>.h5` with K, R, T; x ~ K(RX+T)).
The HDF5 files are tiny and contiguous, so a small reader here avoids a dependency on h5py.
"""

import struct
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.rotation import nearest_rotation, quat_to_rotmat
from .models import load_reconstruction, poses

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".JPG", ".JPEG", ".PNG", ".TIF", ".TIFF")


class GroundTruth(dict):
    """A dict image name -> (R, t) (world-to-camera) that also carries what the source knew besides poses.

    `intrinsics`: name -> 3x3 K where the source gives it; `points`: (N,3) reference surface points or None;
    `source`: the file or folder it came from; `kind`: colmap, middlebury, strecha or imc.
    """

    def __init__(self, poses: Mapping | Iterable = (), *, intrinsics: dict | None = None,
                 points: np.ndarray | None = None, source: str = "", kind: str = ""):
        super().__init__(poses)
        self.intrinsics = dict(intrinsics or {})
        self.points = points
        self.source = str(source)
        self.kind = kind

    def subset(self, names: Iterable[str]) -> "GroundTruth":
        """Only the given images (e.g. the 19 templeRing images present out of the 47 the par file lists)."""
        keep = [n for n in names if n in self]
        return GroundTruth({n: self[n] for n in keep}, intrinsics={n: self.intrinsics[n] for n in keep
                                                                   if n in self.intrinsics},
                           points=self.points, source=self.source, kind=self.kind)


def load_ground_truth_for(path: Path | str, names: Iterable[str]) -> GroundTruth:
    """Ground truth restricted to `names` (the images of the run): pairs of images that are not in the set
    must not count as failures. InputError when fewer than two of the names are in the ground truth."""
    gt = load_ground_truth(path)
    sub = gt.subset(names)
    if len(sub) < 2:
        shown = ", ".join(list(gt)[:3])
        raise InputError(f"{path}: ground truth names ({shown}, ...) match {len(sub)} of the {len(names)} images")
    return sub


def load_ground_truth(path: Path | str) -> GroundTruth:
    """Read ground truth from any supported file or folder; InputError names the path when nothing fits."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: ground truth not found")
    if path.is_file() and path.name.endswith("_par.txt"):
        return load_middlebury_par(path)
    if path.is_dir():
        if (path / "images.bin").exists() or (path / "images.txt").exists():
            return load_colmap_model(path)
        if any(path.glob("*.camera")):
            return load_strecha_cameras(path)
        if any(path.glob("calibration_*.h5")):
            return load_imc_calibration(path)
        found = find_ground_truth(path)
        if found is not None and found != path:
            return load_ground_truth(found)
    raise InputError(f"{path}: not a ground-truth format mvrecon reads (COLMAP model folder, *_par.txt, "
                     "Strecha gt_dense_cameras/, IMC calibration/)")


def find_ground_truth(dataset_dir: Path | str) -> Path | None:
    """The ground truth of a data set folder (catalog scene or `../shared/data/<set>`), or None when it has none."""
    d = Path(dataset_dir)
    for candidate in (d / "gt" / "sparse", d / "gt" / "sparse" / "0", d / "colmap_ground_truth",
                      d / "gt_dense_cameras", d / "calibration"):
        if candidate.is_dir() and (any(candidate.glob("images.*")) or any(candidate.glob("*.camera"))
                                   or any(candidate.glob("calibration_*.h5"))):
            return candidate
    pars = sorted(d.glob("*_par.txt"))
    return pars[0] if pars else None


def load_colmap_model(path: Path | str) -> GroundTruth:
    """A COLMAP model (binary or text): poses of registered images, their K, and the model's 3D points."""
    rec = load_reconstruction(path)
    intrinsics = {im.name: np.asarray(im.camera.calibration_matrix()) for im in rec.images.values() if im.has_pose}
    points = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    return GroundTruth(poses(rec), intrinsics=intrinsics, points=points, source=path, kind="colmap")


def load_middlebury_par(path: Path | str) -> GroundTruth:
    """Middlebury multi-view `*_par.txt`: a count line, then `name k11..k33 r11..r33 t1 t2 t3` (P = K[R t])."""
    path = Path(path)
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    try:
        count = int(lines[0][0])
        rows = lines[1:1 + count]
        if len(rows) != count or any(len(r) != 22 for r in rows):
            raise ValueError("expected a count line and 22 fields per camera")
        out, intrinsics = {}, {}
        for r in rows:
            v = np.array(r[1:], dtype=float)
            intrinsics[r[0]] = v[:9].reshape(3, 3)
            out[r[0]] = (v[9:18].reshape(3, 3), v[18:21])
    except (ValueError, IndexError) as exc:
        raise InputError(f"{path}: not a Middlebury par file ({exc})") from None
    return GroundTruth(out, intrinsics=intrinsics, source=path, kind="middlebury")


def load_strecha_cameras(folder: Path | str) -> GroundTruth:
    """Strecha `<image>.camera` files: K (3 lines), distortion, R camera-to-world (3 lines), centre C, size."""
    folder = Path(folder)
    out, intrinsics = {}, {}
    for f in sorted(folder.glob("*.camera")):
        try:
            v = np.array(f.read_text().split(), dtype=float)
            K, R_wc, C = v[:9].reshape(3, 3), v[12:21].reshape(3, 3), v[21:24]
        except ValueError as exc:
            raise InputError(f"{f}: not a Strecha camera file ({exc})") from None
        if v.size < 24:
            raise InputError(f"{f}: not a Strecha camera file (expected at least 24 numbers, got {v.size})")
        name = f.name[: -len(".camera")]
        R = nearest_rotation(R_wc.T)  # the files round R to 6 decimals
        out[name], intrinsics[name] = (R, -R @ C), K
    return GroundTruth(out, intrinsics=intrinsics, source=folder, kind="strecha")


def load_imc_calibration(folder: Path | str) -> GroundTruth:
    """IMC `calibration_<stem>.h5` files (K, R, T); names get the extension of the image found next door."""
    folder = Path(folder)
    images = folder.parent / "images"
    out, intrinsics = {}, {}
    for f in sorted(folder.glob("calibration_*.h5")):
        data = read_small_hdf5(f)
        missing = {"K", "R", "T"} - set(data)
        if missing:
            raise InputError(f"{f}: IMC calibration lacks {', '.join(sorted(missing))}")
        stem = f.stem[len("calibration_"):]
        name = next((stem + s for s in IMAGE_SUFFIXES if (images / (stem + s)).exists()), stem + ".jpg")
        R = data["R"].reshape(3, 3)
        if "q" in data and not np.allclose(R, quat_to_rotmat(data["q"].ravel()), atol=1e-4):
            raise InputError(f"{f}: R and q disagree")
        out[name], intrinsics[name] = (R, data["T"].ravel().astype(float)), data["K"].reshape(3, 3)
    return GroundTruth(out, intrinsics=intrinsics, source=folder, kind="imc")


# --- a reader for small HDF5 files: superblock v0/v1, one root group of contiguous or compact numeric datasets ---

def read_small_hdf5(path: Path | str) -> dict[str, np.ndarray]:
    """Datasets in the root group of a small HDF5 file (what h5py writes for a few small arrays)."""
    path = Path(path)
    buf = path.read_bytes()
    try:
        if buf[:8] != b"\x89HDF\r\n\x1a\n" or buf[8] > 1:
            raise ValueError("not an HDF5 file with a version 0/1 superblock")
        if buf[13] != 8 or buf[14] != 8:
            raise ValueError("only 8-byte offsets and lengths are supported")
        root = 56 if buf[8] == 0 else 60  # the root group's symbol table entry
        _, _, cache_type = struct.unpack_from("<QQI", buf, root)
        if cache_type != 1:
            raise ValueError("root group has no cached symbol table")
        btree, heap = struct.unpack_from("<QQ", buf, root + 24)
        heap_data = _local_heap_data(buf, heap)
        out = {}
        for name_offset, header in _group_entries(buf, btree):
            name = buf[heap_data + name_offset: buf.index(b"\0", heap_data + name_offset)].decode()
            array = _dataset(buf, header)
            if array is not None:
                out[name] = array
        return out
    except (ValueError, struct.error, IndexError) as exc:
        raise InputError(f"{path}: cannot read this HDF5 file ({exc})") from None


def _local_heap_data(buf, address) -> int:
    if buf[address:address + 4] != b"HEAP":
        raise ValueError("bad local heap")
    return struct.unpack_from("<Q", buf, address + 24)[0]


def _group_entries(buf, address):
    """(name offset, object header address) of every entry under a v1 group B-tree node."""
    if buf[address:address + 4] != b"TREE":
        raise ValueError("bad group B-tree")
    level, used = buf[address + 5], struct.unpack_from("<H", buf, address + 6)[0]
    for k in range(used):
        child = struct.unpack_from("<Q", buf, address + 24 + 8 + 16 * k)[0]
        if level > 0:
            yield from _group_entries(buf, child)
            continue
        if buf[child:child + 4] != b"SNOD":
            raise ValueError("bad symbol table node")
        for e in range(struct.unpack_from("<H", buf, child + 6)[0]):
            name_offset, header = struct.unpack_from("<QQ", buf, child + 8 + 40 * e)
            yield name_offset, header


def _header_messages(buf, address):
    """(type, body offset, size) of the messages of a version 1 object header, following continuations."""
    if buf[address] != 1:
        raise ValueError("only version 1 object headers are supported")
    count, _, size = struct.unpack_from("<HII", buf, address + 2)
    blocks, seen = [(address + 16, size)], 0
    while blocks and seen < count:
        start, length = blocks.pop(0)
        pos = start
        while pos + 8 <= start + length and seen < count:
            mtype, msize = struct.unpack_from("<HH", buf, pos)
            seen += 1
            if mtype == 0x10:
                blocks.append(struct.unpack_from("<QQ", buf, pos + 8))
            else:
                yield mtype, pos + 8, msize
            pos += 8 + msize


def _dataset(buf, header) -> np.ndarray | None:
    shape = dtype = data = None
    for mtype, pos, _ in _header_messages(buf, header):
        if mtype == 0x01:  # dataspace
            version, rank = buf[pos], buf[pos + 1]
            first = pos + (8 if version == 1 else 4)
            shape = struct.unpack_from(f"<{rank}Q", buf, first) if rank else ()
        elif mtype == 0x03:  # datatype
            cls, size = buf[pos] & 0x0F, struct.unpack_from("<I", buf, pos + 4)[0]
            big_endian, signed = buf[pos + 1] & 1, buf[pos + 1] & 8
            if cls == 1:
                dtype = np.dtype(f"{'>' if big_endian else '<'}f{size}")
            elif cls == 0:
                dtype = np.dtype(f"{'>' if big_endian else '<'}{'i' if signed else 'u'}{size}")
        elif mtype == 0x08:  # data layout
            version, layout = buf[pos], buf[pos + 1]
            if version != 3:
                raise ValueError(f"data layout message version {version} is not supported")
            if layout == 0:
                n = struct.unpack_from("<H", buf, pos + 2)[0]
                data = (pos + 4, n)
            elif layout == 1:
                data = struct.unpack_from("<QQ", buf, pos + 2)
            else:
                raise ValueError("chunked datasets are not supported")
    if shape is None or dtype is None or data is None:
        return None  # a group or a non-numeric dataset: not ground truth
    count = int(np.prod(shape)) if shape else 1
    return np.frombuffer(buf, dtype=dtype, count=count, offset=int(data[0])).reshape(shape).astype(float)
