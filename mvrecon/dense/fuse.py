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


def project(view: View, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pixels (N, 2), depths (N,)) of world points in `view`."""
    cam = xyz @ view.R.T + view.t
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam[:, :2] / z[:, None]) * [view.K[0, 0], view.K[1, 1]] + [view.K[0, 2], view.K[1, 2]]
    return uv, z


def _matches(ref: View, xyz: np.ndarray, z_ref: np.ndarray, uv_ref: np.ndarray, src: View, src_depth: np.ndarray,
             rel_tolerance: float, max_reprojection: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(consistent mask, source rows, source columns) of the reference points `xyz` against one source view."""
    uv, z = project(src, xyz)
    rows, cols = src_depth.shape
    ok = (z > 0) & np.isfinite(uv).all(axis=1)
    xs = np.where(ok, np.round(uv[:, 0]), -1).astype(np.int64)
    ys = np.where(ok, np.round(uv[:, 1]), -1).astype(np.int64)
    ok &= (xs >= 0) & (ys >= 0) & (xs < cols) & (ys < rows)
    xs, ys = np.where(ok, xs, 0), np.where(ok, ys, 0)
    d = src_depth[ys, xs]
    ok &= d > 0
    back = back_project(src, src_depth, ys, xs)
    uv2, z2 = project(ref, back)
    with np.errstate(invalid="ignore"):
        ok &= np.abs(z2 - z_ref) <= rel_tolerance * z_ref
        ok &= np.hypot(*(uv2 - uv_ref).T) <= max_reprojection
    return ok, ys, xs


def geometric_filter(ref: DepthView, sources: list[DepthView], *, rel_tolerance: float = 0.01,
                     max_reprojection: float = 1.0, min_consistent: int = 2) -> np.ndarray:
    """The reference depth map with 0 where fewer than `min_consistent` source views agree with it."""
    ys, xs = np.nonzero(ref.depth > 0)
    xyz = back_project(ref.view, ref.depth, ys, xs)
    uv_ref = np.stack([xs, ys], axis=1).astype(float)
    z_ref = ref.depth[ys, xs].astype(float)
    count = np.zeros(len(ys), np.int32)
    for src in sources:
        ok, _, _ = _matches(ref.view, xyz, z_ref, uv_ref, src.view, src.depth, rel_tolerance, max_reprojection)
        count += ok
    out = np.zeros_like(ref.depth)
    keep = count >= min_consistent
    out[ys[keep], xs[keep]] = ref.depth[ys[keep], xs[keep]]
    return out


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
        uv_ref = np.stack([xs, ys], axis=1).astype(float)
        total, count = xyz.copy(), np.ones(len(ys))
        rgb = ref.colors[ys, xs].astype(float) if ref.colors is not None else np.zeros((len(ys), 3))
        normal = (ref.normals[ys, xs] @ ref.view.R) if ref.normals is not None else np.zeros((len(ys), 3))
        for s in ref.sources:
            j = by_index.get(s)
            if j is None:
                continue
            src = views[j]
            ok, sy, sx = _matches(ref.view, xyz, z_ref, uv_ref, src.view, src.depth, rel_tolerance,
                                  max_reprojection)
            ok &= ~used[j][sy, sx]
            used[j][sy[ok], sx[ok]] = True
            total[ok] += back_project(src.view, src.depth, sy[ok], sx[ok])
            count[ok] += 1
            if src.colors is not None:
                rgb[ok] += src.colors[sy[ok], sx[ok]]
            if src.normals is not None:
                normal[ok] += src.normals[sy[ok], sx[ok]] @ src.view.R
        all_xyz.append(total / count[:, None])
        all_rgb.append(rgb / count[:, None])
        norm = np.linalg.norm(normal, axis=1, keepdims=True)
        all_n.append(np.where(norm > 0, normal / np.maximum(norm, 1e-12), 0.0))
    if not all_xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 3))
    rgb = np.clip(np.round(np.concatenate(all_rgb)), 0, 255).astype(np.uint8)
    return np.concatenate(all_xyz), rgb, np.concatenate(all_n)
