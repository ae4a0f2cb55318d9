"""Height maps on the reference image grid from scattered points: gridding, spike removal, profiles.

Sparse SIFT points give heights where the texture allows; a map needs interpolation between them (piecewise
linear over their Delaunay triangulation), which `dense.py` refines at every pixel. World frame, units and signs:
see `parallax.py`.
"""

from pathlib import Path

import numpy as np
import tifffile
from scipy.interpolate import LinearNDInterpolator
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from ..errors import InputError


def grid_heights(xy: np.ndarray, heights: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """float32 (H,W) map from scattered points: xy (N,2) in grid pixels (x = column), NaN outside their hull."""
    h, w = shape
    xy = np.asarray(xy, dtype=float)
    if len(xy) < 3:
        return np.full(shape, np.nan, dtype=np.float32)
    interp = LinearNDInterpolator(xy, np.asarray(heights, dtype=float))
    gx, gy = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    return interp(gx, gy).astype(np.float32)


def profile(height_map: np.ndarray, start: tuple[float, float], end: tuple[float, float],
            samples: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(distance along the line in pixels, heights) sampled bilinearly from (x0, y0) to (x1, y1); NaN propagates."""
    (x0, y0), (x1, y1) = start, end
    length = float(np.hypot(x1 - x0, y1 - y0))
    n = samples or max(2, int(np.ceil(length)) + 1)
    t = np.linspace(0.0, 1.0, n)
    xs, ys = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
    data = np.asarray(height_map, dtype=float)
    values = map_coordinates(np.nan_to_num(data, nan=0.0), [ys, xs], order=1, mode="nearest")
    nan = map_coordinates(np.isnan(data).astype(float), [ys, xs], order=1, mode="nearest") > 0
    return t * length, np.where(nan, np.nan, values)


def height_outliers(points: np.ndarray, neighbours: int = 12, threshold_px: float = 3.0,
                    mad_factor: float = 6.0) -> np.ndarray:
    """Mask of points whose height disagrees with the median of their `neighbours` nearest neighbours in the image
    plane by more than max(threshold_px, mad_factor * 1.4826 * MAD) of those differences.

    A wrong match along the parallax direction passes the affine epipolar test (tilting moves points only across
    the axis, which is exactly the direction the constraint cannot see) and becomes a height spike amplified by
    1 / sin(tilt difference): about 11x for a 5 degree pair. Such spikes are isolated, so a local median finds them.
    """
    points = np.asarray(points, dtype=float)
    if len(points) <= neighbours:
        return np.zeros(len(points), dtype=bool)
    _, idx = cKDTree(points[:, :2]).query(points[:, :2], k=neighbours + 1)
    local = np.median(points[idx[:, 1:], 2], axis=1)
    diff = np.abs(points[:, 2] - local)
    limit = max(threshold_px, mad_factor * 1.4826 * float(np.median(diff)))
    return diff > limit


def height_accuracy(estimate: np.ndarray, truth: np.ndarray) -> dict:
    """Height map against ground truth on the same grid (NaN = no value in either): `coverage` is the share of
    the pixels with a true height that have an estimate, and the errors are over those covered pixels after
    removing the median offset (nothing in a tilt series fixes the absolute level): RMS, 99th percentile of the
    absolute error, both also in % of the true height range."""
    estimate, truth = np.asarray(estimate, float), np.asarray(truth, float)
    known = np.isfinite(truth)
    both = known & np.isfinite(estimate)
    span = float(np.ptp(truth[known])) if known.any() else float("nan")
    if not both.any():
        return {"coverage": 0.0, "pixels": 0, "range": span}
    r = estimate[both] - truth[both]
    r -= np.median(r)
    rms, p99 = float(np.sqrt(np.mean(r * r))), float(np.percentile(np.abs(r), 99))
    return {"coverage": float(both.sum() / known.sum()), "pixels": int(both.sum()), "range": span, "rms": rms,
            "p99": p99, "rms_percent_of_range": 100 * rms / span, "p99_percent_of_range": 100 * p99 / span}


def read_height_map(path: Path | str) -> np.ndarray:
    """float32 height map from .npy or 32-bit TIFF (what `mvrecon sem` and `mvrecon scene make` write), NaN where
    unknown; a missing, unreadable or non-2D file is an InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: ground-truth height map not found")
    try:
        if path.suffix.lower() == ".npy":
            height = np.load(path, allow_pickle=False)
        elif path.suffix.lower() in (".tif", ".tiff"):
            height = tifffile.imread(path)
        else:
            raise ValueError("expected a .npy or .tif height map")
        height = np.asarray(height, dtype=np.float32)
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}: cannot read ground-truth heights ({exc})") from None
    if height.ndim != 2:
        raise InputError(f"{path}: a height map has one value per pixel, this array has shape {height.shape}")
    return height
