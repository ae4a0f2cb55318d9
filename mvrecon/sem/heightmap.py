"""Height maps on the reference image grid: gridding scattered points, dense matching of a rectified pair, profiles.

Sparse SIFT points give heights where the texture allows; a dense map needs either interpolation between them
(piecewise linear over their Delaunay triangulation) or dense matching. Under parallel projection a tilt pair is
rectified by a rotation that turns the tilt axis vertical (parallax becomes horizontal) and, for the second view,
a stretch by cos(t_ref)/cos(t_other) across the axis, after which the horizontal disparity is proportional to
height: D = h sin(t_ref - t_other) / cos(t_other). Semi-global matching (OpenCV SGBM) then measures D per pixel.
World frame, units and signs: see `parallax.py`.
"""

from dataclasses import dataclass

import numpy as np

from .parallax import axis_vectors


def grid_heights(xy, heights, shape) -> np.ndarray:
    """float32 (H,W) map from scattered points: xy (N,2) in grid pixels (x = column), NaN outside their hull."""
    from scipy.interpolate import LinearNDInterpolator

    h, w = shape
    xy = np.asarray(xy, dtype=float)
    if len(xy) < 3:
        return np.full(shape, np.nan, dtype=np.float32)
    interp = LinearNDInterpolator(xy, np.asarray(heights, dtype=float))
    gx, gy = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    return interp(gx, gy).astype(np.float32)


@dataclass(frozen=True)
class DenseConfig:
    """Semi-global matching on the rectified pair. block_size: SGBM window (odd). margin_px: disparity search
    beyond the range the sparse points span. uniqueness: SGBM uniqueness ratio (%); higher rejects more."""

    block_size: int = 5
    margin_px: float = 8.0
    uniqueness: int = 10


