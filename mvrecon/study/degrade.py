"""Image-quality degradations that imitate cheap cameras, motion and compression, applied in one fixed order.

Why a fixed order: the result of composing degradations depends on their order, so the order follows the path
light takes through a camera and its software, and a study that varies one degradation at a time stays
comparable with one that combines them:

    downscale -> blur -> motion_blur -> brightness -> poisson -> noise -> gamma -> sharpen -> jpeg

(a lower-resolution sensor, lens blur, motion during the exposure, exposure gain, photon shot noise, read noise,
the tone curve, in-camera sharpening, and finally the file's compression).

Pixel values are handled as floats in [0, 1] of the image's full scale (255 or 65535), so 8-bit, 16-bit, grey,
colour and alpha images all go through the same code; grey levels in parameters (the noise sigma) are 8-bit grey
levels (a sigma of 10 adds 10/255 of full scale, i.e. 2570 levels in a 16-bit image). Alpha is never degraded.
Random noise is seeded per image from (seed, file name), so the same command gives the same bytes whatever the
order or the subset of files processed. Output files keep their names, formats and EXIF (updated for the new size
when downscaled).

A folder's images are the ones `reconstruct` takes (`io.images.list_images`: sub-folders searched, run outputs and
unreadable files left out) and keep their sub-folder paths in the output, so every engine of a study sees the
same image set in every cell.
"""

import io
import logging
import math
import struct
import zlib
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from ..errors import InputError
from ..io.files import read_json_object, replace_whole, write_json
from ..io.images import FORMATS, IMAGE_EXTENSIONS, image_problem, list_images, write_image
from ..progress import progress

log = logging.getLogger(__name__)

ORDER = ("downscale", "blur", "motion_blur", "brightness", "poisson", "noise", "gamma", "sharpen", "jpeg")
JPEG_SUFFIXES = {".jpg", ".jpeg"}
# A JPEG input that is degraded but not asked to be re-compressed must still be re-encoded: as losslessly as
# JPEG allows, so the requested degradations are the only visible ones: quality 100 and no chroma subsampling
# (4:4:4; the default 4:2:0 averages colour over 2x2 pixels, which took --noise 10 down to a per-channel std
# of 7.1). `--jpeg Q` is encoded as any JPEG writer does at quality Q, 4:2:0 included: that is the degradation.
NEUTRAL_JPEG_QUALITY = 100
NEUTRAL_JPEG_SUBSAMPLING = 0  # Pillow's 4:4:4
RECORD = ".mvrecon-degrade.json"  # in an output folder: its settings and the images finished under them
MAX_POISSON_PEAK = 1e12  # 1e-6 of full scale: invisible even in 16 bits; numpy's Poisson fails above ~9e18
_EXIF_HEADER = b"Exif\x00\x00"
# TIFF tags that describe the pixel layout (size, depth, compression, strips, predictor), not the picture
_TIFF_LAYOUT_TAGS = (256, 257, 258, 259, 262, 273, 277, 278, 279, 284, 317, 339)
_EXIF_IFD = 0x8769
_EXIF_WIDTH, _EXIF_HEIGHT = 0xA002, 0xA003


class SettingError(InputError):
    """A setting an image cannot take (a blur wider than the image): stops the run instead of skipping the image."""


# Degradation field -> (the command-line flag of `degrade` and of a study axis, what it is), for error messages
FLAGS = {"downscale": ("--downscale", "downscale factor"), "blur_sigma": ("--blur", "blur sigma"),
         "motion_length": ("--motion", "motion blur length"), "motion_angle": ("--motion-angle", "motion angle"),
         "brightness": ("--brightness", "brightness gain"), "poisson_peak": ("--poisson", "Poisson peak"),
         "noise_sigma": ("--noise", "noise sigma"), "gamma": ("--gamma", "gamma"),
         "sharpen_amount": ("--sharpen", "sharpen amount"), "sharpen_radius": ("--sharpen-radius", "sharpen radius"),
         "jpeg_quality": ("--jpeg", "JPEG quality")}


