"""Depth of one view by a plane sweep: fronto-parallel planes of the reference camera, evenly spaced in inverse
depth, each source image warped onto the reference through the plane's homography (OpenCV), the zero-mean
normalised cross-correlation (NCC) over a square window computed from box sums, and per plane the mean of the
`best_k` lowest costs over the source views (a pixel hidden in one source is judged by the others). Each pixel
keeps its best plane, refined between planes by a parabola through the costs of its neighbours.

The per-pixel arithmetic runs in numba kernels fused over the whole image: one pass per (plane, source) for the
NCC, one per plane for the best-k aggregation and the running minimum, so no cost volume is held in memory (a
1-Mpx view at 200 planes would need 0.8 GB).
"""

import math

import cv2
import numpy as np
from numba import njit

INVALID = 3.0  # cost of a pixel whose window falls outside a source or has no texture (NCC costs are in [0, 2])


@njit(cache=True, nogil=True)
def _ncc_cost(mu_r, var_r, b1, b2, b12, H, width, height, min_var, out):  # pragma: no cover - compiled
    """out[y, x] = 1 - NCC of the reference window and the warped source window; INVALID where the pixel's
    source position (H @ (x, y, 1)) is outside the source image or either window has no texture."""
    rows, cols = mu_r.shape
    for y in range(rows):
        for x in range(cols):
            w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
            if w <= 0:
                out[y, x] = INVALID
                continue
            u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
            v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
            if u < 0 or v < 0 or u > width - 1 or v > height - 1:
                out[y, x] = INVALID
                continue
            var_s = b2[y, x] - b1[y, x] * b1[y, x]
            vr = var_r[y, x]
            if var_s < min_var or vr < min_var:
                out[y, x] = INVALID
                continue
            ncc = (b12[y, x] - mu_r[y, x] * b1[y, x]) / math.sqrt(vr * var_s)
            out[y, x] = 1.0 - min(max(ncc, -1.0), 1.0)


@njit(cache=True, nogil=True)
def _aggregate(costs, best_k, plane, prev, best, index, left, right):  # pragma: no cover - compiled
    """Mean of the best_k lowest source costs of each pixel at `plane`, and the running minimum over the planes:
    best cost, its plane, and the costs of the planes either side (for the parabola)."""
    n, rows, cols = costs.shape
    k = min(best_k, n)
    buf = np.empty(k, np.float32)
    for y in range(rows):
        for x in range(cols):
            for s in range(k):
                buf[s] = 2.0
            for s in range(n):  # insertion into the k lowest so far (n is a handful)
                v = min(costs[s, y, x], 2.0)
                j = k - 1
                if v >= buf[j]:
                    continue
                while j > 0 and buf[j - 1] > v:
                    buf[j] = buf[j - 1]
                    j -= 1
                buf[j] = v
            c = 0.0
            for s in range(k):
                c += buf[s]
            c /= k
            if index[y, x] == plane - 1:
                right[y, x] = c
            if c < best[y, x]:
                best[y, x] = c
                index[y, x] = plane
                left[y, x] = prev[y, x]
                right[y, x] = np.inf
            prev[y, x] = c


@njit(cache=True, nogil=True)
def _refine(best, index, left, right, q0, dq, max_cost, depth):  # pragma: no cover - compiled
    """Depth from the best plane and a parabola through its neighbours' costs; 0 where the best cost is above
    max_cost (COLMAP's mark of no depth)."""
    rows, cols = best.shape
    for y in range(rows):
        for x in range(cols):
            if index[y, x] < 0 or best[y, x] > max_cost:
                depth[y, x] = 0.0
                continue
            offset = 0.0
            lc, c, rc = left[y, x], best[y, x], right[y, x]
            if np.isfinite(lc) and np.isfinite(rc):
                curvature = lc - 2.0 * c + rc
                if curvature > 1e-9:
                    offset = min(max(0.5 * (lc - rc) / curvature, -0.5), 0.5)
            q = q0 + (index[y, x] + offset) * dq
            depth[y, x] = 1.0 / q if q > 0 else 0.0


