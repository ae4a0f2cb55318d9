"""Geometric consistency of depth maps across views, and their fusion into one point cloud.

A reference pixel's depth is consistent with a source view when its 3D point, projected into the source, lands on
a pixel whose own depth, taken back into the reference, lands within `max_reprojection` pixels of where it began
and at a depth within `rel_tolerance` of the reference's (COLMAP's forward-backward check). A depth kept in the
geometric map is consistent with at least `min_consistent` source views: one wrong match rarely agrees with
two other views. Fusion takes each view's kept pixels in turn and averages each one with the consistent pixels
of its source views, which are then used up, so a surface seen by many views gives one point, not one per view.
"""

from dataclasses import dataclass

import numpy as np
from numba import njit

from .views import View


@dataclass
class DepthView:
    """A view's depth map (0: no depth), normals (camera frame), colours, and its source views."""

    view: View
    depth: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    sources: tuple[int, ...] = ()


def back_project(view: View, depth: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """World points (N, 3) of the pixels (ys, xs) at their depths."""
    z = depth[ys, xs].astype(float)
    K = view.K
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return (cam - view.t) @ view.R


@njit(cache=True, nogil=True)
def _match_pixels(xs, ys, z, K_ref, K_src, R, t, src_depth, rel_tolerance, max_reprojection, ok, sy,
                  sx):  # pragma: no cover - compiled
    """The forward-backward check of each reference pixel (xs, ys) at depth z against one source: its point,
    (R, t) taking reference camera coordinates to the source's, lands on source pixel (sx, sy) whose depth
    taken back into the reference lands within `max_reprojection` pixels and `rel_tolerance` of z (ok)."""
    fx, fy, cx, cy = K_ref[0, 0], K_ref[1, 1], K_ref[0, 2], K_ref[1, 2]
    sfx, sfy, scx, scy = K_src[0, 0], K_src[1, 1], K_src[0, 2], K_src[1, 2]
    rows, cols = src_depth.shape
    for i in range(xs.shape[0]):
        ok[i] = False
        sx[i] = 0
        sy[i] = 0
        x0, y0, z0 = (xs[i] - cx) / fx * z[i], (ys[i] - cy) / fy * z[i], z[i]
        p0 = R[0, 0] * x0 + R[0, 1] * y0 + R[0, 2] * z0 + t[0]
        p1 = R[1, 0] * x0 + R[1, 1] * y0 + R[1, 2] * z0 + t[1]
        p2 = R[2, 0] * x0 + R[2, 1] * y0 + R[2, 2] * z0 + t[2]
        if not p2 > 0:
            continue
        u = np.rint(sfx * p0 / p2 + scx)
        v = np.rint(sfy * p1 / p2 + scy)
        if not (u >= 0 and v >= 0 and u < cols and v < rows):
            continue
        ui, vi = int(u), int(v)
        sx[i] = ui
        sy[i] = vi
        d = src_depth[vi, ui]
        if not d > 0:
            continue
        a0, a1 = (ui - scx) / sfx * d - t[0], (vi - scy) / sfy * d - t[1]
        a2 = d - t[2]
        b0 = R[0, 0] * a0 + R[1, 0] * a1 + R[2, 0] * a2  # R^T (source point - t): back in the reference
        b1 = R[0, 1] * a0 + R[1, 1] * a1 + R[2, 1] * a2
        b2 = R[0, 2] * a0 + R[1, 2] * a1 + R[2, 2] * a2
        if not b2 > 0 or abs(b2 - z0) > rel_tolerance * z0:
            continue
        du = fx * b0 / b2 + cx - xs[i]
        dv = fy * b1 / b2 + cy - ys[i]
        ok[i] = du * du + dv * dv <= max_reprojection * max_reprojection


def _matches(ref: View, ys: np.ndarray, xs: np.ndarray, z_ref: np.ndarray, src: View, src_depth: np.ndarray,
             rel_tolerance: float, max_reprojection: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(consistent mask, source rows, source columns) of the reference pixels (ys, xs) at depths z_ref against
    one source view."""
    R = src.R @ ref.R.T
    t = src.t - R @ ref.t
    ok = np.zeros(len(ys), bool)
    sy, sx = np.zeros(len(ys), np.int64), np.zeros(len(ys), np.int64)
    _match_pixels(xs.astype(np.float64), ys.astype(np.float64), z_ref.astype(np.float64), ref.K, src.K, R, t,
                  src_depth, float(rel_tolerance), float(max_reprojection), ok, sy, sx)
    return ok, sy, sx


def geometric_filter(ref: DepthView, sources: list[DepthView], *, rel_tolerance: float = 0.01,
                     max_reprojection: float = 1.0, min_consistent: int = 2) -> np.ndarray:
    """The reference depth map with 0 where fewer than `min_consistent` source views agree with it."""
    ys, xs = np.nonzero(ref.depth > 0)
    z_ref = ref.depth[ys, xs].astype(float)
    count = np.zeros(len(ys), np.int32)
    for src in sources:
        ok, _, _ = _matches(ref.view, ys, xs, z_ref, src.view, src.depth, rel_tolerance, max_reprojection)
        count += ok
    out = np.zeros_like(ref.depth)
    keep = count >= min_consistent
    out[ys[keep], xs[keep]] = ref.depth[ys[keep], xs[keep]]
    return out


_NONE = np.zeros((0, 0, 3), np.float32)  # a view without colours or normals


@njit(cache=True, nogil=True)
def _add_source(ok, sy, sx, used, depth, K, R, t, colors, normals, total, count, rgb,
                normal):  # pragma: no cover - compiled
    """Add to the reference points' sums (total, count, rgb, normal) the source pixels (sy, sx) that matched
    them (ok) and no point had used before: their world points, colours and world-frame normals (`colors`,
    `normals` empty when the view has none); those pixels are then used (ok is updated)."""
    for i in range(ok.shape[0]):  # used before this source: not again
        if ok[i] and used[sy[i], sx[i]]:
            ok[i] = False
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for i in range(ok.shape[0]):
        if not ok[i]:
            continue
        v, u = sy[i], sx[i]
        used[v, u] = True
        d = np.float64(depth[v, u])
        c0, c1, c2 = (u - cx) / fx * d - t[0], (v - cy) / fy * d - t[1], d - t[2]
        for k in range(3):  # world = R^T (camera - t)
            total[i, k] += R[0, k] * c0 + R[1, k] * c1 + R[2, k] * c2
            if colors.shape[0]:
                rgb[i, k] += colors[v, u, k]
            if normals.shape[0]:
                normal[i, k] += R[0, k] * normals[v, u, 0] + R[1, k] * normals[v, u, 1] + R[2, k] * normals[v, u, 2]
        count[i] += 1


def fuse(views: list[DepthView], *, rel_tolerance: float = 0.01,
         max_reprojection: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 3), colours (N, 3) uint8, unit normals (N, 3)) in the world frame from the views' geometric
    depth maps: each kept pixel averaged with the consistent, not yet used pixels of its source views."""
    used = [np.zeros(v.depth.shape, bool) for v in views]
    by_index = {v.view.index: k for k, v in enumerate(views)}
    all_xyz, all_rgb, all_n = [], [], []
    for k, ref in enumerate(views):
        ys, xs = np.nonzero((ref.depth > 0) & ~used[k])
        used[k][ys, xs] = True
        if not len(ys):
            continue
        xyz = back_project(ref.view, ref.depth, ys, xs)
        z_ref = ref.depth[ys, xs].astype(float)
        total, count = xyz.copy(), np.ones(len(ys))
        rgb = ref.colors[ys, xs].astype(float) if ref.colors is not None else np.zeros((len(ys), 3))
        normal = (ref.normals[ys, xs] @ ref.view.R) if ref.normals is not None else np.zeros((len(ys), 3))
        for s in ref.sources:
            j = by_index.get(s)
            if j is None:
                continue
            src = views[j]
            ok, sy, sx = _matches(ref.view, ys, xs, z_ref, src.view, src.depth, rel_tolerance, max_reprojection)
            _add_source(ok, sy, sx, used[j], src.depth, src.view.K, src.view.R, src.view.t,
                        _NONE if src.colors is None else src.colors, _NONE if src.normals is None else src.normals,
                        total, count, rgb, normal)
        all_xyz.append(total / count[:, None])
        all_rgb.append(rgb / count[:, None])
        norm = np.linalg.norm(normal, axis=1, keepdims=True)
        all_n.append(np.where(norm > 0, normal / np.maximum(norm, 1e-12), 0.0))
    if not all_xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 3))
    rgb = np.clip(np.round(np.concatenate(all_rgb)), 0, 255).astype(np.uint8)
    return np.concatenate(all_xyz), rgb, np.concatenate(all_n)
