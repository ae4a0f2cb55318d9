"""Images in: find them in a folder, decode them (8/16 bit, grey/RGB/RGBA) upright, and read their EXIF.

The two functions other modules need:

- `list_images(folder) -> (names, skipped)`: every JPEG/PNG/TIFF/BMP/PNM under `folder` (recursively), the
  formats COLMAP reads too, as POSIX paths relative to it, sorted. Other files are listed in ONE warning (photo
  formats we do not decode, HEIC or WebP, in one of their own that says to convert them); image files whose header
  cannot be read, or that are cut off (`image_problem`: a file ending early), are warned about one by one.
  Both land in `skipped` (name -> reason). A missing path, a file instead of a folder, or a folder with no
  readable image raises `InputError`.
- `read_image(path) -> np.ndarray`: HxW (grey) or HxWx3 (RGB) in the file's own depth (uint8 or uint16), with the
  EXIF orientation applied (`upright=False`: as stored) and any alpha channel dropped. A file that cannot be
  decoded raises `InputError`.

Pixels are decoded by OpenCV (which keeps 16-bit colour; Pillow does not) and EXIF is read by Pillow (OpenCV only
applies orientation when it also converts depth). `image_metadata` gives the upright size and the camera EXIF
without decoding pixels, which is all the camera grouping needs.
"""

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
from PIL import ExifTags, Image

from ..errors import InputError
from .files import printable_name, some_names

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".pbm", ".pnm")
FORMATS = "JPEG, PNG, TIFF, BMP or PNM"
# photo formats a user may hold that we do not decode (pycolmap's reader here skips WebP and JPEG 2000 too):
# named in the warning, so that the fix (convert them) is in the message rather than "not an image"
_UNREAD_PHOTOS = {".heic": "HEIC", ".heif": "HEIF", ".avif": "AVIF", ".webp": "WebP", ".jp2": "JPEG 2000",
                  ".gif": "GIF", ".dng": "raw", ".cr2": "raw", ".cr3": "raw", ".nef": "raw", ".arw": "raw",
                  ".raf": "raw", ".orf": "raw", ".rw2": "raw", ".exr": "OpenEXR"}
_UNCOMPRESSED = ("BMP", "DIB", "PPM")  # Pillow's names; decoding them is a copy, so it checks their length
_ORIENTATION = 0x0112
# A photo is the user's own, not an upload: Pillow's "decompression bomb" refusal of images over 179 megapixels
# (stitched panoramas, aerial mosaics, 200 MP sensors; COLMAP reads them) is replaced by OpenCV's decoding limit,
# which `image_problem` names; SIFT then works on them shrunk to --max-image-size.
Image.MAX_IMAGE_PIXELS = None
MAX_PIXELS = 1 << 30  # OpenCV's CV_IO_MAX_IMAGE_PIXELS: imdecode refuses larger images
# Orientations 5-8 swap width and height.
TRANSPOSED = {5, 6, 7, 8}


@dataclass(frozen=True, kw_only=True)
class ImageMeta:
    """What the camera grouping needs to know about an image, read from its header only."""

    width: int  # upright (after EXIF orientation)
    height: int
    orientation: int = 1
    make: str = ""
    model: str = ""
    focal_mm: float | None = None  # EXIF FocalLength
    focal_35mm: float | None = None  # EXIF FocalLengthIn35mmFilm
    focal_px_from_sensor: float | None = None  # FocalLength * FocalPlaneXResolution, in this image's pixels


# a workspace, an export, a scene, a study (an older one: study.json), degraded copies (their folders are image
# folders of their own)
OUTPUT_MARKS = ("database.db", "sparse", "scene.json", ".stages/study.json", "study.json",
                ".mvrecon-degrade.json")


