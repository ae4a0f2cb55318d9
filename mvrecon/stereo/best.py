"""The most accurate classical stereo we build: census + gradient cost, 8-path semi-global aggregation, left-right
check, sub-pixel parabola, hole filling from the background side, and an edge-aware weighted median.

Why each piece: census (Zabih & Woodfill 1994) is robust to the exposure and vignetting differences between real
stereo cameras; a small absolute-gradient term sharpens it on fine texture. Semi-global matching (Hirschmueller 2008)
adds P1/P2 smoothness along 8 scanline directions, with P2 lowered across intensity edges so depth edges follow
image edges. The left-right check removes occlusions and mismatches; the parabola fit gives sub-pixel disparities.
Small blobs that passed the check (speckles: mostly wrong matches against the right image's border columns in the
left-edge band, where the true, larger disparity cannot be evaluated) are removed, as is the band the right camera
cannot see. Holes are then filled with the smaller (farther) of the nearest valid disparities to the left and right,
since occluded pixels belong to the background (the left-edge band is refilled from its right), and a weighted
median guided by the image cleans the filled areas.
Everything is vectorised numpy except the scanline recursion, which loops over one image axis.
"""

from dataclasses import dataclass

import cv2
import numpy as np

from ..io.images import to_gray
from ..progress import progress


@dataclass(frozen=True)
class BestConfig:
    """census_size: (width, height) of the census window; gradient_weight: weight of the gradient cost against
    census bits; p1/p2: SGM penalties in cost units (p2 divided by 1 + |dI|/p2_edge across intensity edges);
    lr_threshold: max left-right disagreement (px); speckle_size/speckle_diff: blobs of at most that many pixels
    (neighbours within speckle_diff px) are removed after the check (size 0 disables); median_radius/median_sigma:
    weighted-median filter after filling (radius 0 disables); fill_holes: fill occlusions and mismatches (False
    leaves them NaN).
    Defaults were chosen on Motorcycle and checked on Cones (docs/stereo.md)."""

    min_disparity: int = 0
    num_disparities: int = 64
    census_size: tuple[int, int] = (9, 7)
    gradient_weight: float = 1.0
    gradient_cap: float = 20.0
    p1: float = 10.0
    p2: float = 56.0
    p2_edge: float = 16.0
    lr_threshold: float = 1.0
    speckle_size: int = 20
    speckle_diff: float = 1.0
    fill_holes: bool = True
    median_radius: int = 7
    median_sigma: float = 25.5


def census_transform(gray: np.ndarray, size: tuple[int, int] = (9, 7)) -> np.ndarray:
    """uint64 bit string per pixel: bit k set where neighbour k is darker than the centre (reflected borders)."""
    w, h = size
    if w * h - 1 > 64:
        raise ValueError(f"census window {w}x{h} needs more than 64 bits")
    g = np.asarray(gray, dtype=np.float32)
    rx, ry = w // 2, h // 2
    padded = np.pad(g, ((ry, ry), (rx, rx)), mode="reflect")
    H, W = g.shape
    code = np.zeros((H, W), dtype=np.uint64)
    bit = 0
    for dy in range(h):
        for dx in range(w):
            if dy == ry and dx == rx:
                continue
            code |= (padded[dy:dy + H, dx:dx + W] < g).astype(np.uint64) << np.uint64(bit)
            bit += 1
    return code


def cost_volume(left: np.ndarray, right: np.ndarray, config: BestConfig) -> np.ndarray:
    """(H, W, D) float32 matching cost: census Hamming distance + gradient_weight * capped |dI/dx| difference.

    Pixels whose match falls outside the right image (x - d < 0) get the cost against the right image's border
    column: a real comparison, so at the left edge the range d > x collapses onto it and can win there (wrong
    matches that `remove_speckles` and `clear_left_border` take out)."""
    gl, gr = to_gray(left, np.float32), to_gray(right, np.float32)
    cl, cr = census_transform(gl, config.census_size), census_transform(gr, config.census_size)
    gxl = np.gradient(gl, axis=1)
    gxr = np.gradient(gr, axis=1)
    H, W = gl.shape
    D = config.num_disparities
    volume = np.empty((H, W, D), dtype=np.float32)
    for i in progress(range(D), desc="census cost", unit="disparity"):
        d = config.min_disparity + i
        xs = np.clip(np.arange(W) - d, 0, W - 1)
        ham = np.bitwise_count(cl ^ cr[:, xs]).astype(np.float32)
        grad = np.minimum(np.abs(gxl - gxr[:, xs]), config.gradient_cap)
        volume[:, :, i] = ham + config.gradient_weight * grad
    return volume


def _path_step(cost, prev, p1, p2):
    """One SGM recursion step for a line of pixels: cost (N,D), prev (N,D) aggregated costs, p2 (N,1)."""
    prev_min = prev.min(axis=1, keepdims=True)
    best = np.minimum(prev, prev_min + p2)
    best[:, 1:] = np.minimum(best[:, 1:], prev[:, :-1] + p1)
    best[:, :-1] = np.minimum(best[:, :-1], prev[:, 1:] + p1)
    return cost + best - prev_min