def plane_homography(K_ref: np.ndarray, K_src: np.ndarray, R: np.ndarray, t: np.ndarray,
                     depth: float) -> np.ndarray:
    """Reference pixel -> source pixel for the plane z = depth of the reference camera; (R, t) takes reference
    camera coordinates to the source's."""
    n = np.array([0.0, 0.0, 1.0])
    return K_src @ (R + np.outer(t, n) / depth) @ np.linalg.inv(K_ref)


def sweep_depth(ref: np.ndarray, sources: list[np.ndarray], K_ref: np.ndarray, K_srcs: list[np.ndarray],
                relative: list[tuple[np.ndarray, np.ndarray]], depth_range: tuple[float, float], planes: int, *,
                window: int = 7, best_k: int = 2, max_cost: float = 0.5,
                min_std: float = 0.004) -> tuple[np.ndarray, np.ndarray]:
    """(depth, cost) of the grey float32 reference image `ref` (values in [0, 1]) against the grey `sources`:
    depth 0 where no plane reached an NCC cost below `max_cost`; cost is the best aggregated cost (1 - NCC).
    `relative[i]` = (R, t) from reference camera to source i's; `depth_range` the (near, far) swept."""
    near, far = depth_range
    q0, q1 = 1.0 / far, 1.0 / near
    dq = (q1 - q0) / max(planes - 1, 1)
    rows, cols = ref.shape
    box = dict(ksize=(window, window), borderType=cv2.BORDER_REFLECT)
    mu_r = cv2.blur(ref, **box)
    var_r = cv2.blur(ref * ref, **box) - mu_r * mu_r
    costs = np.empty((len(sources), rows, cols), np.float32)
    best = np.full((rows, cols), np.inf, np.float32)
    index = np.full((rows, cols), -1, np.int32)
    left = np.full((rows, cols), np.inf, np.float32)
    right = np.full((rows, cols), np.inf, np.float32)
    prev = np.full((rows, cols), np.inf, np.float32)
    min_var = np.float32(min_std * min_std)
    for p in range(planes):
        d = 1.0 / (q0 + p * dq)
        for s, (src, K_src, (R, t)) in enumerate(zip(sources, K_srcs, relative)):
            H = plane_homography(K_ref, K_src, R, t, d)
            warped = cv2.warpPerspective(src, H, (cols, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                         borderMode=cv2.BORDER_REPLICATE)
            b1 = cv2.blur(warped, **box)
            b2 = cv2.blur(warped * warped, **box)
            b12 = cv2.blur(ref * warped, **box)
            _ncc_cost(mu_r, var_r, b1, b2, b12, H, src.shape[1], src.shape[0], min_var, costs[s])
        _aggregate(costs, best_k, p, prev, best, index, left, right)
    depth = np.zeros((rows, cols), np.float32)
    _refine(best, index, left, right, q0, dq, max_cost, depth)
    return depth, best


def normals_from_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) in the camera frame, facing the camera, from the depth map's neighbouring points
    (central differences); zero where a neighbour has no depth."""
    rows, cols = depth.shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    pts = np.stack([(x - cx) / fx * depth, (y - cy) / fy * depth, depth], axis=2)
    dx = np.zeros_like(pts)
    dy = np.zeros_like(pts)
    dx[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    dy[1:-1] = pts[2:] - pts[:-2]
    n = np.cross(dx, dy)
    known = depth > 0
    ok = known.copy()
    ok[:, 1:-1] &= known[:, 2:] & known[:, :-2]
    ok[1:-1] &= known[2:] & known[:-2]
    ok[[0, -1], :] = False
    ok[:, [0, -1]] = False
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    n = np.where(ok[..., None] & (norm > 0), n / np.maximum(norm, 1e-12), 0.0)
    facing = np.sum(n * pts, axis=2) > 0  # a normal points back at the camera: n . X < 0
    n[facing] *= -1
    return n.astype(np.float32)