@dataclass(frozen=True)
class Degradation:
    """Parameters of every degradation; the defaults leave an image unchanged (see ORDER for how they compose)."""

    downscale: float = 1.0  # divide width and height by this (>= 1), area-averaging like a coarser sensor
    blur_sigma: float = 0.0  # Gaussian (defocus) blur, standard deviation in pixels
    motion_length: float = 0.0  # linear motion blur, length of the smear in pixels
    motion_angle: float = 0.0  # direction of the smear in degrees, counter-clockwise from the image x axis
    brightness: float = 1.0  # exposure gain (values multiplied, then clipped)
    poisson_peak: float = 0.0  # shot noise: photo-electrons at full scale (lower = noisier); 0 = off
    noise_sigma: float = 0.0  # additive Gaussian noise, standard deviation in 8-bit grey levels
    gamma: float = 1.0  # tone curve out = in ** gamma (> 1 darkens mid-tones, < 1 brightens them)
    sharpen_amount: float = 0.0  # unsharp mask: out = in + amount * (in - blur(in, sharpen_radius))
    sharpen_radius: float = 1.0  # Gaussian sigma of the unsharp mask, pixels
    jpeg_quality: int = 0  # JPEG re-compression quality 1..100; 0 = no re-compression

    def __post_init__(self):
        def refuse(name, rule):  # "--noise -5: noise sigma must be >= 0": the flag the user typed, and its value
            flag, label = FLAGS[name]
            raise InputError(f"{flag} {getattr(self, name):g}: {label} must be {rule}")

        for f in fields(self):  # inf and nan pass the comparisons below (nan fails none), then break the pixels
            if not math.isfinite(getattr(self, f.name)):
                refuse(f.name, "a finite number")
        checks = [("downscale", self.downscale >= 1.0, ">= 1"),
                  ("blur_sigma", self.blur_sigma >= 0, ">= 0"),
                  ("motion_length", self.motion_length >= 0, ">= 0"),
                  ("brightness", self.brightness > 0, "> 0"),
                  ("poisson_peak", self.poisson_peak >= 0, ">= 0"),
                  ("poisson_peak", self.poisson_peak <= MAX_POISSON_PEAK,
                   f"at most {MAX_POISSON_PEAK:g} (the noise is far below one grey level there)"),
                  ("noise_sigma", self.noise_sigma >= 0, ">= 0"),
                  ("gamma", self.gamma > 0, "> 0"),
                  ("sharpen_amount", self.sharpen_amount >= 0, ">= 0"),
                  ("sharpen_radius", self.sharpen_radius > 0, "> 0"),
                  ("jpeg_quality", self.jpeg_quality == 0 or 1 <= self.jpeg_quality <= 100, "1..100 (0 = off)")]
        for name, ok, rule in checks:
            if not ok:
                refuse(name, rule)

    def active(self) -> list[str]:
        """Names (from ORDER) of the steps that change an image, in the order they are applied."""
        on = {"downscale": self.downscale > 1.0, "blur": self.blur_sigma > 0, "motion_blur": self.motion_length > 0,
              "brightness": self.brightness != 1.0, "poisson": self.poisson_peak > 0, "noise": self.noise_sigma > 0,
              "gamma": self.gamma != 1.0, "sharpen": self.sharpen_amount > 0, "jpeg": self.jpeg_quality > 0}
        return [step for step in ORDER if on[step]]

    def describe(self) -> str:
        return ", ".join(f"{f.name}={getattr(self, f.name):g}" for f in fields(self)
                         if getattr(self, f.name) != f.default) or "none"

    def to_dict(self) -> dict:
        return asdict(self)


def with_level(base: Degradation, field: str, value: float) -> Degradation:
    """`base` with one parameter changed (study grids vary one degradation at a time)."""
    value = int(value) if field == "jpeg_quality" and math.isfinite(value) else float(value)
    return replace(base, **{field: value})


def image_seed(seed: int, name: str) -> np.random.SeedSequence:
    """The random stream of one image depends only on the run's seed and the file's name (not on file order)."""
    return np.random.SeedSequence([int(seed), zlib.crc32(name.encode("utf-8"))])


# ---------------------------------------------------------------- pixel operations on float images in [0, 1]

def _gaussian(img: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT_101)


def _scaled_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    return max(1, int(round(width / downscale))), max(1, int(round(height / downscale)))


def check_kernels(deg: Degradation, width: int, height: int, src: Path | str) -> None:
    """SettingError when a blur kernel (OpenCV's Gaussian reaches 4 sigma each side) would not fit in the image
    after downscaling: it only blurs the image to its mean, and takes minutes (--blur 1e5) or all memory
    (--motion 1e9)."""
    w, h = _scaled_size(width, height, deg.downscale) if deg.downscale > 1.0 else (width, height)
    side = min(w, h)
    for on, flag, value, limit in ((deg.blur_sigma > 0, "--blur", deg.blur_sigma, (side - 1) / 8),
                                   (deg.motion_length > 0, "--motion", deg.motion_length, side - 1),
                                   (deg.sharpen_amount > 0, "--sharpen-radius", deg.sharpen_radius, (side - 1) / 8)):
        if on and value > limit:
            raise SettingError(f"{src}: {flag} {value:g} is too large for its {w}x{h} pixels (at most {limit:g}: "
                               "the kernel must fit in the image)")


