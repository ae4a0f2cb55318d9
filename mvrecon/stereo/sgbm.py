"""OpenCV's semi-global block matching (Hirschmueller 2008, OpenCV's variant) as the reference method.

Settings are tuned on scikit-image's Motorcycle pair (see docs/stereo.md): a 3 px block in OpenCV's 3-way mode, the
usual P1 = 8 c b^2 and P2 = 32 c b^2 smoothness penalties, a left-right consistency check of 1 px, uniqueness 10 %
and speckle removal (blocks of 5 and 7 px, and the full 8-path mode, scored 0.3-1.9 points worse).
Pixels OpenCV marks invalid are returned as NaN (holes), never silently filled.
"""

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SGBMConfig:
    """block_size: matching window (odd); p1/p2 multipliers of channels * block_size^2; mode: 'hh' (full 8-path),
    '3way' or 'sgbm' (5 paths); the rest are OpenCV's post-filters (0 disables)."""

    min_disparity: int = 0
    num_disparities: int = 64
    block_size: int = 3
    p1: int = 8
    p2: int = 32
    disp12_max_diff: int = 1
    uniqueness_ratio: int = 10
    speckle_window_size: int = 100
    speckle_range: int = 2
    pre_filter_cap: int = 63
    mode: str = "3way"


def create_matcher(config: SGBMConfig, channels: int) -> cv2.StereoSGBM:
    modes = {"hh": cv2.STEREO_SGBM_MODE_HH, "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY, "sgbm": cv2.STEREO_SGBM_MODE_SGBM}
    area = channels * config.block_size ** 2
    return cv2.StereoSGBM_create(
        minDisparity=config.min_disparity, numDisparities=int(np.ceil(config.num_disparities / 16) * 16),
        blockSize=config.block_size, P1=config.p1 * area, P2=config.p2 * area,
        disp12MaxDiff=config.disp12_max_diff, uniquenessRatio=config.uniqueness_ratio,
        speckleWindowSize=config.speckle_window_size, speckleRange=config.speckle_range,
        preFilterCap=config.pre_filter_cap, mode=modes[config.mode])


def sgbm_disparity(left: np.ndarray, right: np.ndarray, config: SGBMConfig = SGBMConfig()) -> np.ndarray:
    """float32 disparity of the left image, NaN where OpenCV found no valid match."""
    left, right = np.ascontiguousarray(left), np.ascontiguousarray(right)
    channels = 1 if left.ndim == 2 else left.shape[2]
    raw = create_matcher(config, channels).compute(left, right)
    disparity = raw.astype(np.float32) / 16.0
    disparity[raw < config.min_disparity * 16] = np.nan
    return disparity