def visible_files(folder: Path | str) -> list[str]:
    """Every file under `folder` (POSIX names relative to it, sorted as paths), hidden ones (a dot in the path)
    left out, and so are sub-folders holding a run's outputs (one of OUTPUT_MARKS): an output or export written
    inside the image folder must not come back as input images on the next run."""
    folder = Path(folder)
    names = []
    # (device, inode) -> the folder's first path: links are followed, but each folder is read once
    seen = {_identity(folder): folder}
    for root, dirs, files in os.walk(folder, followlinks=True):
        here = Path(root)
        skip = [d for d in dirs if not d.startswith(".") and any((here / d / m).exists() for m in OUTPUT_MARKS)]
        for d in skip:
            log.info("skipping %s: it holds the outputs of a run", here / d)
        kept = []
        # real folders before links, so that a folder is named by its own path where it has one
        for d in sorted(dirs, key=lambda d: ((here / d).is_symlink(), d)):
            if d.startswith(".") or d in skip:
                continue
            first = seen.setdefault(_identity(here / d), here / d)
            if first != here / d:  # a link back up the tree (os.walk would loop until the path is too long)
                log.warning("skipping %s: the same folder as %s, which is read already (a link)", here / d, first)
                continue
            kept.append(d)
        dirs[:] = kept
        for f in files:
            path = here / f
            if f.startswith("."):
                continue
            if path.is_file():
                names.append(path.relative_to(folder).as_posix())
            elif path.suffix.lower() in IMAGE_EXTENSIONS:  # named as an image, yet nothing to read: say why
                log.warning("skipping %s: %s", path, f"a link to {os.readlink(path)}, which does not exist"
                            if path.is_symlink() else "not a regular file (a pipe, socket or device)")
    return sorted(names, key=lambda n: PurePosixPath(n).parts)


def _identity(path: Path):
    try:
        st = path.stat()
        return st.st_dev, st.st_ino
    except OSError:  # a broken link: its own path stands for it
        return str(path)


def list_images(folder: Path | str) -> tuple[list[str], dict[str, str]]:
    """Image names (POSIX, relative to `folder`, sorted) and the skipped files (name -> reason)."""
    folder = Path(folder)
    if not folder.exists():
        raise InputError(f"{folder}: no such folder")
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder (give the folder that holds the images)")
    names, non_images, skipped, photos = [], [], {}, {}
    for name in visible_files(folder):
        path = folder / name
        suffix = path.suffix.lower()
        shown = printable_name(name)
        if suffix not in IMAGE_EXTENSIONS:
            kind = _UNREAD_PHOTOS.get(suffix)
            if kind:
                photos.setdefault(kind, []).append(shown)
                skipped[shown] = f"a {kind} image: not read; convert it to {FORMATS}"
            else:
                non_images.append(shown)
                skipped[shown] = f"not a {FORMATS} file"
            continue
        if shown != name:  # pycolmap cannot take the name (a Latin-1 name from an old archive, say)
            log.warning("skipping %s: its name is not UTF-8 text, which COLMAP's database and models store; "
                        "rename it", folder / shown)
            skipped[shown] = "name not UTF-8 text; rename it"
            continue
        reason = image_problem(path)
        if reason:
            log.warning("skipping %s: %s", path, reason)
            skipped[name] = reason
            continue
        names.append(name)
    if non_images:
        log.warning("skipping %d non-image file(s) in %s: %s", len(non_images), folder, some_names(non_images, 10))
    for kind, found in photos.items():
        log.warning("skipping %d %s image(s) in %s (%s): mvrecon does not read them; convert them to %s",
                    len(found), kind, folder, some_names(found), FORMATS)
    if not names:
        advice = f"; convert the {' and '.join(photos)} images to {FORMATS}" if photos else ""
        raise InputError(f"{folder}: no readable {FORMATS} images found"
                         + (f" ({len(skipped)} file(s) skipped{advice})" if skipped else ""))
    return names, skipped


def header_exif(im: Image.Image) -> Image.Exif:
    """The EXIF of an open image without decoding its pixels. Pillow's PNG getexif() decodes the whole image
    when the EXIF chunk is not ahead of the pixel data (three decodes per image, 0.27 s serial on templeRing);
    camera EXIF after a PNG's pixel data is rare, and such a PNG is read as having none."""
    if im.format == "PNG" and "exif" not in im.info:
        return Image.Exif()
    return im.getexif()


def image_problem(path: Path) -> str | None:
    """Why a file cannot be used as an image (a cut-off PNG or JPEG, a broken header), or None; read without
    decoding the pixels."""
    try:
        im = Image.open(path)
    except Exception as exc:  # Pillow raises many types for broken files; the message is what the user needs
        return f"cannot read image header ({type(exc).__name__}: {exc})"
    with im:
        w, h = im.size
        jpeg = im.format in ("JPEG", "MPO")  # MPO: Pillow's name for a JPEG followed by more JPEGs
        try:
            if im.format == "PNG":
                im.verify()  # reads every chunk to the end and checks its CRC, without inflating the pixels
            elif im.format in _UNCOMPRESSED:
                im.load()  # raises when the file ends before its last row
            else:
                im.getexif()  # walks the file's metadata blocks: catches most truncated files without decoding
        except Exception as exc:  # the header was read: what follows it is missing or damaged
            return f"cut off or corrupt after its header ({type(exc).__name__}: {exc})"
    if w <= 0 or h <= 0:
        return f"empty image ({w}x{h})"
    if w * h > MAX_PIXELS:
        return (f"too large to decode ({w}x{h}, {w * h / 1e6:.0f} megapixels; the limit is "
                f"{MAX_PIXELS / 1e6:.0f}): shrink it first")
    if jpeg:
        try:
            return _jpeg_problem(Path(path).read_bytes())
        except OSError as exc:
            return f"cannot read file ({exc.strerror or exc})"
    return None