def _rectify(image, axis_deg, center, out_shape, out_center, stretch=1.0, shift=(0.0, 0.0)):
    """Resample `image` on a grid whose x runs along the parallax direction (scaled by `stretch`) and y along the
    axis: rectified pixel (p, q) reads image pixel c + shift + stretch (p - pc) n + (q - qc) a."""
    import cv2

    a, n = axis_vectors(axis_deg)
    A = np.column_stack([stretch * n, a])
    t = np.asarray(center, float) + np.asarray(shift, float) - A @ np.asarray(out_center, float)
    M = np.hstack([A, t[:, None]])
    return cv2.warpAffine(image, M, (out_shape[1], out_shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def dense_heights(ref_image, other_image, tilt_ref: float, tilt_other: float, axis_deg: float, other_shift,
                  disparity_range, config: DenseConfig = DenseConfig()) -> np.ndarray:
    """float32 height map (NaN where unmatched) on the 0-degree grid of the reference image, by SGBM.

    `other_shift` is the other view's drift (pixels) from the joint solution, so heights share its gauge;
    `disparity_range` (lo, hi) in rectified pixels is where the sparse points say the disparities lie.
    """
    import cv2

    h, w = ref_image.shape[:2]
    center = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    side = int(np.ceil(np.hypot(w, h)))
    out_shape, out_center = (side, side), np.array([(side - 1) / 2.0] * 2)
    tr, to = np.radians(tilt_ref), np.radians(tilt_other)
    stretch = np.cos(to) / np.cos(tr)
    left = _rectify(ref_image, axis_deg, center, out_shape, out_center)
    right = _rectify(other_image, axis_deg, center, out_shape, out_center, stretch, other_shift)
    lo, hi = disparity_range
    min_disp = int(np.floor(lo - config.margin_px))
    num = int(np.ceil((hi - lo + 2 * config.margin_px) / 16.0)) * 16
    bs = config.block_size
    sgbm = cv2.StereoSGBM_create(minDisparity=min_disp, numDisparities=max(16, num), blockSize=bs,
                                 P1=8 * bs * bs, P2=32 * bs * bs, disp12MaxDiff=1,
                                 uniquenessRatio=config.uniqueness, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp = sgbm.compute(left, right).astype(np.float32) / 16.0
    valid = (disp >= min_disp) & (left > 0)
    height = np.where(valid, disp * np.cos(to) / np.sin(tr - to), np.nan)
    # the reference pixel at rectified p sees alpha = (p - h sin t_ref) / cos t_ref: resample each row onto alpha
    p = np.arange(side, dtype=float) - out_center[0]
    rect = np.full(out_shape, np.nan, dtype=np.float32)
    for row in range(side):
        ok = np.isfinite(height[row])
        if ok.sum() < 2:
            continue
        alpha = (p[ok] - height[row, ok] * np.sin(tr)) / np.cos(tr)
        order = np.argsort(alpha)
        values = np.interp(p, alpha[order], height[row, ok][order], left=np.nan, right=np.nan)
        gaps = np.interp(p, p[ok], np.zeros(ok.sum()), left=np.nan, right=np.nan)  # no values past the ends
        rect[row] = np.where(np.isfinite(gaps), values, np.nan)
        rect[row, ~_near_valid(ok)] = np.nan
    return _unrectify(rect, axis_deg, center, (h, w), out_center)


def _near_valid(ok: np.ndarray, reach: int = 2) -> np.ndarray:
    """Pixels within `reach` of a matched pixel: interpolation must not bridge unmatched stretches."""
    kernel = np.ones(2 * reach + 1)
    return np.convolve(ok.astype(float), kernel, mode="same") > 0


def _unrectify(rect, axis_deg, center, shape, out_center) -> np.ndarray:
    import cv2

    a, n = axis_vectors(axis_deg)
    A = np.column_stack([n, a]).T  # image offset -> (p, q)
    t = np.asarray(out_center, float) - A @ np.asarray(center, float)
    M = np.hstack([A, t[:, None]])
    filled = np.nan_to_num(rect, nan=0.0)
    valid = cv2.warpAffine(np.isfinite(rect).astype(np.float32), M, (shape[1], shape[0]),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    out = cv2.warpAffine(filled, M, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return np.where(valid > 0.999, out, np.nan).astype(np.float32)


def profile(height_map, start, end, samples: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(distance along the line in pixels, heights) sampled bilinearly from (x0, y0) to (x1, y1); NaN propagates."""
    from scipy.ndimage import map_coordinates

    (x0, y0), (x1, y1) = start, end
    length = float(np.hypot(x1 - x0, y1 - y0))
    n = samples or max(2, int(np.ceil(length)) + 1)
    t = np.linspace(0.0, 1.0, n)
    xs, ys = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
    data = np.asarray(height_map, dtype=float)
    values = map_coordinates(np.nan_to_num(data, nan=0.0), [ys, xs], order=1, mode="nearest")
    nan = map_coordinates(np.isnan(data).astype(float), [ys, xs], order=1, mode="nearest") > 0
    return t * length, np.where(nan, np.nan, values)


def height_outliers(points, neighbours: int = 12, threshold_px: float = 3.0, mad_factor: float = 6.0) -> np.ndarray:
    """Mask of points whose height disagrees with the median of their `neighbours` nearest neighbours in the image
    plane by more than max(threshold_px, mad_factor * 1.4826 * MAD) of those differences.

    A wrong match along the parallax direction passes the affine epipolar test (tilting moves points only across
    the axis, which is exactly the direction the constraint cannot see) and becomes a height spike amplified by
    1 / sin(tilt difference): about 11x for a 5 degree pair. Such spikes are isolated, so a local median finds them.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float)
    if len(points) <= neighbours:
        return np.zeros(len(points), dtype=bool)
    _, idx = cKDTree(points[:, :2]).query(points[:, :2], k=neighbours + 1)
    local = np.median(points[idx[:, 1:], 2], axis=1)
    diff = np.abs(points[:, 2] - local)
    limit = max(threshold_px, mad_factor * 1.4826 * float(np.median(diff)))
    return diff > limit