def motion_kernel(length: float, angle_deg: float) -> np.ndarray:
    """A normalised line kernel `length` px long at `angle_deg`, anti-aliased by splatting sub-pixel samples."""
    half = length / 2.0
    size = 2 * int(np.ceil(half)) + 1
    c = size // 2
    kernel = np.zeros((size, size), np.float64)
    a = np.deg2rad(angle_deg)
    n = max(int(np.ceil(length * 8)), 1)
    for s in -half + (np.arange(n) + 0.5) * length / n:  # sample midpoints: a uniform segment, no end bias
        x, y = c + s * np.cos(a), c - s * np.sin(a)  # image y points down
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            if 0 <= x0 + dx < size and 0 <= y0 + dy < size:
                kernel[y0 + dy, x0 + dx] += w
    return (kernel / kernel.sum()).astype(np.float32)


def _jpeg_roundtrip(img: np.ndarray, quality: int) -> np.ndarray:
    """Encode to JPEG in memory and decode (for outputs that are not JPEG files but must carry its artefacts)."""
    u8 = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    pil = Image.fromarray(u8 if u8.ndim == 2 else u8[..., ::-1])  # working images are BGR like OpenCV
    buf = io.BytesIO()
    pil.save(buf, "JPEG", quality=int(quality))
    back = np.asarray(Image.open(buf))
    back = back if back.ndim == 2 else back[..., ::-1]
    return back.astype(np.float32) / 255.0


def apply_pixels(img: np.ndarray, deg: Degradation, rng: np.random.Generator, *, encode_jpeg: bool) -> np.ndarray:
    """Apply the degradations in ORDER to a float32 image in [0, 1] (H x W or H x W x C, colour channels only).

    `encode_jpeg` False leaves the JPEG step to the file writer (the output is itself a JPEG file).
    """
    out = img.astype(np.float32, copy=True)
    for step in deg.active():
        if step == "downscale":
            h, w = out.shape[:2]
            out = cv2.resize(out, _scaled_size(w, h, deg.downscale), interpolation=cv2.INTER_AREA)
        elif step == "blur":
            out = _gaussian(out, deg.blur_sigma)
        elif step == "motion_blur":
            out = cv2.filter2D(out, -1, motion_kernel(deg.motion_length, deg.motion_angle),
                               borderType=cv2.BORDER_REFLECT_101)
        elif step == "brightness":
            out = np.clip(out * deg.brightness, 0.0, 1.0)
        elif step == "poisson":
            out = (rng.poisson(np.clip(out, 0.0, 1.0) * deg.poisson_peak) / deg.poisson_peak).astype(np.float32)
        elif step == "noise":
            out = out + rng.normal(0.0, deg.noise_sigma / 255.0, out.shape).astype(np.float32)
        elif step == "gamma":
            out = np.power(np.clip(out, 0.0, 1.0), deg.gamma)
        elif step == "sharpen":
            out = out + deg.sharpen_amount * (out - _gaussian(out, deg.sharpen_radius))
        elif step == "jpeg" and encode_jpeg:
            out = _jpeg_roundtrip(np.clip(out, 0.0, 1.0), deg.jpeg_quality)
        out = np.clip(out, 0.0, 1.0)  # the sensor saturates and the file's range is finite at every step
    return out.astype(np.float32)


# ---------------------------------------------------------------- files: read, degrade, write with EXIF

def _read(path: Path) -> np.ndarray:
    # keeps 16 bits, grey and alpha; no EXIF rotation. imdecode rather than imread: imread returns a cut-off
    # JPEG with its missing rows grey, where imdecode fails on it as `reconstruct` does
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError(f"{path}: cannot read this image")
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{path}: {img.dtype} pixels are not supported (8- or 16-bit only)")
    return img


def _read_exif(path: Path) -> bytes | None:
    """The EXIF block as stored (with the 'Exif\\0\\0' header), or None; TIFF tags are not EXIF blocks."""
    with Image.open(path) as pil:
        exif = pil.info.get("exif")
    if exif and not exif.startswith(_EXIF_HEADER):
        exif = _EXIF_HEADER + exif
    return exif or None


