"""The seed paper's disparity method: region-based stereo matching with global error energy minimisation.

The seed (section 3.2/4) cites the method of Alagoz (2008), "Obtaining depth maps from colour images by region
based stereo matching algorithms". For every candidate disparity d an error-energy matrix is built,

    e(y, x, d) = 1/(3 n m) * sum over an n x m window and the colour channels of (L(y, x) - R(y, x - d))^2,

the matrices are smoothed by applying an averaging filter to each of them `smoothing_iterations` times (the
"global" part: every pixel's energy is pulled towards its neighbourhood's), the disparity with the least smoothed
energy is chosen, and estimates whose energy exceeds Ve = alpha * mean(chosen energies) are removed as unreliable
("no estimate"). The reliability of the map is the inverse of the mean energy of the kept estimates.
The left image is the reference (Middlebury convention, x_right = x_left - d).
"""

from dataclasses import dataclass

import cv2
import numpy as np

from ..progress import progress


@dataclass(frozen=True)
class GEEConfig:
    """window: n x m block of the error energy (odd, px); smoothing_iterations and smoothing_size: the averaging
    filter applied to each energy matrix and how often; alpha: tolerance of the reliability threshold (Ve = alpha
    times the mean energy; larger keeps more pixels); min/num_disparities: the search range."""

    window: int = 9
    smoothing_iterations: int = 16
    smoothing_size: int = 3
    alpha: float = 3.0
    min_disparity: int = 0
    num_disparities: int = 64


@dataclass(frozen=True)
class GEEResult:
    disparity: np.ndarray  # float32, NaN = no estimate (unreliable)
    energy: np.ndarray  # smoothed error energy of the chosen disparity
    threshold: float  # Ve
    reliability: float | None  # inverse mean energy of the kept estimates; None when none is kept


def error_energy_volume(left: np.ndarray, right: np.ndarray, config: GEEConfig) -> np.ndarray:
    """(D, H, W) float32 smoothed error energies; disparities whose right pixel falls outside get +inf."""
    L = np.asarray(left, dtype=np.float32)
    R = np.asarray(right, dtype=np.float32)
    if L.ndim == 2:
        L, R = L[..., None], R[..., None]
    h, w, channels = L.shape
    volume = np.empty((config.num_disparities, h, w), dtype=np.float32)
    for i in progress(range(config.num_disparities), desc="GEE energies", unit="disparity"):
        d = config.min_disparity + i
        shifted = np.empty_like(R)
        if d >= 0:
            shifted[:, d:] = R[:, :w - d] if d else R
            shifted[:, :d] = R[:, :1]
        else:
            shifted[:, :w + d] = R[:, -d:]
            shifted[:, w + d:] = R[:, -1:]
        e = ((L - shifted) ** 2).sum(axis=2) / channels
        e = cv2.boxFilter(e, -1, (config.window, config.window), borderType=cv2.BORDER_REFLECT)
        for _ in range(config.smoothing_iterations):
            e = cv2.blur(e, (config.smoothing_size, config.smoothing_size), borderType=cv2.BORDER_REFLECT)
        if d > 0:
            e[:, :d] = np.inf
        elif d < 0:
            e[:, w + d:] = np.inf
        volume[i] = e
    return volume


def gee_disparity(left: np.ndarray, right: np.ndarray, config: GEEConfig = GEEConfig()) -> GEEResult:
    """Disparity map of the left image by global error energy minimisation with reliability filtering."""
    volume = error_energy_volume(left, right, config)
    best = np.argmin(volume, axis=0)
    energy = np.take_along_axis(volume, best[None], axis=0)[0]
    disparity = (best + config.min_disparity).astype(np.float32)
    finite = np.isfinite(energy)
    ve = float(config.alpha * energy[finite].mean()) if finite.any() else 0.0
    reliable = finite & (energy <= ve)
    disparity[~reliable] = np.nan
    reliability = float(1.0 / max(energy[reliable].mean(), 1e-12)) if reliable.any() else None
    return GEEResult(disparity, energy, ve, reliability)
