"""Dense heights from stereo matching of rectified tilt pairs, and their robust combination.

Under parallel projection a tilt pair is rectified by a rotation that turns the tilt axis vertical (rectified
rows run along the axis, columns along the parallax direction) and, for the second view, a stretch by
cos(t1) / cos(t2) across the axis; the disparity is then proportional to the height:
d = h sin(t1 - t2) / cos(t2). Any rectified-stereo matcher applies; `pair_heights` runs the stereo module's
`best` (census + semi-global matching, left-right check) or OpenCV's SGBM. World frame, units and signs: see
`parallax.py`.

Integer-based matchers lock onto whole disparities, and a tilt step of 5-10 degrees gives little disparity per
pixel of height (0.09-0.17 px), so these maps are a start for the sub-pixel least-squares refinement of
`dense.py`, not a result: on sem_tilt_small the combined `best` map is 4.9 % of the height range off (RMS),
with contour-shaped errors where the true disparity crosses half-integers.
"""

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ..stereo.best import BestConfig, best_disparity
from ..stereo.sgbm import SGBMConfig, sgbm_disparity
from .parallax import axis_vectors


@dataclass(frozen=True)
class StereoConfig:
    """margin_px: disparity search beyond the range the sparse points span (image pixels). tolerance_px: two
    pairs agree at a pixel when their heights differ by at most this much disparity of each pair.
    max_cost_cells: the semi-global matcher holds a (rows, columns, disparities) cost volume twice; larger
    problems are matched on images shrunk to fit (a start for sub-pixel refinement needs no full resolution).
    matcher: the `best` matcher's settings, holes kept (a pair that did not match a pixel has no say there)."""

    margin_px: float = 3.0
    tolerance_px: float = 1.0
    max_cost_cells: int = 40_000_000
    matcher: BestConfig = field(default_factory=lambda: BestConfig(fill_holes=False, median_radius=0))


def disparity_per_height(tilt1: float, tilt2: float) -> float:
    """Rectified disparity (pixels) per pixel of height for views at tilt1 (left) and tilt2 (right), degrees."""
    t1, t2 = np.radians(tilt1), np.radians(tilt2)
    return float(np.sin(t1 - t2) / np.cos(t2))


def _frame(shape, axis_deg):
    """Rectified frame that holds the whole image: its (rows, columns) and the rectified pixel of the image
    centre."""
    h, w = shape
    a, n = axis_vectors(axis_deg)
    corners = np.array([[x, y] for x in (-(w - 1) / 2, (w - 1) / 2) for y in (-(h - 1) / 2, (h - 1) / 2)])
    cols = int(np.ceil(np.ptp(corners @ n))) + 1
    rows = int(np.ceil(np.ptp(corners @ a))) + 1
    return (rows, cols), np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])


