"""Keypoint refinement across views: every verified track's keypoints moved onto its finest observation.

`refine_keypoints(keypoints, images, pairs)` groups the verified matches into tracks (connected components of
keypoints), and in each track aligns every keypoint's patch to the patch of the track's finest-scale keypoint
(the reference), sampled in each image at the keypoint's own scale and orientation (the SIFT frames' relative
similarity), by Gauss-Newton steps on a sub-pixel translation with a gain and bias of the intensities
(Lucas-Kanade). It is the idea of Pixel-Perfect SfM's keypoint adjustment with image intensities instead of
learned features: a coarse-scale DoG extremum sits where the blob's centre is, which perspective moves away
from the projection of the point that the fine-scale extremum of another view marks.

A keypoint keeps its position when its track holds two keypoints of one image (an inconsistent track), when its
alignment does not converge, moves more than `max_shift` of its scale, or ends with a normalised correlation
below `min_correlation`.
"""

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..config import bounded
from ..io.images import to_gray

_LEVELS = 8  # octaves: patch samples up to 256 pixels apart
_STEPS = 3  # scale-space steps an octave


@dataclass(frozen=True)
class RefineConfig:
    enabled: bool = True  # refine after matching (`--refine-keypoints` / `--no-refine-keypoints`)
    patch_size: int = bounded(13, 3)  # samples a side of the square patch
    patch_radius: float = bounded(3.0, 0.5)  # the patch's half-width in units of the keypoint's scale (sigma)
    min_radius: float = bounded(8.0, 0.0)  # smallest half-width of the reference's patch, in pixels
    iterations: int = bounded(10, 1)  # Gauss-Newton steps at most
    max_shift: float = bounded(1.0, 0.0, low_open=True)  # largest move, in units of the keypoint's scale
    min_correlation: float = bounded(0.8, -1.0)  # normalised correlation with the reference after alignment
    blur: float = bounded(1.0, 0.0)  # Gaussian sigma of the sampled image, in units of the patch's sample spacing
    min_scale: float = bounded(0.0, 0.0)  # finer keypoints (sigma in pixels) keep their detected positions
    max_track: int = bounded(200, 2)  # larger tracks are left as they are (a repeated texture merges tracks)


