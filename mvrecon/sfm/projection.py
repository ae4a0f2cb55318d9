"""Pixels of many views at once, each point seen by one of many posed cameras, in one compiled pass.

The mappers project every observation of a model several times a round (the filters, the bundle adjustments'
point choice, the triangulation gates): at a thousand images that is millions of views a call.
`Reconstruction.project` hands a call of `model.COMPILED_MIN_VIEWS` views or more of a model of polynomial lenses
(the pinholes, SIMPLE_RADIAL, RADIAL and OPENCV: k1, k2, p1, p2) to this module: one loop, the same arithmetic as
`geometry.camera.project` in a fraction of the time of numpy's passes over (n, 3, 3) rotations and per-camera masks
(docs/benchmarks.md, "Every view projected in one compiled pass, and the BA points chosen by two sorts"). A model
with an equidistant fisheye stays with `geometry.camera.project`.
"""

import numpy as np
from numba import njit

from ..geometry import camera as cammodel


def project_views(R: np.ndarray, t: np.ndarray, images: np.ndarray, xyz: np.ndarray, lens_of_image: np.ndarray,
                  lenses: list[tuple[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (n,2; NaN behind the camera) and depths (n,) of the points `xyz` (n,3), point k seen by image
    `images[k]` with pose R[i], t[i] (camera from world) and lens `lenses[lens_of_image[i]]`, a (model, params)
    of a polynomial lens (not OPENCV_FISHEYE)."""
    # a row per lens: fx, fy, cx, cy, k1, k2, p1, p2
    table = np.array([[*cammodel.split(model, params)[:4], *cammodel.distortion_coefficients(model, params)]
                      for model, params in lenses], dtype=np.float64).reshape(-1, 8)
    uv = np.empty((len(images), 2))
    depth = np.empty(len(images))
    _project(np.ascontiguousarray(images, dtype=np.int64), np.ascontiguousarray(xyz, dtype=np.float64),
             np.ascontiguousarray(R, np.float64), np.ascontiguousarray(t, np.float64),
             np.ascontiguousarray(lens_of_image, dtype=np.int64), table, uv, depth)
    return uv, depth


@njit(cache=True, nogil=True)
def _project(images, xyz, R, t, lens_of_image, table, uv, depth):
    for k in range(len(images)):
        i = images[k]
        X0, X1, X2 = xyz[k, 0], xyz[k, 1], xyz[k, 2]
        x = R[i, 0, 0] * X0 + R[i, 0, 1] * X1 + R[i, 0, 2] * X2 + t[i, 0]
        y = R[i, 1, 0] * X0 + R[i, 1, 1] * X1 + R[i, 1, 2] * X2 + t[i, 1]
        z = R[i, 2, 0] * X0 + R[i, 2, 1] * X1 + R[i, 2, 2] * X2 + t[i, 2]
        depth[k] = z
        if not z > 0:  # behind the camera
            uv[k, 0] = np.nan
            uv[k, 1] = np.nan
            continue
        p = table[lens_of_image[i]]
        u = x / z
        v = y / z
        r2 = u * u + v * v
        radial = p[4] * r2 + p[5] * r2 * r2
        du = u * radial + 2 * p[6] * u * v + p[7] * (r2 + 2 * u * u)
        dv = v * radial + 2 * p[7] * u * v + p[6] * (r2 + 2 * v * v)
        uv[k, 0] = p[0] * (u + du) + p[2]
        uv[k, 1] = p[1] * (v + dv) + p[3]