def _rectify(image, axis_deg, frame, stretch, shift):
    """(rectified float32 image, mask of rectified pixels inside the image): rectified pixel (k, r) reads image
    pixel c + shift + stretch (k - kc) n + (r - rc) a."""
    (rows, cols), centre_r = frame
    h, w = image.shape
    a, n = axis_vectors(axis_deg)
    A = np.column_stack([stretch * n, a])
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    M = np.hstack([A, (centre + np.asarray(shift, float) - A @ centre_r)[:, None]])
    flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
    out = cv2.warpAffine(image.astype(np.float32), M, (cols, rows), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    inside = cv2.warpAffine(np.ones((h, w), np.float32), M, (cols, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0.999
    return out, inside


def _disparity(left, right, lo: int, hi: int, matcher) -> np.ndarray:
    """Disparity (NaN = unmatched) searched over lo..hi by the `best` matcher or OpenCV's SGBM (8-bit input)."""
    if isinstance(matcher, SGBMConfig):
        to8 = lambda im: np.clip(np.round(im), 0, 255).astype(np.uint8)  # noqa: E731
        return sgbm_disparity(to8(left), to8(right), replace(matcher, min_disparity=lo, num_disparities=hi - lo + 1))
    return best_disparity(left, right, replace(matcher, min_disparity=lo, num_disparities=hi - lo + 1))


def pair_heights(image1: np.ndarray, image2: np.ndarray, tilt1: float, tilt2: float, axis_deg: float,
                 shift1: np.ndarray, shift2: np.ndarray, height_range: tuple[float, float] | np.ndarray,
                 matcher: BestConfig | SGBMConfig, margin_px: float = 3.0) -> np.ndarray:
    """float32 height map of the world (0-degree) grid in image pixels, NaN where the pair did not match: view 1
    rectified as the left image, view 2 (stretched) as the right one. shift1/shift2 are the views' drifts from
    the joint solution, so heights share its gauge; height_range (lo, hi) bounds the disparity search, widened
    by margin_px of disparity. matcher: a `BestConfig` or an `SGBMConfig`."""
    h, w = image1.shape
    frame = _frame((h, w), axis_deg)
    (rows, cols), centre_r = frame
    t1, t2 = np.radians(tilt1), np.radians(tilt2)
    left, in_left = _rectify(image1, axis_deg, frame, 1.0, shift1)
    right, _ = _rectify(image2, axis_deg, frame, np.cos(t2) / np.cos(t1), shift2)
    per_height = disparity_per_height(tilt1, tilt2)
    ends = np.sort(np.asarray(height_range, float) * per_height)
    lo, hi = int(np.floor(ends[0] - margin_px)), int(np.ceil(ends[1] + margin_px))
    disparity = _disparity(left, right, lo, hi, matcher)
    height = np.where(in_left & (disparity >= lo), disparity / per_height, np.nan)
    # rectified column k of view 1 sees p1 = alpha cos t1 + h sin t1: resample each row onto alpha (the world grid)
    p = np.arange(cols) - centre_r[0]
    rect = np.full((rows, cols), np.nan, np.float32)
    for row in range(rows):
        ok = np.isfinite(height[row])
        if ok.sum() < 2:
            continue
        alpha = (p[ok] - height[row, ok] * np.sin(t1)) / np.cos(t1)
        order = np.argsort(alpha, kind="stable")
        values = np.interp(p, alpha[order], height[row, ok][order], left=np.nan, right=np.nan)
        near = np.convolve(ok.astype(float), np.ones(5), mode="same") > 0  # no bridging of unmatched runs
        rect[row] = np.where(near, values, np.nan)
    # back to the world grid: image offset x - c = (k - kc) n + (r - rc) a
    a, n = axis_vectors(axis_deg)
    B = np.vstack([n, a])
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    M = np.hstack([B, (centre_r - B @ centre)[:, None]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    valid = cv2.warpAffine(np.isfinite(rect).astype(np.float32), M, (w, h), flags=flags)
    out = cv2.warpAffine(np.nan_to_num(rect, nan=0.0), M, (w, h), flags=flags)
    return np.where(valid > 0.999, out, np.nan).astype(np.float32)


def combine_pairs(maps: list[np.ndarray], disparity_scales: list[float],
                  tolerance_px: float = 1.0) -> np.ndarray:
    """One height map from several pairs' maps (NaN = unmatched): per pixel the median weighted by each pair's
    precision (disparity_scale^2, its disparity per pixel of height), then the weighted mean of the pairs within
    tolerance_px of disparity of that median. A pixel needs two agreeing pairs (one when there is one pair): a
    wrong match rarely repeats in another pair, and one pair alone leaves isolated wrong matches on textureless
    ground (spikes on the Karido DSA background)."""
    stack = np.asarray(maps, np.float32)
    scale = np.abs(np.asarray(disparity_scales, np.float32))[:, None, None]
    present = np.isfinite(stack)
    weight = np.where(present, scale * scale, 0.0)
    order = np.argsort(np.where(present, stack, np.inf), axis=0)
    cumulative = np.cumsum(np.take_along_axis(weight, order, axis=0), axis=0)
    middle = np.argmax(cumulative >= 0.5 * cumulative[-1:], axis=0)
    median = np.take_along_axis(np.take_along_axis(stack, order, axis=0), middle[None], axis=0)[0]
    with np.errstate(invalid="ignore"):
        agree = present & (np.abs(stack - median) * scale <= tolerance_px)
    kept = np.where(agree, weight, 0.0)
    total = kept.sum(axis=0)
    mean = (np.where(agree, stack, 0.0) * kept).sum(axis=0) / np.maximum(total, 1e-12)
    enough = agree.sum(axis=0) >= min(2, len(stack))
    return np.where(enough & (total > 0), mean, np.nan).astype(np.float32)


def stereo_heights(images: list[np.ndarray], tilts_deg: np.ndarray, axis_deg: float, shifts: np.ndarray,
                   reference: int, height_range: tuple[float, float],
                   config: StereoConfig = StereoConfig()) -> tuple[np.ndarray, dict]:
    """Height map of the world grid (image pixels; NaN where no pair matched or the pairs disagree) from the pairs
    (reference, j) of every view j tilted away from the reference, matched by `best` and combined by
    `combine_pairs`; and a report (pairs, matched fraction of each, combined fraction, working scale)."""
    h, w = images[reference].shape
    others = [j for j in range(len(images)) if j != reference
              and abs(disparity_per_height(tilts_deg[reference], tilts_deg[j])) > 1e-3]
    if not others:
        return np.full((h, w), np.nan, np.float32), {"pairs": []}
    # shrink so the largest cost volume fits: cells scale with the cube of the image scale
    widest = max(abs(disparity_per_height(tilts_deg[reference], tilts_deg[j])) for j in others)
    disparities = widest * (height_range[1] - height_range[0]) + 2 * config.margin_px + 1
    frame_cells = np.prod(_frame((h, w), axis_deg)[0])
    scale = float(min(1.0, (config.max_cost_cells / (frame_cells * disparities)) ** (1 / 3)))
    size = (max(16, round(w * scale)), max(16, round(h * scale)))
    small = [im if scale == 1.0 else cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in images]
    s = size[0] / w if scale < 1.0 else 1.0
    maps, scales, report = [], [], {"pairs": [], "scale": s}
    for j in others:
        m = pair_heights(small[reference], small[j], tilts_deg[reference], tilts_deg[j], axis_deg,
                         np.asarray(shifts[reference]) * s, np.asarray(shifts[j]) * s,
                         np.asarray(height_range, float) * s, config.matcher, config.margin_px)
        if s != 1.0:
            m = cv2.resize(m, (w, h), interpolation=cv2.INTER_NEAREST) / s
        maps.append(m)
        scales.append(disparity_per_height(tilts_deg[reference], tilts_deg[j]) * s)
        report["pairs"].append({"pair": [reference, j], "matched_fraction": float(np.isfinite(m).mean())})
    combined = combine_pairs(maps, scales, config.tolerance_px)
    report["combined_fraction"] = float(np.isfinite(combined).mean())
    return combined, report
