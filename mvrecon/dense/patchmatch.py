"""Per-pixel refinement of a depth map with slanted planes, PatchMatch-style (numba kernels).

Each pixel carries a plane: its inverse depth q and the gradient (gx, gy) of inverse depth per pixel (for a
plane, inverse depth is affine in the pixel coordinates, so a window's pixel (x + dx, y + dy) lies at inverse
depth q + gx dx + gy dy; gx = gy = 0 is the fronto-parallel plane). A source pixel of a reference pixel p at
inverse depth q is A @ p + b * q (homogeneous), A = K_s R K_ref^-1, b = K_s t; so a slanted plane warps the
window by its homography, and the cost of a plane is the mean of the best-k per-source costs 1 - NCC over the
window (sampled every `step` pixels, bilinear in the sources).

- `_plane_costs`: the cost of every pixel's plane in a band of rows;
- `_propagation_pass`: one PatchMatch pass over a band of rows (`tiles`) in raster order (or reversed): each
  pixel tries its two already visited neighbours' planes, a random change of its plane's depth and of its
  slant, and keeps the best.
Slanted windows are what fronto-parallel ones lack on floors and walls seen at a grazing angle: there a
fronto-parallel window straddles depths several times the tolerance.
"""

import math

import numpy as np
from numba import njit

INVALID = 3.0  # cost of a pixel whose window falls outside a source or has no texture (NCC costs are in [0, 2])
SAME = 1e-6  # a neighbour's plane within this share of a pixel's inverse depth, and of equal slant, is its own


@njit(cache=True, nogil=True)
def _mean_of_best(costs, buf):  # pragma: no cover - compiled
    """Mean of the len(buf) lowest of one pixel's source costs, counting only sources that see the pixel (cost
    below 2; INVALID counts as 2), and at least the lowest one, so that a pixel near the border is judged by the
    one source whose image covers it. `buf`: scratch space of the k wanted."""
    k = buf.shape[0]
    for j in range(k):
        buf[j] = 2.0
    for s in range(costs.shape[0]):  # insertion into the k lowest so far (the sources are a handful)
        v = min(costs[s], 2.0)
        j = k - 1
        if v >= buf[j]:
            continue
        while j > 0 and buf[j - 1] > v:
            buf[j] = buf[j - 1]
            j -= 1
        buf[j] = v
    total = 0.0
    m = 0
    for j in range(k):
        if buf[j] < 2.0 or m == 0:
            total += buf[j]
            m += 1
    return total / m


@njit(cache=True, nogil=True)
def _ref_window(ref, x, y, radius, step, win):  # pragma: no cover - compiled
    """(mean, variance, samples) of the reference window at (x, y), clamped at the border; its samples, row by
    row, into `win` (read once per pixel, not once per plane and source)."""
    rows, cols = ref.shape
    sr = 0.0
    srr = 0.0
    n = 0
    for dy in range(-radius, radius + 1, step):
        yy = min(max(y + dy, 0), rows - 1)
        for dx in range(-radius, radius + 1, step):
            v = ref[yy, min(max(x + dx, 0), cols - 1)]
            win[n] = v
            sr += v
            srr += v * v
            n += 1
    mr = sr / n
    return mr, srr / n - mr * mr, n


