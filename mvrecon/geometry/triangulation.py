"""Multi-view triangulation, batched over many points: DLT, Gauss-Newton refinement, angles and depths.

Every function takes padded arrays so thousands of points are solved in one numpy call: for n points with up
to
k views, R (n,k,3,3) and t (n,k,3) are the cam_from_world poses, x (n,k,2) the undistorted normalised image
coordinates and mask (n,k) marks the views that exist. Errors are in normalised units (multiply by the focal
length for pixels).
"""

import numpy as np


def triangulate_dlt(R, t, x, mask) -> np.ndarray:
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


def residuals(X, R, t, x, mask) -> tuple[np.ndarray, np.ndarray]:
    """Normalised residuals (n,k,2) (zero where mask is False) and depths (n,k)."""
    Xc = np.einsum("nkij,nj->nki", R, X) + t
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = Xc[..., :2] / z[..., None] - x
    r = np.where(mask[..., None], r, 0.0)
    return r, z


def refine_points(X, R, t, x, mask, iterations: int = 5) -> np.ndarray:
    """Gauss-Newton on the normalised reprojection error of each point, all points at once.

    DLT minimises an algebraic error; this step moves each point to the (locally) least-squares reprojection
    optimum, which is what the reprojection checks and bundle adjustment measure.
    """
    X = np.array(X, dtype=float)
    for _ in range(iterations):
        Xc = np.einsum("nkij,nj->nki", R, X) + t
        z = np.where(np.abs(Xc[..., 2]) < 1e-12, 1e-12, Xc[..., 2])
        r = Xc[..., :2] / z[..., None] - x
        # d(u)/dX = (R0 - u R2) / z, d(v)/dX = (R1 - v R2) / z
        u, v = Xc[..., 0] / z, Xc[..., 1] / z
        Ju = (R[..., 0, :] - u[..., None] * R[..., 2, :]) / z[..., None]
        Jv = (R[..., 1, :] - v[..., None] * R[..., 2, :]) / z[..., None]
        w = mask[..., None].astype(float)
        J = np.concatenate([Ju * w, Jv * w], axis=1)  # (n,2k,3)
        res = np.concatenate([r[..., 0] * mask, r[..., 1] * mask], axis=1)  # (n,2k)
        Jt = J.transpose(0, 2, 1)  # batched matmul: ~3x faster than the equivalent einsum here
        H = Jt @ J + 1e-12 * np.eye(3)
        g = (Jt @ res[..., None])[..., 0]
        ok = np.isfinite(H).all(axis=(1, 2)) & np.isfinite(g).all(axis=1)
        # points near infinity (rays almost parallel) have a rank-deficient H: leave them to the angle check
        tr = np.where(ok, np.trace(H, axis1=1, axis2=2), 0.0)
        ok &= np.where(ok, np.linalg.det(np.where(ok[:, None, None], H, np.eye(3))), 0.0) > 1e-9 * tr ** 3
        step = np.zeros_like(X)
        step[ok] = np.linalg.solve(H[ok], g[ok][..., None])[..., 0]
        X = X - step
    return X


def max_triangulation_angle_deg(X, centers, mask, chunk_elements: int = 2_000_000) -> np.ndarray:
    """Largest angle (deg) between any two viewing rays of each point; centers (n,k,3) camera centres.

    All view pairs are compared ((n,k,k) cosines), in chunks of points so memory stays bounded for long
    tracks.
    """
    n, k = mask.shape
    step = max(1, chunk_elements // max(k * k, 1))
    if n > step:
        return np.concatenate([max_triangulation_angle_deg(X[s:s + step], centers[s:s + step],
                                                           mask[s:s + step]) for s in range(0, n, step)])
    rays = X[:, None, :] - centers
    rays = rays / np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-300)
    rays = np.where(mask[..., None], rays, np.nan)
    cos = rays @ rays.transpose(0, 2, 1)
    cos = np.where(np.isnan(cos), 1.0, cos)
    return np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))


def triangulation_angle_deg(center1, center2, X) -> np.ndarray:
    """Angle (deg) at each point X (n,3) between the rays to two camera centres (n,3) or (3,)."""
    a, b = X - center1, X - center2
    cos = np.sum(a * b, axis=-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
