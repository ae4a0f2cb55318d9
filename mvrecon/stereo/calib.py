"""Middlebury `calib.txt` (cam0, cam1, doffs, baseline, width, height, ndisp, ...): read and write."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError


@dataclass(frozen=True)
class StereoCalib:
    """Rectified stereo calibration. Depth Z = f * baseline / (d + doffs), doffs = cx1 - cx0 (pixels)."""

    cam0: np.ndarray
    cam1: np.ndarray
    doffs: float
    baseline: float
    width: int = 0
    height: int = 0
    ndisp: int = 0
    vmin: float = 0.0
    vmax: float = 0.0

    @property
    def focal(self) -> float:
        return float(self.cam0[0, 0])


def _matrix(text: str) -> np.ndarray:
    rows = [r.split() for r in text.strip().strip("[]").split(";")]
    return np.array(rows, dtype=float).reshape(3, 3)


def read_calib(path: Path | str) -> StereoCalib:
    """Parse a Middlebury calib.txt; InputError names the file and what is missing or malformed (a binary file, a
    missing key, a value that is not a number, a focal length or baseline that is not positive)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: calibration file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a Middlebury calib.txt (not text)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the calibration file ({exc.strerror or exc})") from None
    values = {}
    for line in text.splitlines():
        if "=" in line:
            key, value = line.split("=", 1)
            values[key.strip()] = value.strip()
    missing = [k for k in ("cam0", "cam1", "baseline") if k not in values]
    if missing:
        raise InputError(f"{path}: not a Middlebury calib.txt (missing {', '.join(missing)})")
    try:
        cam0, cam1 = _matrix(values["cam0"]), _matrix(values["cam1"])
        doffs = float(values.get("doffs", cam1[0, 2] - cam0[0, 2]))
        calib = StereoCalib(cam0, cam1, doffs, float(values["baseline"]), int(float(values.get("width", 0))),
                            int(float(values.get("height", 0))), int(float(values.get("ndisp", 0))),
                            float(values.get("vmin", 0)), float(values.get("vmax", 0)))
    except ValueError as exc:
        raise InputError(f"{path}: malformed calibration value ({exc})") from None
    if not (np.isfinite(cam0).all() and np.isfinite(cam1).all() and np.isfinite([doffs, calib.baseline]).all()):
        raise InputError(f"{path}: calibration values must be finite numbers")
    if calib.focal <= 0 or calib.baseline <= 0:
        raise InputError(f"{path}: focal length {calib.focal:g} and baseline {calib.baseline:g} must be positive")
    if calib.width < 0 or calib.height < 0 or calib.ndisp < 0:
        raise InputError(f"{path}: width, height and ndisp must not be negative")
    return calib


def check_image_size(path: Path | str, calib: StereoCalib, width: int, height: int,
                     image: Path | str) -> None:
    """Refuse a calib.txt made for other images: its f, cx, cy, doffs and ndisp scale with the image size, so a
    calib.txt of the full-size pair used on a quarter-size one gives wrong depth and search range without any
    error. The file's width/height must equal the image's; a file without them (they are optional here) is judged
    by cam0's principal point, which must lie inside the image (a full-size file on smaller images fails this; a
    smaller file on larger images cannot be told apart and is used as it is)."""
    if calib.width > 0 and calib.height > 0:
        if (calib.width, calib.height) != (width, height):
            raise InputError(f"{path}: made for {calib.width}x{calib.height} images, these are {width}x{height} "
                             f"({image})")
        return
    cx, cy = float(calib.cam0[0, 2]), float(calib.cam0[1, 2])
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise InputError(f"{path}: no width/height given and its principal point ({cx:g}, {cy:g}) lies outside "
                         f"these {width}x{height} images ({image}): made for other images?")


def write_calib(path: Path | str, calib: StereoCalib) -> None:
    def mat(m):
        return "[" + "; ".join(" ".join(f"{v:g}" for v in row) for row in m) + "]"

    Path(path).write_text(
        f"cam0={mat(calib.cam0)}\ncam1={mat(calib.cam1)}\ndoffs={calib.doffs:g}\nbaseline={calib.baseline:g}\n"
        f"width={calib.width}\nheight={calib.height}\nndisp={calib.ndisp}\nvmin={calib.vmin:g}\nvmax={calib.vmax:g}\n")
