"""Multi-view triangulation, batched over many points: DLT, Gauss-Newton refinement, angles and depths.

Every function takes padded arrays so thousands of points are solved in one numpy call: for n points with up
to
k views, R (n,k,3,3) and t (n,k,3) are the cam_from_world poses, x (n,k,2) the undistorted normalised image
coordinates and mask (n,k) marks the views that exist. Errors are in normalised units (multiply by the focal
length for pixels).
"""

from functools import partial

import numpy as np


def triangulate_dlt(R: np.ndarray, t: np.ndarray, x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Linear triangulation (n,3): the null vector of the stacked x cross P X = 0 rows (least squares)."""
    P = np.concatenate([R, t[..., None]], axis=-1)  # (n,k,3,4)
    w = mask[..., None].astype(float)
    rows1 = (x[..., 0:1] * P[..., 2, :] - P[..., 0, :]) * w
    rows2 = (x[..., 1:2] * P[..., 2, :] - P[..., 1, :]) * w
    A = np.concatenate([rows1, rows2], axis=1)  # (n,2k,4)
    A = A / np.maximum(np.linalg.norm(A, axis=-1, keepdims=True), 1e-12)
    # the smallest right singular vector of A is the smallest eigenvector of the 4x4 A^T A (half the time)
    X = np.linalg.eigh(A.transpose(0, 2, 1) @ A)[1][:, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:4]


def two_view_midpoints(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Midpoints (n,3) of the closest points of the rays of normalised matches x1 (camera [I|0]) and x2
    (camera [R|t]), NaN where the rays are parallel: closed form, so cheap enough to test pose hypotheses and
    to start a refinement."""
    d1 = np.column_stack([x1, np.ones(len(x1))])
    d2 = np.column_stack([x2, np.ones(len(x2))]) @ R  # rows R^T (x2, 1): the second rays in the first frame
    c2 = -R.T @ t
    a, b, c = (d1 * d1).sum(axis=1), (d1 * d2).sum(axis=1), (d2 * d2).sum(axis=1)
    p, q = d1 @ c2, d2 @ c2
    det = b * b - a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        s1, s2 = (b * q - c * p) / det, (a * q - b * p) / det
        X = 0.5 * (s1[:, None] * d1 + c2 + s2[:, None] * d2)
    X[~(np.abs(det) > 1e-12 * a * c)] = np.nan
    return X


def residuals(X: np.ndarray, R: np.ndarray, t: np.ndarray, x: np.ndarray,
              mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised residuals (n,k,2) (zero where mask is False) and depths (n,k)."""
    Xc = np.einsum("nkij,nj->nki", R, X) + t
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = Xc[..., :2] / z[..., None] - x
    r = np.where(mask[..., None], r, 0.0)
    return r, z


COMPILED_MIN_VIEWS = 100_000  # points x views from which `refine_points` runs compiled (kernels.py)


def refine_points(X: np.ndarray, R: np.ndarray, t: np.ndarray, x: np.ndarray, mask: np.ndarray,
                  iterations: int = 5) -> np.ndarray:
    """Gauss-Newton on the normalised reprojection error of each point, all points at once.

    DLT minimises an algebraic error; this step moves each point to the (locally) least-squares reprojection
    optimum, which is what the reprojection checks and bundle adjustment measure. A point whose normal equations
    are near singular (rays almost parallel: a point near infinity) is not moved by that step; the angle checks
    decide it. From `COMPILED_MIN_VIEWS` entries of `mask` on it runs compiled, point by point over its views
    (`kernels.gauss_newton_points`, the same arithmetic about 12x faster: the mappers re-fit every point their
    subset BAs leave out, at a thousand images hundreds of thousands a round); below, numpy's batched passes cost
    less than loading numba, which a small run never needs.
    """
    if mask.size >= COMPILED_MIN_VIEWS:
        from .kernels import gauss_newton_points  # noqa: PLC0415 - numba, for large batches only

        as_float = partial(np.ascontiguousarray, dtype=np.float64)
        return gauss_newton_points(np.array(X, dtype=np.float64).reshape(-1, 3), as_float(R), as_float(t),
                                   as_float(x), np.ascontiguousarray(mask, dtype=np.bool_), iterations)
    X = np.array(X, dtype=float)
    w = mask.astype(float)
    R0, R1, R2 = R[..., 0, :], R[..., 1, :], R[..., 2, :]
    for _ in range(iterations):
        Xc = np.einsum("nkij,nj->nki", R, X) + t
        z = np.where(np.abs(Xc[..., 2]) < 1e-12, 1e-12, Xc[..., 2])
        u, v = Xc[..., 0] / z, Xc[..., 1] / z
        # d(u)/dX = (R0 - u R2) / z, d(v)/dX = (R1 - v R2) / z; absent views weigh 0
        wz = (w / z)[..., None]
        J = np.concatenate([(R0 - u[..., None] * R2) * wz, (R1 - v[..., None] * R2) * wz], axis=1)  # (n,2k,3)
        res = np.concatenate([(u - x[..., 0]) * w, (v - x[..., 1]) * w], axis=1)  # (n,2k)
        Jt = J.transpose(0, 2, 1)  # batched matmul: ~3x faster than the equivalent einsum here
        H = Jt @ J
        H[:, (0, 1, 2), (0, 1, 2)] += 1e-12
        step, det = _solve_sym3(H, (Jt @ res[..., None])[..., 0])
        tr = np.trace(H, axis1=1, axis2=2)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(step).all(axis=1) & (det > 1e-9 * tr ** 3)
        X = X - np.where(ok[:, None], step, 0.0)
    return X


def _solve_sym3(H, g):
    """Solutions (n,3) and determinants (n,) of symmetric 3x3 systems H x = g, by cofactors: a tenth of the
    time of the batched LAPACK solve and determinant for this size."""
    a, b, c, d, e, f = H[:, 0, 0], H[:, 0, 1], H[:, 0, 2], H[:, 1, 1], H[:, 1, 2], H[:, 2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    g0, g1, g2 = g[:, 0], g[:, 1], g[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.stack([A * g0 + B * g1 + C * g2, B * g0 + D * g1 + E * g2, C * g0 + E * g1 + F * g2], axis=1)
        return x / det[:, None], det


def _unit_rays(X, centers) -> np.ndarray:
    """Unit viewing rays (n,k,3) from the camera centres (n,k,3) to the points X (n,3)."""
    rays = X[:, None, :] - centers
    return rays / np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-300)


def max_triangulation_angle_deg(X: np.ndarray, centers: np.ndarray, mask: np.ndarray,
                                chunk_elements: int = 2_000_000) -> np.ndarray:
    """Largest angle (deg) between any two viewing rays of each point; centers (n,k,3) camera centres.

    All view pairs are compared ((n,k,k) cosines), in chunks of points so memory stays bounded for long
    tracks.
    """
    n, k = mask.shape
    step = max(1, chunk_elements // max(k * k, 1))
    if n > step:
        return np.concatenate([max_triangulation_angle_deg(X[s:s + step], centers[s:s + step],
                                                           mask[s:s + step]) for s in range(0, n, step)])
    rays = np.where(mask[..., None], _unit_rays(X, centers), np.nan)
    cos = rays @ rays.transpose(0, 2, 1)
    cos = np.where(np.isnan(cos), 1.0, cos)
    return np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))


def reaches_triangulation_angle(X: np.ndarray, centers: np.ndarray, mask: np.ndarray,
                                min_deg: float) -> np.ndarray:
    """Whether the largest angle between two viewing rays of each point reaches `min_deg` (the same test as
    `max_triangulation_angle_deg(...) >= min_deg`). The angles to each point's first ray bound that largest
    angle from below and decide nearly every point; only the rest compare all view pairs."""
    n = len(mask)
    if n == 0:
        return np.zeros(0, bool)
    rays = _unit_rays(X, centers)
    first = rays[np.arange(n), np.argmax(mask, axis=1)]
    cos = np.where(mask, np.einsum("nkj,nj->nk", rays, first), 1.0)
    with np.errstate(invalid="ignore"):
        ok = np.degrees(np.arccos(np.clip(cos.min(axis=1), -1.0, 1.0))) >= min_deg
    rest = np.flatnonzero(~ok)
    if len(rest):
        ok[rest] = max_triangulation_angle_deg(X[rest], centers[rest], mask[rest]) >= min_deg
    return ok


def triangulation_angle_deg(center1: np.ndarray, center2: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Angle (deg) at each point X (n,3) between the rays to two camera centres (n,3) or (3,)."""
    a, b = X - center1, X - center2
    cos = np.sum(a * b, axis=-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
