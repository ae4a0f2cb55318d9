"""SURF (Bay, Ess, Tuytelaars, Van Gool 2008): Fast-Hessian detector on an integral image and the SURF-64 descriptor.

The OpenCV wheel used here is built without the non-free module, so `cv2.xfeatures2d.SURF_create` raises
"patented"; `extract_surf` uses OpenCV's SURF when it exists and this implementation otherwise.

Detector: the determinant of the Hessian, with the second derivatives approximated by box filters evaluated in
constant time on the integral image (det = Dxx Dyy - (0.9 Dxy)^2, each response divided by the filter area, so the
threshold means the same as OpenCV's `hessianThreshold` on 8-bit images). Scale space is built by growing the
filter (9, 15, 21, 27 px, doubled every octave, OpenCV's layout) while the sampling step doubles per octave;
maxima over 3x3x3 neighbours are refined by a quadratic fit in (x, y, filter size); scale s = 1.2 L / 9.
Orientation: Haar responses (size 4s) at step s within radius 6s, Gaussian weighted (sigma 2.5s), summed in a
sliding 60-degree window; the longest sum gives the angle. Descriptor: a 20s square aligned with that angle, 4x4
sub-regions of 5x5 samples, Haar responses of size 2s rotated into the keypoint frame and weighted by a Gaussian
(sigma 3.3s); each sub-region gives (sum dx, sum dy, sum |dx|, sum |dy|); the 64 values are normalised to unit length.
All stages are vectorised over pixels or keypoints; there is no per-keypoint Python loop.
"""

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import maximum_filter

from ..io.images import to_gray

# Box layouts of the 9x9 filters (x0, y0, x1, y1, weight), the coordinates OpenCV and the paper use.
_DXX = ((0, 2, 3, 7, 1), (3, 2, 6, 7, -2), (6, 2, 9, 7, 1))
_DYY = ((2, 0, 7, 3, 1), (2, 3, 7, 6, -2), (2, 6, 7, 9, 1))
_DXY = ((1, 1, 4, 4, 1), (5, 1, 8, 4, -1), (1, 5, 4, 8, -1), (5, 5, 8, 8, 1))


@dataclass(frozen=True)
class SurfConfig:
    """hessian_threshold: minimum det(H) (8-bit intensity units, OpenCV's meaning); octaves and layers: scale
    space size (layers per octave, 4 = two usable middle layers); upright: skip orientation (U-SURF);
    max_features: keep the strongest responses (0 = all)."""

    hessian_threshold: float = 100.0
    octaves: int = 4
    layers: int = 4
    upright: bool = False
    max_features: int = 0


def integral_image(gray: np.ndarray) -> np.ndarray:
    """(H+1, W+1) float64 cumulative sums with a zero first row and column."""
    g = np.asarray(gray, dtype=np.float64)
    ii = np.zeros((g.shape[0] + 1, g.shape[1] + 1))
    ii[1:, 1:] = g.cumsum(0).cumsum(1)
    return ii


def box_sum(ii: np.ndarray, y0: np.ndarray | int, x0: np.ndarray | int, y1: np.ndarray | int,
            x1: np.ndarray | int) -> np.ndarray:
    """Sum over rows y0..y1-1, cols x0..x1-1 (arrays broadcast); coordinates are clipped into the image."""
    H, W = ii.shape[0] - 1, ii.shape[1] - 1
    y0, y1 = np.clip(y0, 0, H), np.clip(y1, 0, H)
    x0, x1 = np.clip(x0, 0, W), np.clip(x1, 0, W)
    return ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]


def _scaled_pattern(pattern, size: int):
    s = size / 9.0
    return [(int(round(x0 * s)), int(round(y0 * s)), int(round(x1 * s)), int(round(y1 * s)), w)
            for x0, y0, x1, y1, w in pattern]


def _filter(ii, cy, cx, size: int, pattern) -> np.ndarray:
    """Box-filter response at centres cy (ny,1) x cx (1,nx), normalised by the filter area."""
    top, left = cy - size // 2, cx - size // 2
    out = 0.0
    for x0, y0, x1, y1, w in _scaled_pattern(pattern, size):
        out = out + w * box_sum(ii, top + y0, left + x0, top + y1, left + x1)
    return out / float(size * size)


