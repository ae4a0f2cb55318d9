"""Export a model for NeRF / Gaussian-splatting trainers: undistorted images and a PINHOLE COLMAP model.

The layout is the one nerfstudio (`ns-process-data` output, `colmap` data parser) and the Gaussian-splatting
reference code (`convert.py` output) read:

    DIR/images/<name>        undistorted images (distortion removed, same names, sub-folders kept)
    DIR/sparse/0/            cameras/images/points3D .bin with PINHOLE cameras matching those images

COLMAP's own undistorter does the resampling (`pycolmap.undistort_images`), so the result is exactly what
`colmap image_undistorter` gives; it writes `sparse/` flat, which is moved to `sparse/0/` here. COLMAP reads pixels
as stored, so images with an EXIF orientation (our cameras are upright) and 16-bit ones (trainers read 8 bits) are
given to it as upright 8-bit copies in DIR.partial/input/, the others as links.
"""

import logging
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import InputError
from ..eval.models import load_reconstruction
from .images import image_metadata, image_problem, read_image


def export_undistorted(model_dir, image_dir, out_dir, *, max_image_size: int = -1,
                       text: bool = False) -> Path:
    """Undistort the images of the model in `model_dir` into `out_dir`; returns out_dir/sparse/0."""
    import pycolmap

    model_dir, image_dir, out_dir = Path(model_dir), Path(image_dir), Path(out_dir)
    rec = load_reconstruction(model_dir)
    names = [im.name for im in rec.images.values()]
    if not image_dir.is_dir():
        raise InputError(f"{image_dir}: image folder not found (pass --image-dir)")
    missing = [n for n in names if not (image_dir / n).is_file()]
    if missing:  # COLMAP's undistorter would log each one and write an export without them
        raise InputError(f"{image_dir}: {len(missing)} of the model's {len(names)} images are not here (first: "
                         f"{missing[0]}); pass --image-dir")
    metas = {}
    for im in rec.images.values():
        path, cam = image_dir / im.name, rec.cameras[im.camera_id]
        problem = image_problem(path)  # COLMAP would write a cut-off image as a mostly black one, and carry on
        if problem:
            raise InputError(f"{path}: {problem}")
        m = metas[im.name] = image_metadata(path)
        if (m.width, m.height) != (cam.width, cam.height):  # pycolmap would abort the whole process (SIGABRT)
            turned = f" upright (EXIF orientation {m.orientation})" if m.orientation != 1 else ""
            raise InputError(f"{path}: is {m.width}x{m.height}{turned} but its camera {cam.camera_id} in the model is "
                             f"{cam.width}x{cam.height}: not the image the model was made from; pass --image-dir")
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
    out_dir.mkdir(parents=True)
    try:
        source = _upright_8bit(image_dir, metas, out_dir / "input")
    except InputError:
        shutil.rmtree(out_dir)  # a failed export leaves nothing behind
        raise
    options = pycolmap.UndistortCameraOptions(max_image_size=int(max_image_size))
    # COLMAP logs a line per image on stderr (glog); those show only with -vv, like our own debug lines
    saved = pycolmap.logging.minloglevel
    if not logging.getLogger("mvrecon").isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = pycolmap.logging.WARNING
    try:
        pycolmap.undistort_images(str(out_dir), str(model_dir), str(source), output_type="COLMAP",
                                  undistort_options=options)
    finally:
        pycolmap.logging.minloglevel = saved
    flat = out_dir / "sparse"
    target = flat / "0"
    target.mkdir(parents=True, exist_ok=True)
    for f in list(flat.iterdir()):
        if f.is_file():
            shutil.move(str(f), str(target / f.name))
    for extra in ("input", "stereo", "run-colmap-geometric.sh", "run-colmap-photometric.sh"):
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
    return final / "sparse" / "0"


def _upright_8bit(image_dir: Path, metas: dict, folder: Path) -> Path:
    """`image_dir`, or `folder` holding upright 8-bit copies (no EXIF) of the images that are rotated by EXIF or
    16-bit, and links to the others. COLMAP kept 16 bits, which 8-bit readers divide by 256 (14-bit data came out
    dark); like our feature reader we stretch by the maximum, but one for all images, so views keep their relative
    brightness."""
    import cv2

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
        image = read_image(src)  # upright, as the model's cameras
        if image.dtype != np.uint8:
            image = cv2.convertScaleAbs(image, alpha=255.0 / max(top, 1))
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        ok, data = cv2.imencode(dst.suffix, image, [cv2.IMWRITE_JPEG_QUALITY, 100, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                                    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
        if not ok:
            raise InputError(f"{src}: cannot write an upright copy to {dst}")
        data.tofile(dst)
    return folder


def _more_than_8_bits(path: Path) -> bool:
    """Whether `read_image` gives uint16 for this file (16/32-bit or float samples), from the header only."""
    with Image.open(path) as im:
        raw = str(im.tile[0].args) if im.tile else ""
        return im.mode.startswith(("I", "F")) or ";16" in raw or ";32" in raw