@njit(cache=True, nogil=True, fastmath=True)
def _plane_cost(win, srcs, sizes, A, b, x, y, q, gx, gy, radius, step, mr, vr, n, min_var, costs,
                kbuf):  # pragma: no cover - compiled
    """Best-k aggregated cost of the plane (q, gx, gy) at reference pixel (x, y) (its window's samples in
    `win`); 2 when no source sees it. Inverse depth and the homography's third row are affine over the window,
    and a homography positive there maps the square window onto the convex quadrilateral of its corners' images,
    so the window is checked at its four corners: in front of both cameras and inside the source image."""
    last = -radius + ((2 * radius) // step) * step  # the window's last sample offset
    samples = (2 * radius) // step + 1
    if (q - gx * radius - gy * radius <= 0 or q + gx * last - gy * radius <= 0 or q - gx * radius + gy * last <= 0
            or q + gx * last + gy * last <= 0):
        for s in range(srcs.shape[0]):
            costs[s] = 2.0
        return _mean_of_best(costs, kbuf)
    for s in range(srcs.shape[0]):
        width, height = sizes[s, 0], sizes[s, 1]
        # the source pixel of window sample (dx, dy): (A @ (x + dx, y + dy, 1) + b * q') / its third row,
        # q' = q + gx dx + gy dy: the centre's value plus a step per dx and per dy
        hx = A[s, 0, 0] * x + A[s, 0, 1] * y + A[s, 0, 2] + b[s, 0] * q
        hy = A[s, 1, 0] * x + A[s, 1, 1] * y + A[s, 1, 2] + b[s, 1] * q
        hw = A[s, 2, 0] * x + A[s, 2, 1] * y + A[s, 2, 2] + b[s, 2] * q
        ux, uy = A[s, 0, 0] + b[s, 0] * gx, A[s, 0, 1] + b[s, 0] * gy
        vx, vy = A[s, 1, 0] + b[s, 1] * gx, A[s, 1, 1] + b[s, 1] * gy
        wx, wy = A[s, 2, 0] + b[s, 2] * gx, A[s, 2, 1] + b[s, 2] * gy
        ok = True
        for c in range(4):
            dx = -radius if c % 2 == 0 else last
            dy = -radius if c < 2 else last
            pw = hw + wx * dx + wy * dy
            if pw <= 0:
                ok = False
                break
            u = (hx + ux * dx + uy * dy) / pw
            v = (hy + vx * dx + vy * dy) / pw
            if u < 0 or v < 0 or u >= width - 1 or v >= height - 1:
                ok = False
                break
        if not ok:
            costs[s] = 2.0
            continue
        ss = 0.0
        sss = 0.0
        srs = 0.0
        k = 0
        for iy in range(samples):
            dy = -radius + iy * step
            px = hx + uy * dy - ux * radius  # numerators and denominator at the row's first sample
            py = hy + vy * dy - vx * radius
            pw = hw + wy * dy - wx * radius
            for _ in range(samples):
                inv = 1.0 / pw
                u = px * inv
                v = py * inv
                u0 = min(int(u), width - 2)  # inside by the corners' check; min() guards rounding
                v0 = min(int(v), height - 2)
                fu = u - u0
                fv = v - v0
                top = srcs[s, v0, u0] + fu * (srcs[s, v0, u0 + 1] - srcs[s, v0, u0])
                bottom = srcs[s, v0 + 1, u0] + fu * (srcs[s, v0 + 1, u0 + 1] - srcs[s, v0 + 1, u0])
                sv = top + fv * (bottom - top)
                ss += sv
                sss += sv * sv
                srs += win[k] * sv
                k += 1
                px += ux * step
                py += vx * step
                pw += wx * step
        ms = ss / n
        vs = sss / n - ms * ms
        if vs < min_var:
            costs[s] = 2.0
            continue
        ncc = (srs / n - mr * ms) / math.sqrt(vr * vs)
        costs[s] = 1.0 - min(max(ncc, -1.0), 1.0)
    return _mean_of_best(costs, kbuf)


@njit(cache=True, nogil=True)
def _plane_costs(ref, srcs, sizes, A, b, q, gx, gy, radius, step, best_k, min_var, cost, first,
                 last):  # pragma: no cover - compiled
    """cost[y, x] for the rows first <= y < last: the aggregated cost of each pixel's plane (q, gx, gy) over a
    window of (2 radius / step + 1)^2 samples; INVALID where the reference window has no texture or the pixel
    has no depth (q = 0)."""
    cols = ref.shape[1]
    costs = np.empty(srcs.shape[0], np.float32)
    kbuf = np.empty(min(best_k, srcs.shape[0]), np.float32)
    win = np.empty(((2 * radius) // step + 1) ** 2, np.float32)
    for y in range(first, last):
        for x in range(cols):
            mr, vr, n = _ref_window(ref, x, y, radius, step, win)
            if vr < min_var or not q[y, x] > 0:
                cost[y, x] = INVALID
                continue
            cost[y, x] = _plane_cost(win, srcs, sizes, A, b, x, y, q[y, x], gx[y, x], gy[y, x], radius, step, mr,
                                     vr, n, min_var, costs, kbuf)


@njit(cache=True, nogil=True)
def _propagation_pass(ref, srcs, sizes, A, b, q, gx, gy, cost, dq, tilt, radius, step, best_k, min_var, reverse,
                      seed, settled, row0, first, last):  # pragma: no cover - compiled
    """One PatchMatch pass over a band of the image, in raster order (`reverse`: from the last pixel back),
    updating (q, gx, gy, cost) in place: each textured pixel tries the planes of its left and upper
    neighbours (right and lower when reversed; already updated in this pass, so a good plane spreads across a
    surface), its own plane with the depth moved by up to `dq`, and with the slant moved by up to `tilt`
    (gradient change per pixel relative to q: tilt = 1/f is a turn of about 45 degrees), keeping the lowest
    cost. A pixel whose cost is below `settled` skips the random changes.
    The plane arrays hold the image's rows row0, row0 + 1, ...; the pass updates their rows first <= y < last
    and reads the rows around them (a band's halo) only as neighbours; `ref` is the whole reference image."""
    cols = ref.shape[1]
    rows = q.shape[0]
    np.random.seed(seed)
    costs = np.empty(srcs.shape[0], np.float32)
    kbuf = np.empty(min(best_k, srcs.shape[0]), np.float32)
    win = np.empty(((2 * radius) // step + 1) ** 2, np.float32)
    d = 1 if reverse else -1
    total = (last - first) * cols
    for i in range(total):
        k = total - 1 - i if reverse else i
        y = first + k // cols
        x = k - (y - first) * cols
        if cost[y, x] >= INVALID:  # no texture: nothing to match
            continue
        mr, vr, n = _ref_window(ref, x, row0 + y, radius, step, win)
        for j in range(4):
            if j == 0 or j == 1:  # a neighbour's plane, evaluated at this pixel
                nx = x + d if j == 0 else x
                ny = y if j == 0 else y + d
                if nx < 0 or ny < 0 or nx >= cols or ny >= rows or cost[ny, nx] >= 2.0:
                    continue
                cgx = gx[ny, nx]
                cgy = gy[ny, nx]
                cq = q[ny, nx] + cgx * (x - nx) + cgy * (y - ny)
                if cgx == gx[y, x] and cgy == gy[y, x] and abs(cq - q[y, x]) <= SAME * q[y, x]:
                    continue  # the pixel's own plane (copied here, or upsampled from one coarse pixel): no change
            elif cost[y, x] < settled:  # a good match already: random changes rarely improve it
                break
            elif j == 2:  # the depth moved
                cq = q[y, x] + dq * (2.0 * np.random.random() - 1.0)
                cgx = gx[y, x]
                cgy = gy[y, x]
            else:  # the slant moved
                cq = q[y, x]
                cgx = gx[y, x] + tilt * cq * (2.0 * np.random.random() - 1.0)
                cgy = gy[y, x] + tilt * cq * (2.0 * np.random.random() - 1.0)
            if not cq > 0:
                continue
            c = _plane_cost(win, srcs, sizes, A, b, x, row0 + y, cq, cgx, cgy, radius, step, mr, vr, n,
                            min_var, costs, kbuf)
            if c < cost[y, x]:
                cost[y, x] = c
                q[y, x] = cq
                gx[y, x] = cgx
                gy[y, x] = cgy
