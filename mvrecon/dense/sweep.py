"""Depth of one view by a plane sweep: fronto-parallel planes of the reference camera, evenly spaced in inverse
depth, each source image warped onto the reference through the plane's homography (OpenCV), the zero-mean
normalised cross-correlation (NCC) over a square window computed from box sums, and per plane the mean of the
`best_k` lowest costs over the source views that see the pixel (a pixel hidden in one source is judged by the
others; one near the image border by the one source whose image covers it). Each pixel
keeps its best plane, refined between planes by a parabola through the costs of its neighbours.

The per-pixel arithmetic runs in numba kernels fused over the whole image: one pass per (plane, source) for the
NCC, one per plane for the best-k aggregation and the running minimum, so no cost volume is held in memory (a
1-Mpx view at 200 planes would need 0.8 GB).

`pyramid_depth` sweeps at a coarse size only, then refines each pixel's plane, slant included, at each finer
level up to full size (`patchmatch`).
"""

import math

import cv2
import numpy as np
from numba import njit

from .patchmatch import INVALID, _mean_of_best
from .tiles import TILE_ROWS, plane_costs, propagation_pass, run_tasks


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
            c = _mean_of_best(costs[:, y, x], buf)
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
                window: int = 7, best_k: int = 2, max_cost: float = 0.5, min_std: float = 0.004,
                threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(depth, cost) of the grey float32 reference image `ref` (values in [0, 1]) against the grey `sources`:
    depth 0 where no plane reached an NCC cost below `max_cost`; cost is the best aggregated cost (1 - NCC).
    `relative[i]` = (R, t) from reference camera to source i's; `depth_range` the (near, far) swept. Each
    plane's sources are scored on `threads` threads (each source's costs on their own: the same result)."""
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

    def score(s: int, d: float) -> None:  # costs[s] of the plane at depth d
        src, K_src, (R, t) = sources[s], K_srcs[s], relative[s]
        H = plane_homography(K_ref, K_src, R, t, d)
        warped = cv2.warpPerspective(src, H, (cols, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_REPLICATE)
        b1 = cv2.blur(warped, **box)
        b2 = cv2.blur(warped * warped, **box)
        b12 = cv2.blur(ref * warped, **box)
        _ncc_cost(mu_r, var_r, b1, b2, b12, H, src.shape[1], src.shape[0], min_var, costs[s])

    for p in range(planes):
        d = 1.0 / (q0 + p * dq)
        run_tasks([lambda s=s, d=d: score(s, d) for s in range(len(sources))], threads)
        _aggregate(costs, best_k, p, prev, best, index, left, right)
    depth = np.zeros((rows, cols), np.float32)
    _refine(best, index, left, right, q0, dq, max_cost, depth)
    return depth, best


def plane_normals(q: np.ndarray, gx: np.ndarray, gy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) in the camera frame, facing the camera, of each pixel's plane (`patchmatch`): its
    inverse depth at pixel (x', y') is a . (x', y', 1), a = (gx, gy, q - gx x - gy y); the plane's points X
    (pixel K X / z) satisfy (K^T a) . X = 1, so -K^T a is its normal towards the camera. Zero where q = 0.
    The plane is what the window matched, so the normal is as sharp at a depth edge as inside a surface, where
    a finite difference of the depth map mixes the two sides."""
    rows, cols = q.shape
    fx, fy, cx, cy = (np.float32(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    x = cx - np.arange(cols, dtype=np.float32)
    y = cy - np.arange(rows, dtype=np.float32)
    n = np.empty((rows, cols, 3), np.float32)
    n[..., 0] = -fx * gx
    n[..., 1] = -fy * gy
    n[..., 2] = -(q + gx * x[None, :] + gy * y[:, None])
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    n /= np.where(norm > 0, norm, 1)
    n[~((q > 0) & (norm[..., 0] > 0))] = 0
    return n


def scaled(image: np.ndarray, K: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """The image resized by `factor` (area averaging) and its camera matrix (pixel centres kept)."""
    if factor == 1.0:
        return image, K
    rows, cols = image.shape
    size = (max(1, round(cols * factor)), max(1, round(rows * factor)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    sx, sy = size[0] / cols, size[1] / rows
    Ks = K.copy()
    Ks[0, 0] *= sx
    Ks[1, 1] *= sy
    Ks[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return small, Ks


def pyramid_depth(ref: np.ndarray, sources: list[np.ndarray], K_ref: np.ndarray, K_srcs: list[np.ndarray],
                  relative: list[tuple[np.ndarray, np.ndarray]], depth_range: tuple[float, float], *,
                  coarse_size: int = 400, pixels_per_plane: float = 2.0, max_planes: int = 192,
                  window: int = 7, best_k: int = 2, max_cost: float = 0.5, min_std: float = 0.004,
                  radius: int = 4, step: int = 2, passes: int = 2, final_passes: int = 1,
                  settled: float = 0.2, threads: int = 1,
                  tile_rows: int = TILE_ROWS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth, cost, normals) as `sweep_depth`, with each pixel's unit normal (`plane_normals`, camera frame;
    zero without depth), coarse to fine with slanted planes: the fronto-parallel sweep on the
    images scaled so the long side is about `coarse_size` (planes `pixels_per_plane` apart in the widest
    source's disparity there); then at that level and at each doubling of the resolution up to full size, each
    pixel's plane (inverse depth and its gradient, `patchmatch`) upsampled and PatchMatch passes (`passes`,
    `final_passes` at full size) that spread planes between neighbours and perturb their depth (by up to the
    plane spacing, halved at each level and pass) and slant (windows of radius `radius` sampled every `step`
    pixels). Far fewer evaluations than a full-resolution sweep, and slanted surfaces (floors, walls at a
    grazing angle) within the tolerance a fronto-parallel window misses: on object_orbit_small the share of
    pixels within 0.5% of the true depth goes from 0.47 to 0.88; a second pass at full size, or planes one
    pixel apart, add under 0.005 to that for a quarter more time. At full size a pixel whose plane already
    costs under `settled` (1 - NCC) only tries its neighbours' planes, not random changes of its own: those
    find little there and cost a fifth of the time.
    The work runs on `threads` threads: the sweep source by source, PatchMatch in bands of `tile_rows` rows
    (`tiles`); the result does not depend on `threads`."""
    rows, cols = ref.shape
    levels = 0
    while max(rows, cols) / 2 ** (levels + 1) >= coarse_size * 0.75:
        levels += 1
    factor = 0.5**levels
    near, far = depth_range
    small_ref, small_K = scaled(ref, K_ref, factor)
    small_src = [scaled(s, K, factor) for s, K in zip(sources, K_srcs)]
    baseline = max(np.linalg.norm(t) for _, t in relative)
    disparity = small_K[0, 0] * baseline * (1.0 / near - 1.0 / far)
    planes = int(np.clip(np.ceil(disparity / pixels_per_plane), 32, max_planes))
    depth, cost = sweep_depth(small_ref, [s for s, _ in small_src], small_K, [K for _, K in small_src], relative,
                              depth_range, planes, window=window, best_k=best_k, max_cost=np.inf,
                              min_std=min_std, threads=threads)
    q = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-12), 0.0).astype(np.float32)
    gx, gy = np.zeros_like(q), np.zeros_like(q)
    dq = (1.0 / near - 1.0 / far) / max(planes - 1, 1)
    min_var = np.float32(min_std * min_std)
    for level in range(levels, -1, -1):
        factor = 0.5**level
        lref, lK = scaled(ref, K_ref, factor)
        lsrc = [scaled(s, K, factor) for s, K in zip(sources, K_srcs)]
        if level < levels:
            q, gx, gy = _upsample_planes(q, gx, gy, lref.shape)
            dq *= 0.5
        stack, sizes, A, b = _source_stack(lsrc, lK, relative)
        tiling = dict(threads=threads, tile_rows=tile_rows)
        cost = plane_costs(lref, stack, sizes, A, b, q, gx, gy, radius, step, best_k, min_var, **tiling)
        for p in range(passes if level else final_passes):
            propagation_pass(lref, stack, sizes, A, b, q, gx, gy, cost, dq * 0.5**p, 0.5**p / lK[0, 0],
                             radius, step, best_k, min_var, p % 2 == 1, 1000 * level + p,
                             settled if level == 0 else -1.0, **tiling)
    q[~(cost <= max_cost)] = 0.0
    depth = np.where(q > 0, 1.0 / np.maximum(q, 1e-12), 0.0).astype(np.float32)
    return depth, cost, plane_normals(q, gx, gy, K_ref)


def _upsample_planes(q: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                     shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's plane (inverse depth q, its gradients per pixel) at the finer `shape`: the plane of the
    coarse pixel it falls in, evaluated at its centre (0 stays 0: no depth)."""
    rows, cols = shape
    sy, sx = q.shape[0] / rows, q.shape[1] / cols
    fy = (np.arange(rows) + 0.5) * sy - 0.5  # fine pixel centres in coarse pixels
    fx = (np.arange(cols) + 0.5) * sx - 0.5
    ys = np.clip(np.round(fy), 0, q.shape[0] - 1).astype(int)
    xs = np.clip(np.round(fx), 0, q.shape[1] - 1).astype(int)
    qc, gxc, gyc = q[np.ix_(ys, xs)], gx[np.ix_(ys, xs)], gy[np.ix_(ys, xs)]
    fine = qc + gxc * (fx - xs)[None, :] + gyc * (fy - ys)[:, None]
    fine = np.where((qc > 0) & (fine > 0), fine, qc)
    return fine.astype(np.float32), (gxc * sx).astype(np.float32), (gyc * sy).astype(np.float32)


def _source_stack(sources: list[tuple[np.ndarray, np.ndarray]], K_ref: np.ndarray,
                  relative: list[tuple[np.ndarray, np.ndarray]]):
    """The source images in one zero-padded array, their sizes, and per source A = K_s R K_ref^-1, b = K_s t."""
    rows = max(s.shape[0] for s, _ in sources)
    cols = max(s.shape[1] for s, _ in sources)
    stack = np.zeros((len(sources), rows, cols), np.float32)
    sizes = np.zeros((len(sources), 2), np.int64)
    A = np.zeros((len(sources), 3, 3))
    b = np.zeros((len(sources), 3))
    K_inv = np.linalg.inv(K_ref)
    for i, ((image, K), (R, t)) in enumerate(zip(sources, relative)):
        stack[i, : image.shape[0], : image.shape[1]] = image
        sizes[i] = image.shape[1], image.shape[0]
        A[i] = K @ R @ K_inv
        b[i] = K @ t
    return stack, sizes, A, b


def warm_up() -> None:
    """Compile the kernels (numba caches them on disk) on a tiny problem: worker processes started afterwards
    load them instead of compiling them each, and never write the cache at the same time."""
    image = np.random.default_rng(0).random((24, 32)).astype(np.float32)
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    pyramid_depth(image, [image], K, [K], [(np.eye(3), np.array([0.1, 0, 0]))], (1.0, 2.0), coarse_size=8)
