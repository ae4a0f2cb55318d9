"""Export a model for NeRF / Gaussian-splatting trainers: undistorted images and a PINHOLE COLMAP model.

The layout is the one nerfstudio (`ns-process-data` output, `colmap` data parser) and the Gaussian-splatting
reference code (`convert.py` output) read:

    DIR/images/<name>        undistorted images (distortion removed, same names, sub-folders kept)
    DIR/sparse/0/            cameras/images/points3D .bin with PINHOLE cameras matching those images

COLMAP's own undistorter does the resampling (`pycolmap.undistort_images`), so the result is exactly what
`colmap image_undistorter` gives; it writes `sparse/` flat, which is moved to `sparse/0/` here. COLMAP reads pixels
as stored, so images with an EXIF orientation and 16-bit ones (trainers read 8 bits) are given to it as 8-bit
copies without the tag in DIR.partial/input/, the others as links. The copies are in the frame the model was made
in: upright when mvrecon extracted the image's features (its reader applies the orientation), as stored when
COLMAP did (a COLMAP database mapped with `mvrecon map -o`, or a bare COLMAP model); see `_stored_frame`.
"""

import logging
import shutil
import sqlite3
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image

from ..errors import InputError
from .colmap_model import load_reconstruction, model_bytes
from .files import require_room, some_names
from .images import TRANSPOSED, image_metadata, image_problem, read_image
from .sqlite import connect_readonly


def export_undistorted(model_dir: Path | str, image_dir: Path | str, out_dir: Path | str, *,
                       max_image_size: int = -1, text: bool = False,
                       database: Path | str | None = None) -> Path:
    """Undistort the images of the model in `model_dir` into `out_dir`; returns out_dir/sparse/0. `database`:
    the database the model was mapped from, which tells the frame of images with an EXIF orientation."""
    model_dir, image_dir, out_dir = Path(model_dir), Path(image_dir), Path(out_dir)
    rec = load_reconstruction(model_dir)
    lenses = sorted({cam.model.name for cam in rec.cameras.values()})
    names = [im.name for im in rec.images.values()]
    if not image_dir.is_dir():
        raise InputError(f"{image_dir}: image folder not found (pass --image-dir)")
    missing = [n for n in names if not (image_dir / n).is_file()]
    if missing:  # COLMAP's undistorter would log each one and write an export without them
        raise InputError(f"{image_dir}: {len(missing)} of the model's {len(names)} images are not here (first: "
                         f"{missing[0]}); pass --image-dir")
    metas = {}
    for im in rec.images.values():
        path = image_dir / im.name
        problem = image_problem(path)  # COLMAP would write a cut-off image as a mostly black one, and carry on
        if problem:
            raise InputError(f"{path}: {problem}")
        metas[im.name] = image_metadata(path)
    stored = _stored_frame(rec, image_dir, metas, database, model_dir)
    out = out_dir.resolve()
    for source in (model_dir, image_dir):  # replacing the output must never delete what is being exported
        if out == source.resolve() or out in source.resolve().parents:
            raise InputError(f"{out_dir}: holds {source}, which is being exported; choose another output folder")
    if out_dir.exists() and any(out_dir.iterdir()):
        # only an earlier export (images/ and sparse/0/, nothing else) is replaced
        if {p.name for p in out_dir.iterdir()} - {"images", "sparse"} or not (out_dir / "sparse" / "0").is_dir():
            raise InputError(f"{out_dir}: exists and is not an export folder; choose an empty or new folder")
    # written next to it first and moved into place when complete: an interrupted export leaves only the
    # .partial folder, which the next run clears, never a half export taken for a whole one
    final, out_dir = out_dir, out_dir.with_name(out_dir.name + ".partial")
    if out_dir.exists():
        shutil.rmtree(out_dir)
    # COLMAP's undistorter aborts the process when an image cannot be written; its images can outgrow their
    # sources (JPEG at a higher quality, a larger size), and EXIF-turned or 16-bit ones are copied first
    require_room(final, 3 * sum((image_dir / n).stat().st_size for n in names) + model_bytes(rec))
    out_dir.mkdir(parents=True)
    try:
        source = _8bit_in_model_frame(image_dir, metas, stored, out_dir / "input")
    except InputError:
        shutil.rmtree(out_dir)  # a failed export leaves nothing behind
        raise
    options = pycolmap.UndistortCameraOptions(max_image_size=int(max_image_size))
    # COLMAP logs a line per image on stderr (glog); those show only with -vv, like our own debug lines
    saved = pycolmap.logging.minloglevel
    if not logging.getLogger("mvrecon").isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = pycolmap.logging.WARNING
    try:
        pycolmap.undistort_images(str(out_dir), str(_resampled_fisheyes(rec, model_dir, out_dir / "model")),
                                  str(source), output_type="COLMAP", undistort_options=options)
    finally:
        pycolmap.logging.minloglevel = saved
    flat = out_dir / "sparse"
    target = flat / "0"
    target.mkdir(parents=True, exist_ok=True)
    for f in list(flat.iterdir()):
        if f.is_file():
            shutil.move(str(f), str(target / f.name))
    for extra in ("input", "model", "stereo", "run-colmap-geometric.sh", "run-colmap-photometric.sh"):
        p = out_dir / extra
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    rec = pycolmap.Reconstruction(str(target))
    kept = [cam for cam in rec.cameras.values() if cam.model != pycolmap.CameraModelId.PINHOLE]
    for cam in kept:
        # COLMAP copies the images of a camera without distortion (SIMPLE_PINHOLE, or k = 0) and keeps its model;
        # the trainers read PINHOLE only, and for such a camera PINHOLE is the same projection
        if not cam.is_undistorted():
            raise InputError(f"{model_dir}: camera {cam.camera_id} ({cam.model.name}) was not undistorted")
        cam.model, cam.params = pycolmap.CameraModelId.PINHOLE, [cam.focal_length_x, cam.focal_length_y,
                                                                 cam.principal_point_x, cam.principal_point_y]
    if kept:
        rec.write(str(target))
    if text:
        rec.write_text(str(target))
    if final.exists():
        shutil.rmtree(final)  # the earlier export checked above
    out_dir.replace(final)
    outside, total = observations_outside(rec)
    if outside > OUTSIDE_WARNING * total:
        logging.getLogger(__name__).warning(
            "%s: %.0f%% of the model's observations (%d of %d) fall outside the undistorted images: COLMAP's "
            "undistorter keeps of the %s view only what a PINHOLE image can hold", final, 100 * outside / total,
            outside, total, "/".join(lenses))
    return final / "sparse" / "0"