def tracks(num_keypoints: dict[int, int], pairs: list[tuple[int, int, np.ndarray]]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Connected components of the verified matches: (image id, keypoint index, component label) of every
    matched keypoint, sorted by component."""
    ids = sorted(num_keypoints)
    offset, total = {}, 0
    for i in ids:
        offset[i] = total
        total += num_keypoints[i]
    rows = [offset[i] + m[:, 0] for i, _, m in pairs if len(m)]
    cols = [offset[j] + m[:, 1] for _, j, m in pairs if len(m)]
    if not rows:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(total, total))
    _, labels = connected_components(graph, directed=False)
    matched = np.zeros(total, bool)
    matched[r] = matched[c] = True
    nodes = np.flatnonzero(matched)
    starts = np.array([offset[i] for i in ids], np.int64)
    where = np.searchsorted(starts, nodes, side="right") - 1
    image = np.array(ids, np.int64)[where]
    index = nodes - starts[where]
    order = np.argsort(labels[nodes], kind="stable")
    return image[order], index[order], labels[nodes][order]


def scale_space(gray: np.ndarray, config: RefineConfig) -> list[tuple[np.ndarray, float]]:
    """(image, pixel size in full-size pixels) of every step of a scale space of `_STEPS` steps an octave: step
    b's patch samples are 2^(b/_STEPS) full-size pixels apart, and its image is blurred to `config.blur` times
    that spacing, so that two views' patches of one point carry the same blur whatever their scales."""
    import cv2  # noqa: PLC0415 - as features/sift.py: loaded where it is used

    out, level = [], np.ascontiguousarray(gray, np.float32)
    for octave in range(_LEVELS):
        for step in range(_STEPS):
            spacing = 2.0 ** (step / _STEPS)  # in this octave's pixels
            # a pyrDown level already carries about 0.8 pixel of blur (the sensor's, on the finest)
            sigma = np.sqrt(max((config.blur * spacing) ** 2 - 0.8 ** 2, 0.0))
            out.append((cv2.GaussianBlur(level, (0, 0), sigma) if sigma > 0.05 else level, float(2 ** octave)))
        if min(level.shape) < 32:
            break
        level = cv2.pyrDown(level)
    return out


def _level(scale: np.ndarray, config: RefineConfig, steps: int) -> np.ndarray:
    """The step of the scale space whose sample spacing is the patch's (rounded down)."""
    spacing = 2 * config.patch_radius * scale / (config.patch_size - 1)
    return np.clip(np.floor(np.log2(np.maximum(spacing, 1e-6)) * _STEPS + 1e-9), 0, steps - 1).astype(np.int64)


def refine_keypoints(keypoints: dict[int, np.ndarray], load: Callable[[int], np.ndarray],
                     pairs: list[tuple[int, int, np.ndarray]], config: RefineConfig = RefineConfig()
                     ) -> tuple[dict[int, np.ndarray], int]:
    """Keypoints (N,4+: x, y in COLMAP pixels, scale, orientation) of every image with the positions of its
    tracks' keypoints refined, and the number moved. `load(image id)`: the image (full size, grey or colour, 8
    or 16 bit), called twice an image (one image's pyramid in memory at a time); `pairs`: (image id 1, image
    id 2, (K,2) verified inlier keypoint indices)."""
    image, index, label = tracks({i: len(k) for i, k in keypoints.items()}, pairs)
    out = {i: np.array(k, np.float64, copy=True) for i, k in keypoints.items()}
    if not len(label):
        return out, 0
    n = len(label)
    starts = np.flatnonzero(np.r_[True, label[1:] != label[:-1]])
    sizes = np.diff(np.r_[starts, n])
    # consistent tracks: one keypoint an image, not too many
    ok = sizes <= config.max_track
    by_image = np.lexsort((image, label))
    twice = (label[by_image][1:] == label[by_image][:-1]) & (image[by_image][1:] == image[by_image][:-1])
    ok[np.searchsorted(starts, by_image[1:][twice], side="right") - 1] = False
    scale = np.array([keypoints[i][j, 2] for i, j in zip(image, index)], np.float64)
    # the reference of each track: its finest keypoint
    finest = np.lexsort((scale, label))[starts]  # rows are sorted by label, so each track's first by scale
    ref = np.repeat(finest, sizes)
    use = np.repeat(ok, sizes) & (ref != np.arange(n)) & (scale >= config.min_scale)
    if not use.any():
        return out, 0
    frame = np.array([keypoints[i][j, :4] for i, j in zip(image, index)], np.float64)
    # a track's patches cover at least min_radius pixels around its reference: a fine blob's own patch holds
    # too little texture to fix a position to a tenth of a pixel
    frame[:, 2] *= np.maximum(1.0, config.min_radius / (config.patch_radius * scale[ref]))
    grid = _grid(config)
    weights = np.exp(-0.5 * (grid ** 2).sum(axis=1) / (config.patch_radius / 2) ** 2)
    # the reference patches, sampled once, then every other keypoint aligned to its reference's
    refs = np.unique(ref[use])
    ref_patch = np.zeros((n, len(grid)), np.float64)
    for i in np.unique(image[refs]):
        levels = scale_space(_gray(load(int(i))), config)
        sel = refs[image[refs] == i]
        lev = _level(frame[sel, 2], config, len(levels))
        for L in np.unique(lev):
            these = sel[lev == L]
            ref_patch[these] = _sample(levels[L][0], frame[these], grid, levels[L][1])
    moved = 0
    todo = np.flatnonzero(use)
    for i in np.unique(image[todo]):
        levels = scale_space(_gray(load(int(i))), config)
        sel = todo[image[todo] == i]
        lev = _level(frame[sel, 2], config, len(levels))
        for L in np.unique(lev):
            these = sel[lev == L]
            shift, corr, converged = _align(levels[L][0], frame[these], ref_patch[ref[these]], grid, weights,
                                            levels[L][1], config.iterations)
            good = (converged & (corr >= config.min_correlation)
                    & (np.hypot(shift[:, 0], shift[:, 1]) <= config.max_shift * scale[these]))
            out[int(i)][index[these[good]], :2] += shift[good]
            moved += int(good.sum())
    return out, moved


def _gray(image: np.ndarray) -> np.ndarray:
    """Grey float32 on [0, 1] of an 8/16-bit grey, RGB or RGBA image."""
    return to_gray(image, np.float32)


def _grid(config: RefineConfig) -> np.ndarray:
    """(n,2) sample offsets of a patch in units of the keypoint's scale."""
    t = np.linspace(-config.patch_radius, config.patch_radius, config.patch_size)
    u, v = np.meshgrid(t, t)
    return np.stack([u.ravel(), v.ravel()], axis=1)


@numba.njit(cache=True)
def _bilinear(img, x, y):
    """Value and gradient (per level pixel) at (x, y) in OpenCV's convention (pixel centres on integers),
    clamped at the border; nan outside."""
    h, w = img.shape
    if not (0.0 <= x <= w - 1.0 and 0.0 <= y <= h - 1.0):
        return np.nan, 0.0, 0.0
    x0 = min(int(x), w - 2)
    y0 = min(int(y), h - 2)
    ax, ay = x - x0, y - y0
    a, b = img[y0, x0], img[y0, x0 + 1]
    c, d = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    top, bottom = a + (b - a) * ax, c + (d - c) * ax
    value = top + (bottom - top) * ay
    gx = (b - a) * (1.0 - ay) + (d - c) * ay
    gy = bottom - top
    return value, gx, gy


@numba.njit(cache=True)
def _sample_one(img, x, y, s, angle, deform, grid, factor, out, gx, gy, qx, qy):
    """A patch around (x, y) (COLMAP pixels, full size) at scale s and orientation angle (OpenCV's), its offsets
    q deformed by (I + deform) (a 2x2 affine correction), on a level `factor` times smaller: values, gradients
    per full-size pixel, and the offsets q. False if a sample falls outside."""
    ca, sa = np.cos(angle), np.sin(angle)
    for k in range(grid.shape[0]):
        u, v = grid[k, 0] * s, grid[k, 1] * s
        ox, oy = ca * u - sa * v, sa * u + ca * v
        px = x + ox + deform[0] * ox + deform[1] * oy
        py = y + oy + deform[2] * ox + deform[3] * oy
        val, dx, dy = _bilinear(img, (px - 0.5) / factor, (py - 0.5) / factor)
        if np.isnan(val):
            return False
        out[k], gx[k], gy[k], qx[k], qy[k] = val, dx / factor, dy / factor, ox, oy
    return True


@numba.njit(cache=True)
def _sample_all(img, frames, grid, factor):
    n, m = frames.shape[0], grid.shape[0]
    out = np.full((n, m), np.nan)
    gx, gy, qx, qy = np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m)
    deform = np.zeros(4)
    for i in range(n):
        row = np.zeros(m)
        if _sample_one(img, frames[i, 0], frames[i, 1], frames[i, 2], frames[i, 3], deform, grid, factor, row, gx,
                       gy, qx, qy):
            out[i] = row
    return out