# In entropy-coded data a 0xFF byte is followed by 0x00 (a stuffed FF) or RST0-7 (D0-D7); any other code is the
# marker that ends the scan; outside scans FF + any code but 00 is a marker. FF fill bytes may come before a
# marker: FF followed by FF is not a match, so the last FF of the run is found. (A leading `\xff+` would cost 20x:
# it loses the regex engine's fast search for the literal first byte, 8 ms instead of 0.4 on a 1.3 MB JPEG.)
_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
_NEXT_MARKER = re.compile(rb"\xff[^\x00\xff]")
_NO_LENGTH = {0x01, *range(0xD0, 0xD8)}  # TEM and RSTn stand alone; SOI/EOI are handled apart
_SOS, _EOI = 0xDA, 0xD9


def _jpeg_problem(data: bytes) -> str | None:
    """Why a JPEG's bytes end before its end-of-image marker (an interrupted copy), or None. Walks the marker
    segments from SOI by their lengths (an EXIF thumbnail's own SOI/EOI inside APP1 is skipped whole) and scans
    each scan's entropy-coded data for the marker that ends it (a regex, at C speed: 0.4 ms for 6 MP), through
    every progressive scan, up to EOI; what follows EOI (a Motion Photo's video, MPO's other pictures) is not
    read. Stray bytes between segments are skipped as libjpeg skips them; what is reported is a missing end,
    which libjpeg decodes without an error (its missing part grey), and a segment length below 2."""
    truncated = "truncated JPEG: the file ends before its end-of-image marker"
    if data[:2] != b"\xff\xd8":
        return "not a JPEG: no start-of-image marker"
    i, n = 2, len(data)
    while True:
        m = _NEXT_MARKER.search(data, i)  # at i unless stray bytes come first
        if m is None:
            return truncated
        code, i = data[m.end() - 1], m.end()  # i: just after the marker code
        if code == _EOI:
            return None
        if code in _NO_LENGTH or code == 0xD8:
            continue
        if i + 2 > n:
            return truncated
        length = int.from_bytes(data[i:i + 2], "big")
        if length < 2:
            return f"corrupt JPEG: marker FF{code:02X} has a length of {length}"
        i += length
        if i > n:
            return truncated
        if code == _SOS:
            m = _SCAN_END.search(data, i)
            if m is None:
                return truncated
            i = m.start()


def image_metadata(path: Path | str) -> ImageMeta:
    """Upright size and camera EXIF (make, model, focal length in mm and 35 mm equivalent), without decoding."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            w, h = im.size
            exif = header_exif(im)
    except Exception as exc:
        raise InputError(f"{path}: cannot read image header ({exc})") from None
    orientation = int(exif.get(_ORIENTATION, 1) or 1)
    if orientation in TRANSPOSED:
        w, h = h, w
    sub = exif.get_ifd(ExifTags.IFD.Exif) if exif else {}

    def number(tag):
        value = sub.get(tag, exif.get(tag))
        try:
            value = float(value)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
        return value if np.isfinite(value) and value > 0 else None

    def text(tag):
        value = exif.get(tag)
        return str(value).strip("\x00 ").strip() if value else ""

    focal_mm = number(ExifTags.Base.FocalLength)
    return ImageMeta(width=w, height=h, orientation=orientation, make=text(ExifTags.Base.Make),
                     model=text(ExifTags.Base.Model), focal_mm=focal_mm,
                     focal_35mm=number(ExifTags.Base.FocalLengthIn35mmFilm),
                     focal_px_from_sensor=_focal_from_sensor(focal_mm, sub, exif, w if orientation not in
                                                             TRANSPOSED else h))


# EXIF FocalPlaneResolutionUnit: 2 = inch, 3 = cm, 4 = mm, 5 = micrometre.
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


def _focal_from_sensor(focal_mm, sub, exif, stored_width) -> float | None:
    """Focal length in pixels from the sensor's pixel density (the 'sensor width' EXIF carries), scaled from the
    sensor's full width (PixelXDimension) to the stored width in case the image was resized after capture."""
    try:
        xres = float(sub.get(ExifTags.Base.FocalPlaneXResolution, 0) or 0)
        unit = _UNIT_MM.get(int(sub.get(ExifTags.Base.FocalPlaneResolutionUnit, 2) or 2))
        full_width = float(sub.get(ExifTags.Base.ExifImageWidth, 0)
                           or exif.get(ExifTags.Base.ExifImageWidth, 0) or stored_width)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    if not focal_mm or xres <= 0 or not unit or full_width <= 0:
        return None
    return focal_mm * xres / unit * stored_width / full_width


