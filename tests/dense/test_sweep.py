"""Plane-sweep depth: a fronto-parallel textured plane seen by three cameras, and the normals of a depth map."""

import cv2
import numpy as np

from mvrecon.dense.sweep import normals_from_depth, pyramid_depth

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
DEPTH = 4.0


def _render_plane(R: np.ndarray, t: np.ndarray, texture: np.ndarray, scale: float) -> np.ndarray:
    """The view (240x320) of the plane z = DEPTH (world = reference camera) carrying `texture`, whose pixel (u, v)
    sits at x = (u - w/2) * scale, y = (v - h/2) * scale."""
    h, w = texture.shape
    plane_from_texture = np.array([[scale, 0, -w / 2 * scale], [0, scale, -h / 2 * scale], [0, 0, 1]])
    image_from_plane = K @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * DEPTH + t])
    H = image_from_plane @ plane_from_texture
    return cv2.warpPerspective(texture, H, (320, 240), flags=cv2.INTER_LINEAR)


def test_fronto_parallel_plane_within_half_percent_on_95_percent_of_pixels():
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.random((1200, 1600)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    scale = 3 * DEPTH / 300 / 1200 * 240 / 2  # the texture covers about three times the reference view
    cams = [(np.eye(3), np.zeros(3))]
    for angle, shift in ((4.0, [0.4, 0.0, 0.0]), (-3.0, [-0.35, 0.1, 0.05]), (2.0, [0.0, -0.3, 0.0])):
        R = cv2.Rodrigues(np.radians([0.0, angle, 0.0]))[0]
        cams.append((R, np.asarray(shift, float)))
    images = [_render_plane(R, t, texture, scale) for R, t in cams]
    # the default: a 320-px view is swept at full resolution
    depth, _ = pyramid_depth(images[0], images[1:], K, [K] * 3, cams[1:], (2.0, 10.0))
    good = np.abs(depth - DEPTH) <= 0.005 * DEPTH
    assert good.mean() >= 0.95, f"{good.mean():.3f} of the pixels within 0.5%"
    assert np.median(np.abs(depth[good] - DEPTH)) < 0.002 * DEPTH
    # coarse to fine, as larger views are: swept at 160 px, then searched locally at full resolution
    depth, _ = pyramid_depth(images[0], images[1:], K, [K] * 3, cams[1:], (2.0, 10.0), coarse_size=160)
    err = np.abs(depth - DEPTH) / DEPTH
    assert (err <= 0.005).mean() >= 0.92 and (err <= 0.01).mean() >= 0.97, (err <= 0.005).mean()


def test_normals_of_a_slanted_plane_face_the_camera():
    rows, cols = np.mgrid[0:240, 0:320].astype(float)
    n_true = np.array([0.0, -0.6, -0.8])  # a floor-like plane n . X = -3, seen from above it
    rays = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(cols)], axis=2)
    depth = (-3.0 / (rays @ n_true)).astype(np.float32)
    normals = normals_from_depth(depth, K)
    inner = normals[1:-1, 1:-1].reshape(-1, 3)
    assert np.allclose(inner, n_true, atol=1e-3)
    assert not normals[0].any() and not normals[:, -1].any()