OUTSIDE_WARNING = 0.01  # share of observations outside the undistorted images that is worth a warning


def observations_outside(rec: pycolmap.Reconstruction) -> tuple[int, int]:
    """(observations of a 3D point outside their undistorted image, all such observations) of an exported model.
    COLMAP's undistorter keeps every observation but crops each image to what a PINHOLE camera can hold: a lens
    wider than that (past 180 deg it cannot hold it all) lost half of a wide fisheye's observations silently."""
    outside = total = 0
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        xy = np.array([p.xy for p in im.points2D if p.has_point3D()], dtype=float).reshape(-1, 2)
        inside = np.isfinite(xy).all(axis=1) & (xy >= 0).all(axis=1) & (xy[:, 0] <= cam.width) \
            & (xy[:, 1] <= cam.height)
        outside += int((~inside).sum())
        total += len(xy)
    return outside, total


FISHEYE_NUDGE = 1e-7  # k1 of a fisheye without distortion terms for the export: over COLMAP's 1e-8, 1e-4 px


def _resampled_fisheyes(rec, model_dir: Path, folder: Path) -> Path:
    """`model_dir`, or a copy in `folder` whose fisheye cameras without distortion terms have k1 = FISHEYE_NUDGE.
    COLMAP takes a camera whose extra parameters are all zero for undistorted, a fisheye one too, and copies its
    images, which were then exported as PINHOLE with the fisheye's focal: an equidistant view labelled perspective.
    The nudge moves no pixel by more than 1e-4 px (k1 theta^3 f at 90 deg, f = 300 px) and makes COLMAP
    resample."""
    flat = [cam for cam in rec.cameras.values()
            if cam.is_perspective_fisheye() and cam.extra_params_idxs() and cam.is_undistorted()]
    if not flat:
        return model_dir
    for cam in flat:
        params = list(cam.params)
        params[cam.extra_params_idxs()[0]] = FISHEYE_NUDGE
        cam.params = params
    folder.mkdir()
    rec.write(str(folder))
    return folder