def _sample(img: np.ndarray, frames: np.ndarray, grid: np.ndarray, factor: float) -> np.ndarray:
    """(n, samples) patches of keypoint frames (x, y, scale, orientation); rows of nan where outside."""
    return _sample_all(img, np.ascontiguousarray(frames, np.float64), grid, factor)


@numba.njit(cache=True)
def _align(img, frames, refs, grid, weights, factor, iterations):
    """Per keypoint: the translation (full-size pixels) that best aligns its patch to its reference patch, with
    an affine correction of the patch's shape (the SIFT frames' scale and orientation are estimates, and
    perspective shears the patch) and a gain and bias of the intensities (weighted least squares,
    Gauss-Newton); the normalised correlation after it; converged."""
    n, m = frames.shape[0], grid.shape[0]
    shift = np.zeros((n, 2))
    corr = np.full(n, -1.0)
    converged = np.zeros(n, np.bool_)
    val, gx, gy, qx, qy = np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m), np.zeros(m)
    A = np.zeros((8, 8))
    rhs = np.zeros(8)
    jac = np.zeros(8)
    deform = np.zeros(4)
    for i in range(n):
        ref = refs[i]
        if np.isnan(ref[0]):
            continue
        tx, ty, gain, bias = 0.0, 0.0, 1.0, 0.0
        deform[:] = 0.0
        inside = True
        for it in range(iterations):
            if not _sample_one(img, frames[i, 0] + tx, frames[i, 1] + ty, frames[i, 2], frames[i, 3], deform, grid,
                               factor, val, gx, gy, qx, qy):
                inside = False
                break
            if it == 0:  # start from the gain and bias of the two patches' means and spreads
                mv, mr = 0.0, 0.0
                for k in range(m):
                    mv += val[k]
                    mr += ref[k]
                mv /= m
                mr /= m
                sv, sr = 0.0, 0.0
                for k in range(m):
                    sv += (val[k] - mv) ** 2
                    sr += (ref[k] - mr) ** 2
                if sv <= 1e-12 or sr <= 1e-12:
                    inside = False
                    break
                gain = np.sqrt(sr / sv)
                bias = mr - gain * mv
            A[:] = 0.0
            rhs[:] = 0.0
            for k in range(m):
                w = weights[k]
                r = gain * val[k] + bias - ref[k]
                jx, jy = gain * gx[k], gain * gy[k]
                jac[0], jac[1] = jx, jy
                jac[2], jac[3], jac[4], jac[5] = jx * qx[k], jx * qy[k], jy * qx[k], jy * qy[k]
                jac[6], jac[7] = val[k], 1.0
                for a in range(8):
                    rhs[a] -= w * jac[a] * r
                    for b in range(8):
                        A[a, b] += w * jac[a] * jac[b]
            for a in range(8):
                A[a, a] *= 1.0 + 1e-4
            try:
                step = np.linalg.solve(A, rhs)
            except Exception:  # noqa: BLE001 - a singular system: no texture
                inside = False
                break
            tx += step[0]
            ty += step[1]
            for a in range(4):
                deform[a] += step[2 + a]
            gain += step[6]
            bias += step[7]
            if step[0] * step[0] + step[1] * step[1] < 1e-4:
                converged[i] = True
                break
        if not inside or not converged[i]:
            converged[i] = False
            continue
        if not _sample_one(img, frames[i, 0] + tx, frames[i, 1] + ty, frames[i, 2], frames[i, 3], deform, grid,
                           factor, val, gx, gy, qx, qy):
            converged[i] = False
            continue
        # weighted normalised correlation of the aligned patch with the reference
        sw, mv, mr = 0.0, 0.0, 0.0
        for k in range(m):
            sw += weights[k]
            mv += weights[k] * val[k]
            mr += weights[k] * ref[k]
        mv /= sw
        mr /= sw
        cvr, cvv, crr = 0.0, 0.0, 0.0
        for k in range(m):
            cvr += weights[k] * (val[k] - mv) * (ref[k] - mr)
            cvv += weights[k] * (val[k] - mv) ** 2
            crr += weights[k] * (ref[k] - mr) ** 2
        corr[i] = cvr / np.sqrt(max(cvv * crr, 1e-24))
        shift[i, 0], shift[i, 1] = tx, ty
    return shift, corr, converged