def sgm_aggregate(volume: np.ndarray, gray: np.ndarray, config: BestConfig) -> np.ndarray:
    """Sum of the 8 directional SGM path costs (H, W, D)."""
    H, W, D = volume.shape
    g = np.asarray(gray, dtype=np.float32)
    total = np.zeros_like(volume)
    p1 = np.float32(config.p1)

    def penalty(diff):
        return np.maximum(np.float32(config.p2) / (1 + np.abs(diff)[:, None] / config.p2_edge), p1).astype(np.float32)

    bar = progress(total=2 * W + 6 * H, desc="SGM paths", unit="line")  # the longest part of `best`
    # Horizontal paths: march over columns, all rows at once.
    for step in (1, -1):
        cols = range(W) if step == 1 else range(W - 1, -1, -1)
        prev = None
        for x in cols:
            if prev is None:
                cur = volume[:, x, :].copy()
            else:
                cur = _path_step(volume[:, x, :], prev, p1, penalty(g[:, x] - g[:, x - step]))
            total[:, x, :] += cur
            prev = cur
            bar.update()
    # Vertical and diagonal paths: march over rows, all columns at once; dx shifts the predecessor column.
    for dy in (1, -1):
        for dx in (0, 1, -1):
            rows = range(H) if dy == 1 else range(H - 1, -1, -1)
            prev = None
            for y in rows:
                if prev is None:
                    cur = volume[y].copy()
                else:
                    shifted = np.zeros_like(prev)
                    gprev = np.empty(W, dtype=np.float32)
                    if dx == 0:
                        shifted[:] = prev
                        gprev[:] = g[y - dy]
                    elif dx == 1:  # predecessor at x - 1
                        shifted[1:] = prev[:-1]
                        gprev[1:] = g[y - dy, :-1]
                        gprev[0] = g[y, 0]
                    else:  # predecessor at x + 1
                        shifted[:-1] = prev[1:]
                        gprev[:-1] = g[y - dy, 1:]
                        gprev[-1] = g[y, -1]
                    cur = _path_step(volume[y], shifted, p1, penalty(g[y] - gprev))
                    if dx == 1:  # the first column has no predecessor: restart the path there
                        cur[0] = volume[y, 0]
                    elif dx == -1:
                        cur[-1] = volume[y, -1]
                total[y] += cur
                prev = cur
                bar.update()
    bar.close()
    return total


def _subpixel(aggregated, index) -> np.ndarray:
    """Parabola through the costs at index-1, index, index+1 (index on the border stays integer)."""
    D = aggregated.shape[2]
    i = np.clip(index, 1, D - 2)
    c0 = np.take_along_axis(aggregated, (i - 1)[..., None], axis=2)[..., 0]
    c1 = np.take_along_axis(aggregated, i[..., None], axis=2)[..., 0]
    c2 = np.take_along_axis(aggregated, (i + 1)[..., None], axis=2)[..., 0]
    denom = c0 - 2 * c1 + c2
    offset = np.where(denom > 1e-6, (c0 - c2) / (2 * np.maximum(denom, 1e-6)), 0.0)
    inner = (index > 0) & (index < D - 1)
    return index + np.where(inner, np.clip(offset, -0.5, 0.5), 0.0)


def right_disparity(aggregated: np.ndarray, min_disparity: int) -> np.ndarray:
    """Integer disparity of the right image from the left costs: argmin over d of S_L(y, x + d, d), found with a
    running minimum over d instead of building a second cost volume. Pixels with no candidate get NaN."""
    H, W, D = aggregated.shape
    best_cost = np.full((H, W), np.inf, dtype=np.float32)
    best_d = np.full((H, W), np.nan, dtype=np.float32)
    for i in progress(range(D), desc="right disparities", unit="disparity"):
        d = min_disparity + i
        if d >= W or -d >= W:
            continue
        xr = slice(0, W - d) if d >= 0 else slice(-d, W)  # right-image columns x with x + d inside the left image
        xl = slice(d, W) if d >= 0 else slice(0, W + d)
        cost = aggregated[:, xl, i]
        better = cost < best_cost[:, xr]
        best_cost[:, xr] = np.where(better, cost, best_cost[:, xr])
        best_d[:, xr] = np.where(better, np.float32(d), best_d[:, xr])
    return best_d


def left_right_check(disp_left: np.ndarray, disp_right: np.ndarray, threshold: float) -> np.ndarray:
    """Mask of left pixels whose disparity agrees with the right map at x - d within threshold."""
    H, W = disp_left.shape
    xs = np.arange(W)[None, :] - np.round(disp_left).astype(int)
    inside = (xs >= 0) & (xs < W)
    xs = np.clip(xs, 0, W - 1)
    dr = np.take_along_axis(disp_right, xs, axis=1)
    return inside & (np.abs(disp_left - dr) <= threshold)


