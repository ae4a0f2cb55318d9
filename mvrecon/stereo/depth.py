"""Depth from disparity and the coloured point cloud: Z = f * B / (d + doffs), X = (x - cx) Z / f,
Y = (y - cy) Z / f."""

from pathlib import Path

import numpy as np

from ..io.ply import write_ply


def disparity_to_depth(disparity: np.ndarray, focal: float, baseline: float,
                       doffs: float = 0.0) -> np.ndarray:
    """Depth in the baseline's unit; NaN where the disparity is a hole or d + doffs <= 0 (point at infinity)."""
    d = np.asarray(disparity, dtype=np.float64) + doffs
    with np.errstate(divide="ignore", invalid="ignore"):
        z = focal * baseline / d
    z[~np.isfinite(z) | (d <= 0)] = np.nan
    return z


def depth_to_points(depth: np.ndarray, focal: float, cx: float, cy: float,
                    max_depth: float | None = None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """(points (N,3), (rows, cols) of the valid pixels) in the left camera frame; pixel centres at integers."""
    z = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(z)
    if max_depth is not None:
        valid &= z <= max_depth
    rows, cols = np.nonzero(valid)
    zz = z[rows, cols]
    pts = np.column_stack([(cols - cx) * zz / focal, (rows - cy) * zz / focal, zz])
    return pts, (rows, cols)


def write_point_cloud(path: Path | str, depth: np.ndarray, image: np.ndarray, focal: float, cx: float,
                      cy: float, max_depth: float | None = None) -> int:
    """Write the coloured PLY of every pixel with a depth; returns the number of points."""
    pts, (rows, cols) = depth_to_points(depth, focal, cx, cy, max_depth)
    img = np.asarray(image)
    colors = img[rows, cols] if img.ndim == 3 else np.repeat(img[rows, cols][:, None], 3, axis=1)
    write_ply(path, pts, colors=colors[:, :3].astype(np.uint8))
    return len(pts)
