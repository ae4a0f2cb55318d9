"""The rotation test's and the point refinement's inner loops, and symmetric 3x3 inverses, compiled with numba.

The global mapper's view graph tests every verified pair for a rotation about the camera centre (thousands at a
few hundred images), and the mappers re-fit every point their subset bundle adjustments leave out: numpy's
batched passes spent most of that time on temporaries. `two_view.rotation_between_views` imports this module at
its first call and `triangulation.refine_points` for large batches only: importing the geometry (every command's
start-up) does not load numba, nor does a small run. Global positioning (sfm/), compiled itself, inverts its
points' blocks with `symmetric_inverses`.
"""

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def symmetric_cofactors(a: float, b: float, c: float, d: float, e: float,
                        f: float) -> tuple[float, float, float, float, float, float, float]:  # pragma: no cover
    """(A, B, C, D, E, F, det): the cofactors of the symmetric 3x3 matrix [[a, b, c], [b, d, e], [c, e, f]] (its
    adjugate is [[A, B, C], [B, D, E], [C, E, F]], symmetric as it is) and its determinant."""
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    return A, B, C, D, E, F, a * A + b * B + c * C


@njit(cache=True, nogil=True)
def symmetric_inverses(H: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The inverse of each symmetric 3x3 block of H (n,3,3), by its adjugate: one pass, where LAPACK's batched
    inverse costs about as much as the rest of a global positioning step's pass over the points."""
    out = np.empty_like(H)
    for p in range(len(H)):
        A, B, C, D, E, F, det = symmetric_cofactors(H[p, 0, 0], H[p, 0, 1], H[p, 0, 2], H[p, 1, 1], H[p, 1, 2],
                                                    H[p, 2, 2])
        out[p, 0, 0], out[p, 0, 1], out[p, 0, 2] = A / det, B / det, C / det
        out[p, 1, 0], out[p, 1, 1], out[p, 1, 2] = B / det, D / det, E / det
        out[p, 2, 0], out[p, 2, 1], out[p, 2, 2] = C / det, E / det, F / det
    return out


@njit(cache=True, nogil=True)
def unit_rays(x: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Unit viewing rays (n,3) of normalised image points (n,2)."""
    out = np.empty((x.shape[0], 3))
    for k in range(x.shape[0]):
        norm = np.sqrt(x[k, 0] ** 2 + x[k, 1] ** 2 + 1.0)
        out[k, 0], out[k, 1], out[k, 2] = x[k, 0] / norm, x[k, 1] / norm, 1.0 / norm
    return out


@njit(cache=True, nogil=True)
def _rotation_inliers(R, r1, x2, threshold2, out):  # pragma: no cover - compiled
    """Fills `out` with whether R turns each ray of r1 to within the threshold of its match x2, in front of the
    camera; returns how many do."""
    count = 0
    for k in range(r1.shape[0]):
        p0 = R[0, 0] * r1[k, 0] + R[0, 1] * r1[k, 1] + R[0, 2] * r1[k, 2]
        p1 = R[1, 0] * r1[k, 0] + R[1, 1] * r1[k, 1] + R[1, 2] * r1[k, 2]
        z = R[2, 0] * r1[k, 0] + R[2, 1] * r1[k, 1] + R[2, 2] * r1[k, 2]
        d2 = (p0 - x2[k, 0] * z) ** 2 + (p1 - x2[k, 1] * z) ** 2
        ok = z > 0 and d2 < threshold2 * z * z
        out[k] = ok
        count += ok
    return count


@njit(cache=True, nogil=True)
def _kabsch(M):  # pragma: no cover - compiled
    """rotation.nearest_rotation of one 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    if np.linalg.det(U @ Vt) < 0:
        U[:, 2] = -U[:, 2]
    return U @ Vt


@njit(cache=True, nogil=True)
def best_rotation_sample(r1: np.ndarray, r2: np.ndarray, x2: np.ndarray, threshold2: float, samples: np.ndarray,
                         best: int, inliers: np.ndarray, found: np.ndarray) -> int:  # pragma: no cover - compiled
    """The rotation of each sample (a pair of matches, rows of `samples`) scored by its inliers; where one has
    more than `best`, `inliers` becomes the first such sample's. Returns the best count."""
    for s in range(samples.shape[0]):
        a, b = samples[s, 0], samples[s, 1]
        M = np.outer(r2[a], r1[a]) + np.outer(r2[b], r1[b])
        count = _rotation_inliers(_kabsch(M), r1, x2, threshold2, found)
        if count > best:
            best = count
            inliers[:] = found
    return best


@njit(cache=True, nogil=True)
def refit_rotation(r1: np.ndarray, r2: np.ndarray, x2: np.ndarray, threshold2: float, inliers: np.ndarray,
                   found: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """(R, inliers): the least-squares rotation of the inliers, refitted on its own inliers up to three times."""
    R = np.eye(3)
    for _ in range(3):
        if inliers.sum() < 2:
            break
        M = np.zeros((3, 3))
        for k in range(r1.shape[0]):
            if inliers[k]:
                M += np.outer(r2[k], r1[k])
        R = _kabsch(M)
        _rotation_inliers(R, r1, x2, threshold2, found)
        if np.array_equal(found, inliers):
            break
        inliers[:] = found
    return R, inliers


@njit(cache=True, nogil=True)
def gauss_newton_points(X: np.ndarray, R: np.ndarray, t: np.ndarray, x: np.ndarray, mask: np.ndarray,
                        iterations: int) -> np.ndarray:  # pragma: no cover - compiled
    """`triangulation.refine_points`' iterations on X (n,3) in place, point by point over its views; returns X.
    A step is skipped where the point's normal equations are near singular (rays almost parallel)."""
    H, g = np.empty(6), np.empty(3)
    for p in range(X.shape[0]):
        for _ in range(iterations):
            H[:] = 0.0
            g[:] = 0.0
            for j in range(mask.shape[1]):
                if not mask[p, j]:
                    continue
                c0 = R[p, j, 0, 0] * X[p, 0] + R[p, j, 0, 1] * X[p, 1] + R[p, j, 0, 2] * X[p, 2] + t[p, j, 0]
                c1 = R[p, j, 1, 0] * X[p, 0] + R[p, j, 1, 1] * X[p, 1] + R[p, j, 1, 2] * X[p, 2] + t[p, j, 1]
                c2 = R[p, j, 2, 0] * X[p, 0] + R[p, j, 2, 1] * X[p, 1] + R[p, j, 2, 2] * X[p, 2] + t[p, j, 2]
                z = 1e-12 if abs(c2) < 1e-12 else c2
                u, v = c0 / z, c1 / z
                # d(u)/dX = (R0 - u R2) / z, d(v)/dX = (R1 - v R2) / z
                a0 = (R[p, j, 0, 0] - u * R[p, j, 2, 0]) / z
                a1 = (R[p, j, 0, 1] - u * R[p, j, 2, 1]) / z
                a2 = (R[p, j, 0, 2] - u * R[p, j, 2, 2]) / z
                b0 = (R[p, j, 1, 0] - v * R[p, j, 2, 0]) / z
                b1 = (R[p, j, 1, 1] - v * R[p, j, 2, 1]) / z
                b2 = (R[p, j, 1, 2] - v * R[p, j, 2, 2]) / z
                ru, rv = u - x[p, j, 0], v - x[p, j, 1]
                H[0] += a0 * a0 + b0 * b0
                H[1] += a0 * a1 + b0 * b1
                H[2] += a0 * a2 + b0 * b2
                H[3] += a1 * a1 + b1 * b1
                H[4] += a1 * a2 + b1 * b2
                H[5] += a2 * a2 + b2 * b2
                g[0] += a0 * ru + b0 * rv
                g[1] += a1 * ru + b1 * rv
                g[2] += a2 * ru + b2 * rv
            a, d, f = H[0] + 1e-12, H[3] + 1e-12, H[5] + 1e-12
            A, B, C, D, E, F, det = symmetric_cofactors(a, H[1], H[2], d, H[4], f)
            tr = a + d + f
            if not det > 1e-9 * tr ** 3:  # a point near infinity: left to the angle checks
                continue
            s0 = (A * g[0] + B * g[1] + C * g[2]) / det
            s1 = (B * g[0] + D * g[1] + E * g[2]) / det
            s2 = (C * g[0] + E * g[1] + F * g[2]) / det
            if np.isfinite(s0) and np.isfinite(s1) and np.isfinite(s2):
                X[p, 0] -= s0
                X[p, 1] -= s1
                X[p, 2] -= s2
    return X
