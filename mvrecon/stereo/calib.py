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


def read_calib(path) -> StereoCalib:
    """Parse a Middlebury calib.txt; InputError names the file and what is missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: calibration file not found")
    values = {}
    for line in path.read_text().splitlines():
        if "=" in line:
            key, value = line.split("=", 1)
            values[key.strip()] = value.strip()
    missing = [k for k in ("cam0", "cam1", "baseline") if k not in values]
    if missing:
        raise InputError(f"{path}: not a Middlebury calib.txt (missing {', '.join(missing)})")
    try:
        cam0, cam1 = _matrix(values["cam0"]), _matrix(values["cam1"])
        doffs = float(values.get("doffs", cam1[0, 2] - cam0[0, 2]))
        return StereoCalib(cam0, cam1, doffs, float(values["baseline"]), int(float(values.get("width", 0))),
                           int(float(values.get("height", 0))), int(float(values.get("ndisp", 0))),
                           float(values.get("vmin", 0)), float(values.get("vmax", 0)))
    except ValueError as exc:
        raise InputError(f"{path}: malformed calibration value ({exc})") from exc


def write_calib(path, calib: StereoCalib) -> None:
    def mat(m):
        return "[" + "; ".join(" ".join(f"{v:g}" for v in row) for row in m) + "]"

    Path(path).write_text(
        f"cam0={mat(calib.cam0)}\ncam1={mat(calib.cam1)}\ndoffs={calib.doffs:g}\nbaseline={calib.baseline:g}\n"
        f"width={calib.width}\nheight={calib.height}\nndisp={calib.ndisp}\nvmin={calib.vmin:g}\nvmax={calib.vmax:g}\n")