def _resized_exif(exif: bytes, width: int, height: int) -> bytes:
    """EXIF with the pixel dimensions (PixelXDimension/PixelYDimension) updated after downscaling."""
    parsed = Image.Exif()
    parsed.load(exif)
    sub = parsed.get_ifd(_EXIF_IFD)
    if _EXIF_WIDTH in sub or _EXIF_HEIGHT in sub:
        sub[_EXIF_WIDTH], sub[_EXIF_HEIGHT] = width, height
    return parsed.tobytes()


def _png_with_exif(png: bytes, exif: bytes) -> bytes:
    """Insert an eXIf chunk (the EXIF block without its header) right after IHDR, as the PNG spec allows."""
    body = exif[len(_EXIF_HEADER):] if exif.startswith(_EXIF_HEADER) else exif
    chunk = struct.pack(">I", len(body)) + b"eXIf" + body + struct.pack(">I", zlib.crc32(b"eXIf" + body))
    ihdr_end = 8 + 8 + 13 + 4  # signature + IHDR length/type + IHDR data + CRC
    return png[:ihdr_end] + chunk + png[ihdr_end:]


def _to_pil(pixels: np.ndarray) -> Image.Image:
    if pixels.ndim == 2:
        return Image.fromarray(pixels)
    order = [2, 1, 0, 3][: pixels.shape[2]]
    return Image.fromarray(np.ascontiguousarray(pixels[..., order]))


def _write(path: Path, pixels: np.ndarray, src: Path, exif: bytes | None, jpeg_quality: int) -> None:
    suffix = path.suffix.lower()
    if suffix in JPEG_SUFFIXES:
        with Image.open(src) as pil:
            icc = pil.info.get("icc_profile")
        extra = {"exif": exif} if exif else {}
        if icc:
            extra["icc_profile"] = icc
        if jpeg_quality:  # the --jpeg degradation: Pillow's encoder at that quality, with its usual 4:2:0
            _to_pil(pixels).save(path, "JPEG", quality=jpeg_quality, **extra)
        else:  # only a re-encode, which must not hide what the other degradations did (the noise's colour)
            _to_pil(pixels).save(path, "JPEG", quality=NEUTRAL_JPEG_QUALITY, subsampling=NEUTRAL_JPEG_SUBSAMPLING,
                                 **extra)
    elif suffix == ".png":
        ok, buf = cv2.imencode(".png", pixels)
        if not ok:
            raise InputError(f"{src}: PNG encoding failed")
        data = buf.tobytes()
        path.write_bytes(_png_with_exif(data, exif) if exif else data)
    else:  # TIFF: Pillow keeps the source's tags for the layouts it can hold, OpenCV writes the rest
        with Image.open(src) as pil:
            tags = pil.getexif()
        for tag in _TIFF_LAYOUT_TAGS:  # the writer sets these for the new pixels
            tags.pop(tag, None)
        if pixels.dtype == np.uint8 or pixels.ndim == 2:
            _to_pil(pixels).save(path, "TIFF", exif=tags)
        else:
            if len(tags):
                log.warning("%s: 16-bit colour TIFF written without its metadata tags", src.name)
            write_image(path, pixels)


def degrade_image(src: Path, dst: Path, deg: Degradation, seed: int = 0, name: str | None = None) -> None:
    """Write a degraded copy of `src` to `dst` (same format as dst's suffix), keeping EXIF; `dst` appears whole.

    `name` (default: the file's name) seeds the noise: a folder passes the path relative to it, so that a/0.png and
    b/0.png do not get the same noise."""
    raw = _read(src)
    if not deg.active():  # nothing to do: the copy is the original's bytes
        replace_whole(dst, lambda tmp: tmp.write_bytes(src.read_bytes()))
        return
    check_kernels(deg, raw.shape[1], raw.shape[0], src)
    scale = 255.0 if raw.dtype == np.uint8 else 65535.0
    has_alpha = raw.ndim == 3 and raw.shape[2] in (2, 4)
    colour = raw[..., :-1] if has_alpha else raw
    is_jpeg_file = dst.suffix.lower() in JPEG_SUFFIXES
    rng = np.random.default_rng(image_seed(seed, name or Path(src).name))
    out = apply_pixels(colour.astype(np.float32) / scale, deg, rng, encode_jpeg=not is_jpeg_file)
    if out.ndim == 2 and colour.ndim == 3:
        out = out[..., None]  # OpenCV drops a single channel axis
    pixels = np.clip(np.rint(out * scale), 0, scale).astype(raw.dtype)
    if has_alpha:
        alpha = raw[..., -1:]
        if alpha.shape[:2] != pixels.shape[:2]:
            alpha = cv2.resize(alpha, pixels.shape[1::-1], interpolation=cv2.INTER_AREA)[..., None]
        pixels = np.concatenate([pixels, alpha], axis=2)
    if is_jpeg_file and raw.dtype != np.uint8:
        raise InputError(f"{src}: 16-bit JPEG files do not exist; cannot write {dst.name}")
    exif = _read_exif(src)
    if exif and pixels.shape[:2] != raw.shape[:2]:
        exif = _resized_exif(exif, pixels.shape[1], pixels.shape[0])
    replace_whole(dst, lambda tmp: _write(tmp, pixels, src, exif, deg.jpeg_quality))