def _stored_frame(rec, image_dir: Path, metas: dict, database, model_dir: Path) -> set[str]:
    """The model's images in the stored pixel frame (the others are upright), each checked against its camera's
    size first: pycolmap aborts the whole process (SIGABRT) on an image of another size.

    Only images with an EXIF orientation can be either. The database the model was mapped from tells, image by
    image (`database_frames`); where it does not (a bare model folder), the model does: a camera of the image's
    stored size is COLMAP's frame, one of its upright size mvrecon's. When both sizes are the same (a 180 deg
    turn, a mirror, a square image) the image is in the frame the model's other EXIF-rotated images agree on;
    with none to go by it is taken as stored, as COLMAP reads pixels, and a warning names it."""
    log = logging.getLogger(__name__)
    cameras = {im.name: rec.cameras[im.camera_id] for im in rec.images.values()}
    turned = {n: m for n, m in metas.items() if m.orientation != 1}
    told = database_frames(database, turned) if turned else {}  # name -> True when as stored
    by_size = {n: frame for n, m in turned.items() if n not in told
               and (frame := _frame_from_size(m, cameras[n])) is not None}
    untold = sorted(n for n in turned if n not in told and n not in by_size)
    agreed = set(told.values()) | set(by_size.values())
    guess = next(iter(agreed)) if len(agreed) == 1 else True
    frames = {**told, **by_size, **dict.fromkeys(untold, guess)}
    _check_sizes(image_dir, metas, cameras, frames, told)
    if any(told.values()):
        log.info("%s: COLMAP extracted the features of %d of the %d image(s) with an EXIF orientation: exported as "
                 "stored (not turned), without the tag, as the model sees them", database, sum(told.values()),
                 len(turned))
    if any(by_size.values()):
        log.info("%s: the cameras of %d of the %d image(s) with an EXIF orientation have their stored size "
                 "(COLMAP's frame: it ignores the tag): exported as stored, without the tag", model_dir,
                 sum(by_size.values()), len(turned))
    if untold and len(agreed) == 1:
        log.info("%s: %s (the same size upright and as stored) taken %s, as the model's other image(s) with an "
                 "EXIF orientation are", model_dir, some_names(untold, 5), "as stored" if guess else "upright")
    elif untold:
        log.warning("%s: cannot tell the frame of %s in the model (no database says, and the size is the same "
                    "upright and as stored): exported as stored, as COLMAP reads images", model_dir,
                    some_names(untold, 5))
    return {n for n, stored in frames.items() if stored}


def _check_sizes(image_dir: Path, metas: dict, cameras: dict, frames: dict, told: dict) -> None:
    """Refuse an image whose size in its frame (`frames`: True when as stored) is not its camera's."""
    for name, m in metas.items():
        path, cam, stored = image_dir / name, cameras[name], frames.get(name, False)
        size = (m.height, m.width) if stored and m.orientation in TRANSPOSED else (m.width, m.height)
        if size == (cam.width, cam.height):
            continue
        what = f"{size[0]}x{size[1]}"
        if name in told:
            what += (f" as stored (EXIF orientation {m.orientation} not applied)" if stored else
                     f" upright (EXIF orientation {m.orientation})")
        elif m.orientation in TRANSPOSED:  # the camera has neither of the image's sizes
            what = f"{m.width}x{m.height} upright (EXIF orientation {m.orientation}), {m.height}x{m.width} as stored"
        elif m.orientation != 1:
            what += f" (EXIF orientation {m.orientation})"
        raise InputError(f"{path}: is {what} but its camera {cam.camera_id} in the model is {cam.width}x{cam.height}: "
                         f"not the image the model was made from; pass --image-dir")


