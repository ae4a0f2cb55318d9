"""What several test files build the same way: the repository's paths and small synthetic image sets.

Helpers that take arguments live here and are imported (`from tests.helpers import textured_views`); fixtures
shared by several folders live in conftest.py.
"""

from pathlib import Path

import cv2
import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]  # the repository: pyproject.toml, mvrecon/, tests/
DATA = ROOT.parent / "shared" / "data"  # the public image sets, read in place; tests skip when a set is absent


def textured_views(folder: Path, count: int = 6, size: tuple[int, int] = (240, 320)) -> Path:
    """Overlapping crops of one blurred-noise texture: every pair shares content, SIFT finds it quickly."""
    rng = np.random.default_rng(0)
    h, w = size
    noise = (rng.random((h + 20 * count, w + 30 * count, 3)) * 255).astype(np.uint8)
    texture = cv2.GaussianBlur(noise, (0, 0), 1.5)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        Image.fromarray(texture[12 * i:12 * i + h, 20 * i:20 * i + w]).save(folder / f"view{i:02d}.png")
    return folder


def pattern(h: int = 60, w: int = 80) -> np.ndarray:
    """An asymmetric RGB gradient: any flip or rotation changes it."""
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 3 % 256, y * 4 % 256, (x + 2 * y) % 256], axis=-1).astype(np.uint8)
