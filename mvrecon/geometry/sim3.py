"""Similarity and rigid transforms between point sets: Umeyama's closed form, and a RANSAC wrapper for outliers."""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Sim3:
    """dst = scale * R @ src + t."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points, dtype=float) @ self.R.T + self.t

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.t
        return M

    def inverse(self) -> "Sim3":
        Ri = self.R.T
        return Sim3(1.0 / self.scale, Ri, -Ri @ self.t / self.scale)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True,
            weights: np.ndarray | None = None) -> Sim3:
    """Least-squares Sim3 (or rigid, with_scale=False) taking src (N,3) onto dst (N,3); Umeyama 1991."""
    src, dst = np.asarray(src, dtype=float), np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[0] < 3:
        raise ValueError(f"umeyama needs two (N,3) arrays with N >= 3, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(src.shape[1])
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[-1, -1] = -1
    R = U @ S @ Vt
    var_s = float(w @ (xs ** 2).sum(axis=1))
    scale = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - scale * R @ mu_s
    return Sim3(scale, R, t)


def ransac_umeyama(src: np.ndarray, dst: np.ndarray, threshold: float, with_scale: bool = True,
                   iterations: int = 1000, seed: int = 0) -> tuple[Sim3, np.ndarray]:
    """Robust Sim3: minimal 3-point samples, inliers within `threshold` (dst units), refit on the best inliers.

    Returns the transform and the boolean inlier mask. With fewer than 3 points it raises ValueError.
    """
    src, dst = np.asarray(src, dtype=float), np.asarray(dst, dtype=float)
    n = len(src)
    if n < 3:
        raise ValueError(f"need at least 3 point pairs for a Sim3, got {n}")
    rng = np.random.default_rng(seed)
    best_mask, best_count, best_err = np.ones(n, bool), -1, np.inf
    for _ in range(iterations if n > 3 else 1):
        idx = rng.choice(n, 3, replace=False)
        try:
            T = umeyama(src[idx], dst[idx], with_scale)
        except (ValueError, np.linalg.LinAlgError):
            continue
        err = np.linalg.norm(T.apply(src) - dst, axis=1)
        mask = err < threshold
        count, total = int(mask.sum()), float(np.minimum(err, threshold).sum())
        if count > best_count or (count == best_count and total < best_err):
            best_mask, best_count, best_err = mask, count, total
    if best_count < 3:
        best_mask = np.ones(n, bool)
    T = umeyama(src[best_mask], dst[best_mask], with_scale)
    for _ in range(3):  # refit on the inliers of the refined transform
        mask = np.linalg.norm(T.apply(src) - dst, axis=1) < threshold
        if mask.sum() < 3 or np.array_equal(mask, best_mask):
            break
        best_mask = mask
        T = umeyama(src[best_mask], dst[best_mask], with_scale)
    return T, best_mask