def read_image(path: Path | str, *, upright: bool = True) -> np.ndarray:
    """Decode an image upright: HxW grey or HxWx3 RGB, uint8 or uint16 as stored; alpha is dropped. With
    `upright=False` the EXIF orientation is not applied: the pixels as stored, the frame COLMAP works in."""
    return _decode(Path(path), 1, upright)


def read_image_for_detection(path: Path | str, detection_size: int) -> tuple[np.ndarray, int]:
    """`read_image(path)`, or for a large JPEG the same picture decoded at 1/2, 1/4 or 1/8 of its size, and
    that factor: (image, 1) or (image, r) as `decoding_for_detection` chooses r."""
    path = Path(path)
    _, _, factor, grey = decoding_for_detection(path, detection_size)
    return _decode(path, factor, True, grey=grey), factor


def decoding_for_detection(path: Path | str, detection_size: int) -> tuple[int, int, int, bool]:
    """(width, height, r, grey) of an image as stored (its header; (0, 0, 1, False) if unreadable), and the
    fraction 1/r of its size to decode it at for a detector that shrinks it to `detection_size` pixels on its
    long side. libjpeg shrinks a JPEG in its inverse DCT at a fraction of the memory and time of a whole
    decode (a 12000 x 9000 photo: 81 MB instead of 324 MB at 1/2; castle's 2832 x 2128 photos decode in 71 ms
    at 1/2 against 190 ms whole). r is the largest of 2, 4, 8 that keeps the long side at least
    `detection_size` pixels, so that the detector still shrinks the picture, and that divides both sides, so
    that pixel k of the reduced picture covers pixels r*k .. r*k+r-1 exactly and coordinates scale by r;
    otherwise 1 (and always for other formats)."""
    try:
        with Image.open(path) as im:
            (w, h), jpeg, grey = im.size, im.format in ("JPEG", "MPO"), im.mode == "L"
    except Exception:  # noqa: BLE001 - reading the pixels names the problem
        return 0, 0, 1, False
    if jpeg:
        for r in (8, 4, 2):
            if max(w, h) // r >= detection_size and w % r == 0 and h % r == 0:
                return w, h, r, grey
    return w, h, 1, grey and jpeg


# cv2.imdecode flags for a JPEG at 1/r of its size, colour or grey (EXIF orientation is applied by _decode)
_REDUCED = {(2, False): "IMREAD_REDUCED_COLOR_2", (4, False): "IMREAD_REDUCED_COLOR_4",
            (8, False): "IMREAD_REDUCED_COLOR_8", (2, True): "IMREAD_REDUCED_GRAYSCALE_2",
            (4, True): "IMREAD_REDUCED_GRAYSCALE_4", (8, True): "IMREAD_REDUCED_GRAYSCALE_8"}


def _decode(path: Path, factor: int, upright: bool, grey: bool = False) -> np.ndarray:
    """The pixels of `path` (at 1/factor of its size: a JPEG only) as read_image gives them."""
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read file ({exc.strerror or exc})") from None
    # A failed decode is reported below, by file name; OpenCV's own log lines would only repeat it.
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    flags = cv2.IMREAD_UNCHANGED if factor == 1 else \
        getattr(cv2, _REDUCED[factor, grey]) | cv2.IMREAD_IGNORE_ORIENTATION
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None or image.size == 0:
        raise InputError(f"{path}: cannot decode image (corrupt, truncated or unsupported)")
    if image.dtype not in (np.uint8, np.uint16):
        if np.issubdtype(image.dtype, np.floating):
            finite = image[np.isfinite(image)]
            top = float(finite.max()) if finite.size else 1.0
            scaled = np.nan_to_num(image) / (top if top > 0 else 1.0) * 65535
            image = np.clip(scaled, 0, 65535).astype(np.uint16)
        else:
            image = np.clip(image, 0, 65535).astype(np.uint16)
    if image.ndim == 3:
        channels = image.shape[2]
        if channels <= 2:  # grey, or grey + alpha
            image = image[:, :, 0]
        elif channels == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
        else:
            image = cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2RGB)
    return apply_orientation(image, _orientation(path)) if upright else image