def _frame_from_size(meta, cam) -> bool | None:
    """True when the camera has the image's stored size and not its upright one, False for the reverse, None when
    the size cannot tell (the two are the same: a 180 deg turn, a mirror, a square image) or is neither."""
    upright = (meta.width, meta.height)
    stored = upright[::-1] if meta.orientation in TRANSPOSED else upright
    size = (cam.width, cam.height)
    if upright == stored or size not in (upright, stored):
        return None
    return size == stored


def database_frames(database: Path | str | None, names: Iterable[str]) -> dict[str, bool]:
    """Which frame the database the model was mapped from says each of `names` is in: True (stored pixel frame)
    where COLMAP extracted its features, False (upright) where mvrecon did; names it has no keypoints of are left
    out (as all are without a database: a bare model folder).

    Told by the keypoints table: COLMAP writes 6 columns per keypoint (x, y and the affine shape a11 a12 a21 a22),
    mvrecon 4 (x, y, scale, orientation; `database.write_features`). This travels with the features themselves,
    image by image: it still holds when a COLMAP database was copied into a workspace of ours, or the two were
    mixed, where the workspace's record (our features stage) or images.json would speak for the folder, and
    report.json is written by `map` for either. A COLMAP from before its affine keypoints (about 2018) wrote 4
    columns too: its images are taken as mvrecon's, upright."""
    if database is None or not Path(database).is_file():
        return {}
    try:
        with connect_readonly(database) as con:
            rows = con.execute("SELECT images.name, keypoints.cols FROM images JOIN keypoints "
                               "ON images.image_id = keypoints.image_id").fetchall()
    except sqlite3.Error as exc:
        raise InputError(f"{database}: cannot read it to tell which frame the model's EXIF-rotated images are in "
                         f"({exc})") from None
    wanted = set(names)
    return {name: cols == 6 for name, cols in rows if name in wanted}


def _8bit_in_model_frame(image_dir: Path, metas: dict, stored: set, folder: Path) -> Path:
    """`image_dir`, or `folder` holding 8-bit copies without EXIF of the images that are rotated by EXIF or 16-bit,
    and links to the others. A copy is upright, as mvrecon's cameras are, or as stored for the images in `stored`
    (the model's frame; without the tag, viewers and trainers see what the model describes). COLMAP kept 16 bits,
    which 8-bit readers divide by 256 (14-bit data came out dark); like our feature reader we stretch by the
    maximum, but one for all images, so views keep their relative brightness."""
    deep = [n for n in metas if _more_than_8_bits(image_dir / n)]
    copies = set(deep) | {n for n, m in metas.items() if m.orientation != 1}
    if not copies:
        return image_dir
    top = max((int(read_image(image_dir / n).max()) for n in deep), default=255)
    for name in metas:
        src, dst = image_dir / name, folder / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        if name not in copies:
            try:
                dst.symlink_to(src.resolve())
            except OSError:  # a file system without links (FAT, some Windows set-ups)
                shutil.copyfile(src, dst)
            continue
        image = read_image(src, upright=name not in stored)  # in the frame of the model's cameras
        if image.dtype != np.uint8:
            image = cv2.convertScaleAbs(image, alpha=255.0 / max(top, 1))
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        ok, data = cv2.imencode(dst.suffix, image, [cv2.IMWRITE_JPEG_QUALITY, 100, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                                    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
        if not ok:
            raise InputError(f"{src}: cannot write an 8-bit copy to {dst}")
        data.tofile(dst)
    return folder


def _more_than_8_bits(path: Path) -> bool:
    """Whether `read_image` gives uint16 for this file (16/32-bit or float samples), from the header only."""
    with Image.open(path) as im:
        raw = str(im.tile[0].args) if im.tile else ""
        return im.mode.startswith(("I", "F")) or ";16" in raw or ";32" in raw