def _nearest_valid_right(d) -> np.ndarray:
    """For every pixel, the disparity of the nearest valid pixel at or to its right on the row (NaN if none)."""
    H, W = d.shape
    idx = np.where(np.isfinite(d), np.arange(W)[None, :], W)
    right_idx = np.minimum.accumulate(idx[:, ::-1], axis=1)[:, ::-1]
    return np.where(right_idx < W, d[np.arange(H)[:, None], np.clip(right_idx, 0, W - 1)], np.nan)


def remove_speckles(disparity: np.ndarray, size: int, max_diff: float) -> np.ndarray:
    """NaN over blobs of at most `size` pixels whose neighbours differ by at most `max_diff` (OpenCV's
    filterSpeckles on 1/16 px): small islands that passed the left-right check are wrong matches, and in the
    left-edge band a chain of them would stop `clear_left_border`'s run (Motorcycle: disparities 0 at columns 0-5)."""
    d = np.asarray(disparity, dtype=np.float32)
    if size <= 0:
        return d
    hole = np.iinfo(np.int16).min  # disparities stay within +-2047 px: a wider range has no cost volume in memory
    fixed = np.where(np.isfinite(d), np.round(np.clip(d, -2047, 2047) * 16), hole).astype(np.int16)
    cv2.filterSpeckles(fixed, hole, size, max(1, round(16 * max_diff)))
    return np.where(fixed == hole, np.nan, d).astype(np.float32)


def clear_left_border(disparity: np.ndarray) -> np.ndarray:
    """NaN over the band at the left edge that the right camera cannot see.

    A pixel at column x next to a surface of disparity d > x on its right could not test that surface (x - d < 0
    is outside the right image), so whatever matched there (often a small, wrong disparity that passed the
    left-right check by chance) is removed; hole filling then extends the surface from the right. The band is the
    run of such pixels that starts at column 0. The surface is the nearest valid pixel strictly to the right: a
    pixel's own wrong disparity (0 at column 0) must not vouch for itself."""
    d = np.asarray(disparity, dtype=np.float32)
    ref = np.full_like(d, np.nan)
    ref[:, :-1] = _nearest_valid_right(d)[:, 1:]
    with np.errstate(invalid="ignore"):
        band = np.logical_and.accumulate(np.arange(d.shape[1])[None, :] < ref, axis=1)
    return np.where(band, np.nan, d).astype(np.float32)


def fill_holes_background(disparity: np.ndarray) -> np.ndarray:
    """Fill NaN pixels with the smaller of the nearest valid disparities to their left and right on the row."""
    d = np.asarray(disparity, dtype=np.float32)
    H, W = d.shape
    valid = np.isfinite(d)
    idx = np.where(valid, np.arange(W)[None, :], -1)
    left_idx = np.maximum.accumulate(idx, axis=1)
    rows = np.arange(H)[:, None]
    left_val = np.where(left_idx >= 0, d[rows, np.clip(left_idx, 0, W - 1)], np.inf)
    right_val = np.nan_to_num(_nearest_valid_right(d), nan=np.inf)
    filled = np.where(valid, d, np.minimum(left_val, right_val))
    return np.where(np.isfinite(filled), filled, np.nan).astype(np.float32)


def weighted_median(disparity: np.ndarray, guide: np.ndarray, radius: int, sigma: float) -> np.ndarray:
    """Edge-aware weighted median of the disparity (OpenCV ximgproc), guided by the left image in grey: with a
    colour guide OpenCV 5.0's filter gives different results from run to run on the same input (58 % of the
    pixels of a random map, by up to 30 px); in grey it is repeatable (Motorcycle bad-2 6.58 against
    6.32-6.34 in colour, before the speckle filter)."""
    d = np.nan_to_num(np.asarray(disparity, dtype=np.float32), nan=0.0)
    guide8 = to_gray(np.clip(np.asarray(guide), 0, 255).astype(np.uint8))
    return cv2.ximgproc.weightedMedianFilter(guide8, d, radius, sigma)


def best_disparity(left: np.ndarray, right: np.ndarray, config: BestConfig = BestConfig()) -> np.ndarray:
    """float32 disparity of the left image; NaN holes only when fill_holes is False."""
    gray = to_gray(left, np.float32)
    aggregated = sgm_aggregate(cost_volume(left, right, config), gray, config)
    index_l = np.argmin(aggregated, axis=2)
    disp_l = _subpixel(aggregated, index_l) + config.min_disparity
    keep = left_right_check(disp_l, right_disparity(aggregated, config.min_disparity), config.lr_threshold)
    disparity = np.where(keep, disp_l, np.nan).astype(np.float32)
    disparity = clear_left_border(remove_speckles(disparity, config.speckle_size, config.speckle_diff))
    if not config.fill_holes:
        return disparity
    disparity = fill_holes_background(disparity)
    if config.median_radius > 0:
        guide = np.asarray(left)
        disparity = weighted_median(disparity, guide, config.median_radius, config.median_sigma)
    return disparity.astype(np.float32)