def write_image(path: Path | str, image: np.ndarray) -> None:
    """`cv2.imwrite` (BGR or grey pixels; the format from the suffix) through bytes: OpenCV's own imwrite and
    imread crash the process (SIGSEGV) on a path that is not UTF-8."""
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    ok, data = cv2.imencode(Path(path).suffix, image)
    if not ok:
        raise InputError(f"{path}: OpenCV could not encode the image")
    Path(path).write_bytes(data.tobytes())


def _orientation(path: Path) -> int:
    try:
        with Image.open(path) as im:
            return int(header_exif(im).get(_ORIENTATION, 1) or 1)
    except Exception:
        return 1


def apply_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """Turn a stored image upright given its EXIF orientation (1-8), the way viewers display it."""
    ops = {
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1],
        5: lambda a: np.swapaxes(a, 0, 1),
        6: lambda a: np.swapaxes(a, 0, 1)[:, ::-1],
        7: lambda a: np.swapaxes(a, 0, 1)[::-1, ::-1],
        8: lambda a: np.swapaxes(a, 0, 1)[::-1],
    }
    op = ops.get(int(orientation))
    return np.ascontiguousarray(op(image)) if op else image


def as_uint8(image: np.ndarray) -> np.ndarray:
    """8-bit copy: 16-bit (or float) images stretched by their maximum, so 10/12-bit data keeps its contrast; the
    matchers work on 8-bit data."""
    img = np.asarray(image)
    if img.dtype == np.uint8:
        return img
    top = float(np.nanmax(img)) if img.size else 1.0
    return np.clip(img.astype(np.float32) * (255.0 / max(top, 1e-9)), 0, 255).round().astype(np.uint8)


LUMA_WEIGHTS = (0.299, 0.587, 0.114)  # ITU-R BT.601, the weights of OpenCV's RGB2GRAY


def to_gray(image: np.ndarray, dtype: type[np.uint8] | type[np.float32] = np.uint8) -> np.ndarray:
    """The image in grey, by the BT.601 weights, the one conversion every path uses (an alpha channel is ignored).

    uint8 (for detection and matching): OpenCV's RGB2GRAY, then `as_uint8` (a 16-bit image stretched by the
    maximum of its grey); 8-bit grey comes back as given. float32 (for costs that need sub-level differences):
    the weighted sum in float32, unrounded, on the image's own scale."""
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    if dtype == np.float32:
        img = np.asarray(image, dtype=np.float32)
        return img[..., :3] @ np.array(LUMA_WEIGHTS, dtype=np.float32) if img.ndim == 3 else img
    if dtype != np.uint8:
        raise ValueError(f"to_gray gives uint8 or float32, not {np.dtype(dtype)}")
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return as_uint8(img)


def colors_at(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N,3) RGB of `image` at COLMAP pixel coordinates `xy` (top-left pixel centre at (0.5, 0.5)), bilinear
    and NaN where the 2x2 neighbourhood leaves the image: COLMAP's sampling of point colours, so that colours
    taken at the keypoints while the features are extracted give what `extract_colors_for_all_images` gives,
    without decoding every image again. float32 (half of float64's memory; float16 moved 4% of templeRing's
    point colours by one level); grey images give grey, 16-bit ones are scaled to 8 bits."""
    img = image[:, :, None] if image.ndim == 2 else image
    h, w = img.shape[:2]
    x, y = xy[:, 0].astype(np.float64) - 0.5, xy[:, 1].astype(np.float64) - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.clip(x0, 0, max(w - 2, 0)), np.clip(y0, 0, max(h - 2, 0))
    dx, dy = (x - x0)[:, None], (y - y0)[:, None]

    def at(r, c):  # only the sampled pixels are converted, not the whole (maybe 24-megapixel) image
        return img[r, c].astype(np.float64)

    top = at(y0, x0) * (1 - dx) + at(y0, x0 + 1) * dx
    bottom = at(y0 + 1, x0) * (1 - dx) + at(y0 + 1, x0 + 1) * dx
    rgb = (top * (1 - dy) + bottom * dy) / (257.0 if image.dtype == np.uint16 else 1.0)
    out = np.broadcast_to(rgb, (len(x), 3)).astype(np.float32)
    out[~inside] = np.nan
    return out