def image_sources(images: Path | str) -> tuple[Path, list[str]]:
    """The folder and the image names in it (POSIX, relative to it) that `degrade_folder` degrades: the images
    `reconstruct` takes from a folder (`io.images.list_images`), or one image file; InputError when there are none."""
    path = Path(images)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    if path.is_file():
        problem = image_problem(path) if path.suffix.lower() in IMAGE_EXTENSIONS else f"not a {FORMATS} file"
        if problem:
            raise InputError(f"{path}: {problem}")
        return path.parent, [path.name]
    names, _ = list_images(path)  # warns about each file it leaves out, with the reason
    return path, names


def _finished(out_dir: Path, settings: dict) -> set[str]:
    """Names finished in `out_dir` by an earlier run with the same `settings` (none in a folder without a record);
    InputError when it was made with others: two degradations must not mix in one folder."""
    path = out_dir / RECORD
    if not path.is_file():
        return set()
    record = read_json_object(path)
    old = record.get("settings") if record is not None else None
    if old != settings:
        differing = sorted(k for k in settings if not isinstance(old, dict) or old.get(k) != settings[k])
        raise InputError(f"{out_dir}: written earlier with another {', '.join(differing) or 'record'} ({path.name}); "
                         "choose another output folder, or delete this one to start over")
    return {name for name in record.get("done", []) if (out_dir / name).is_file()}


def _save_record(out_dir: Path, settings: dict, done: set[str]) -> None:
    write_json(out_dir / RECORD, {"settings": settings, "done": sorted(done)}, indent=1)


def degrade_folder(images: Path | str, out_dir: Path | str, deg: Degradation, seed: int = 0,
                   progress_desc: str = "degrade", names: list[str] | None = None) -> list[Path]:
    """Degrade every image of `images` (a folder or one image) into `out_dir` under the same names, sub-folders
    kept; returns the written paths. `names` (POSIX, relative to the folder `images`): the images to degrade when
    the caller has listed them already (a study lists once for all its cells); default `image_sources(images)`.

    A rerun after an interruption skips the images finished under the same settings (recorded in out_dir/RECORD
    after each image), so it continues where the first run stopped."""
    folder, names = image_sources(images) if names is None else (Path(images), list(names))
    out_dir = Path(out_dir)
    source, out = folder.resolve(), out_dir.resolve()
    if out == source:
        raise InputError(f"{out_dir}: the output folder must differ from the input folder")
    if Path(images).is_dir() and source in out.parents:  # sub-folders are images too: the copies would come back
        raise InputError(f"{out_dir}: inside the input folder {images}, whose sub-folders are searched for images "
                         "too; choose an output folder outside it")
    if Path(images).is_dir() and out in source.parents:  # the output folder would hold the clean originals
        raise InputError(f"{out_dir}: holds the input folder {images}, so its images would sit among the degraded "
                         "copies; choose an output folder outside it")
    out_dir.mkdir(parents=True, exist_ok=True)
    settings = {"source": str(Path(images).resolve()), "seed": int(seed), "degradation": deg.to_dict()}
    done = _finished(out_dir, settings)
    if done:
        log.info("%s: %d image(s) finished earlier with the same settings, kept", out_dir, len(done))
    written, skipped = [], []
    for name in progress(names, desc=progress_desc, unit="img"):
        src, dst = folder / name, out_dir / name
        if name in done:
            written.append(dst)
            continue
        # files whose header is broken or that are cut off are not listed (as `reconstruct` does not take them);
        # what is left is a file the decoder refuses
        try:
            dst.parent.mkdir(parents=True, exist_ok=True)
            degrade_image(src, dst, deg, seed, name=name)
            written.append(dst)
            done.add(name)
            _save_record(out_dir, settings, done)
            continue
        except SettingError:
            raise
        except InputError as exc:
            problem = str(exc).removeprefix(f"{src}: ")
        log.warning("skipping %s: %s", src, problem)
        skipped.append(name)
    if not written:
        raise InputError(f"{images}: none of the {len(names)} image(s) could be read (first: {skipped[0]})")
    return written