def hessian_responses(ii: np.ndarray, size: int, cy: np.ndarray,
                      cx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(det of the approximated Hessian, sign of its trace) on the centre grid."""
    dxx = _filter(ii, cy, cx, size, _DXX)
    dyy = _filter(ii, cy, cx, size, _DYY)
    dxy = _filter(ii, cy, cx, size, _DXY)
    return dxx * dyy - (0.9 * dxy) ** 2, np.sign(dxx + dyy)


def fast_hessian(gray: np.ndarray, config: SurfConfig = SurfConfig()) -> np.ndarray:
    """Keypoints (N, 5): x, y (pixel centres at integers), scale s, response det(H), Laplacian sign."""
    g = np.asarray(gray, dtype=np.float64)
    ii = integral_image(g)
    H, W = g.shape
    found = []
    for octave in range(config.octaves):
        step = 1 << octave
        sizes = [(9 + 6 * k) << octave for k in range(config.layers)]
        margin = sizes[-1] // 2 + step
        ys = np.arange(margin, H - margin, step)
        xs = np.arange(margin, W - margin, step)
        if len(ys) < 3 or len(xs) < 3:
            break
        stack = np.empty((len(sizes), len(ys), len(xs)))
        signs = np.empty_like(stack)
        for k, size in enumerate(sizes):
            stack[k], signs[k] = hessian_responses(ii, size, ys[:, None], xs[None, :])
        peaks = (stack == maximum_filter(stack, size=3, mode="constant", cval=-np.inf)) & (
            stack > config.hessian_threshold)
        peaks[0] = peaks[-1] = False
        peaks[:, 0] = peaks[:, -1] = False
        peaks[:, :, 0] = peaks[:, :, -1] = False
        k, i, j = np.nonzero(peaks)
        if len(k) == 0:
            continue
        offset, ok = _quadratic_offset(stack, k, i, j)
        size_step = 6 << octave
        # an even filter (every octave after the first) is centred half a pixel before the sample position
        centre = xs[j] - 0.5 * (np.asarray(sizes)[k] % 2 == 0), ys[i] - 0.5 * (np.asarray(sizes)[k] % 2 == 0)
        x = centre[0] + offset[:, 0] * step
        y = centre[1] + offset[:, 1] * step
        L = np.asarray(sizes)[k] + offset[:, 2] * size_step
        found.append(np.column_stack([x, y, 1.2 * L / 9.0, stack[k, i, j], signs[k, i, j]])[ok])
    if not found:
        return np.zeros((0, 5))
    kps = np.vstack(found)
    kps = kps[np.argsort(-kps[:, 3], kind="stable")]
    return kps[:config.max_features] if config.max_features > 0 else kps


def _quadratic_offset(stack, k, i, j) -> tuple[np.ndarray, np.ndarray]:
    """Sub-sample (dx, dy, dlayer) of each peak by Newton's step on a 3-D quadratic; ok = |offset| < 0.5 per axis
    (Brown & Lowe 2002), otherwise the peak is not localised well enough and is dropped."""
    def v(dk, di, dj):
        return stack[k + dk, i + di, j + dj]

    c = v(0, 0, 0)
    g = np.stack([(v(0, 0, 1) - v(0, 0, -1)) / 2, (v(0, 1, 0) - v(0, -1, 0)) / 2,
                  (v(1, 0, 0) - v(-1, 0, 0)) / 2], axis=1)
    dxx = v(0, 0, 1) + v(0, 0, -1) - 2 * c
    dyy = v(0, 1, 0) + v(0, -1, 0) - 2 * c
    dss = v(1, 0, 0) + v(-1, 0, 0) - 2 * c
    dxy = (v(0, 1, 1) - v(0, 1, -1) - v(0, -1, 1) + v(0, -1, -1)) / 4
    dxs = (v(1, 0, 1) - v(1, 0, -1) - v(-1, 0, 1) + v(-1, 0, -1)) / 4
    dys = (v(1, 1, 0) - v(1, -1, 0) - v(-1, 1, 0) + v(-1, -1, 0)) / 4
    Hm = np.stack([np.stack([dxx, dxy, dxs], -1), np.stack([dxy, dyy, dys], -1), np.stack([dxs, dys, dss], -1)], 1)
    det = np.linalg.det(Hm)
    good = np.abs(det) > 1e-12
    offset = np.zeros_like(g)
    offset[good] = -np.linalg.solve(Hm[good], g[good][..., None])[..., 0]
    ok = good & np.all(np.abs(offset) < 0.5, axis=1)
    return offset, ok


def haar(ii: np.ndarray, x: np.ndarray | float, y: np.ndarray | float,
         size: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Haar wavelet responses (dx, dy) of side `size` centred at (x, y); arrays broadcast."""
    half = np.maximum(np.round(size / 2).astype(int), 1)
    xi, yi = np.round(x).astype(int), np.round(y).astype(int)
    dx = box_sum(ii, yi - half, xi, yi + half, xi + half) - box_sum(ii, yi - half, xi - half, yi + half, xi)
    dy = box_sum(ii, yi, xi - half, yi + half, xi + half) - box_sum(ii, yi - half, xi - half, yi, xi + half)
    return dx, dy


def orientations(ii: np.ndarray, kps: np.ndarray, window: float = np.pi / 3, bins: int = 42) -> np.ndarray:
    """Dominant angle (radians, image axes: x right, y down) of each keypoint (N, >=3: x, y, s)."""
    if len(kps) == 0:
        return np.zeros(0)
    u, v = np.mgrid[-6:7, -6:7]
    inside = u ** 2 + v ** 2 < 36
    u, v = u[inside].astype(float), v[inside].astype(float)  # 109 samples within radius 6
    s = kps[:, 2:3]
    dx, dy = haar(ii, kps[:, 0:1] + u * s, kps[:, 1:2] + v * s, 4 * s)
    w = np.exp(-(u ** 2 + v ** 2) / (2 * 2.5 ** 2))
    dx, dy = dx * w, dy * w
    ang = np.arctan2(dy, dx)
    starts = np.linspace(-np.pi, np.pi, bins, endpoint=False)
    best = np.zeros(len(kps))
    best_len = np.full(len(kps), -1.0)
    for a in starts:
        inwin = ((ang - a) % (2 * np.pi)) < window
        sx, sy = (dx * inwin).sum(1), (dy * inwin).sum(1)
        length = sx ** 2 + sy ** 2
        better = length > best_len
        best_len[better] = length[better]
        best[better] = np.arctan2(sy, sx)[better]
    return best


def descriptors(ii: np.ndarray, kps: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """SURF-64 descriptors (N, 64) float32, unit length."""
    n = len(kps)
    if n == 0:
        return np.zeros((0, 64), np.float32)
    grid = np.arange(20) - 9.5  # sample centres of the 20 x 20 grid, in units of s
    gu, gv = np.meshgrid(grid, grid)  # gu: along the keypoint's x axis, gv: along its y axis
    gu, gv = gu.ravel(), gv.ravel()
    s = kps[:, 2:3]
    c, sn = np.cos(angles)[:, None], np.sin(angles)[:, None]
    x = kps[:, 0:1] + (c * gu - sn * gv) * s
    y = kps[:, 1:2] + (sn * gu + c * gv) * s
    dx, dy = haar(ii, x, y, 2 * s)
    ru = c * dx + sn * dy  # responses in the keypoint frame
    rv = -sn * dx + c * dy
    w = np.exp(-(gu ** 2 + gv ** 2) / (2 * 3.3 ** 2))
    ru, rv = ru * w, rv * w
    cell = (np.floor((gv + 10) / 5).astype(int) * 4 + np.floor((gu + 10) / 5).astype(int))  # 0..15
    onehot = np.zeros((400, 16))
    onehot[np.arange(400), cell] = 1.0
    desc = np.stack([ru @ onehot, rv @ onehot, np.abs(ru) @ onehot, np.abs(rv) @ onehot], axis=2).reshape(n, 64)
    desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    return desc.astype(np.float32)


def surf(gray: np.ndarray, config: SurfConfig = SurfConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Our SURF: keypoints (N, 4: x, y, scale s, angle in radians; pixel centres at integers) and (N, 64)
    float32 descriptors."""
    g = np.asarray(gray, dtype=np.float64)
    if g.ndim == 3:
        g = to_gray(g, np.float32).astype(np.float64)
    ii = integral_image(g)
    kps = fast_hessian(g, config)
    angles = np.zeros(len(kps)) if config.upright else orientations(ii, kps)
    return np.column_stack([kps[:, :3], angles]) if len(kps) else np.zeros((0, 4)), descriptors(ii, kps, angles)


def opencv_surf_available() -> bool:
    try:
        cv2.xfeatures2d.SURF_create()
        return True
    except (AttributeError, cv2.error):
        return False


def extract_surf(gray: np.ndarray, config: SurfConfig = SurfConfig()) -> tuple[np.ndarray, np.ndarray, str]:
    """(keypoints (N,4), descriptors, "opencv" | "mvrecon"): OpenCV's SURF when the build has it, else ours."""
    if opencv_surf_available():
        det = cv2.xfeatures2d.SURF_create(config.hessian_threshold, config.octaves, config.layers - 2,
                                          False, config.upright)
        kp, desc = det.detectAndCompute(np.asarray(gray, dtype=np.uint8), None)
        pts = np.array([(k.pt[0], k.pt[1], k.size * 1.2 / 9.0, np.radians(k.angle)) for k in kp]).reshape(-1, 4)
        return pts, (desc if desc is not None else np.zeros((0, 64), np.float32)), "opencv"
    kps, desc = surf(gray, config)
    return kps, desc, "mvrecon"
