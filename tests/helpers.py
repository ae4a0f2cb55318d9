"""What several test files build the same way: the repository's paths and small synthetic image sets.

Helpers that take arguments live here and are imported (`from tests.helpers import textured_views`); fixtures
shared by several folders live in conftest.py.
"""

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image

from mvrecon.scenes import make_scene
from mvrecon.scenes.catalog import load_entry

ROOT = Path(__file__).resolve().parents[1]  # the repository: pyproject.toml, mvrecon/, tests/
DATA = ROOT.parent / "shared" / "data"  # the public image sets, read in place; tests skip without them


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


def synthetic_scene(root: Path) -> tuple[Path, Path]:
    """8 images (640x480) of a pycolmap synthetic scene and its ground-truth model; made once per folder."""
    images, gt = root / "images", root / "gt" / "sparse"
    if not (gt / "images.bin").exists():
        images.mkdir(parents=True, exist_ok=True)
        gt.mkdir(parents=True, exist_ok=True)
        pycolmap.set_random_seed(0)
        rec = pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(
            num_rigs=1, num_frames_per_rig=8, num_points3D=300, camera_width=640, camera_height=480,
            camera_params=[1200.0, 320.0, 240.0, 0.0]))
        image_options = pycolmap.SyntheticImageOptions()
        image_options.feature_patch_radius = 8  # apart enough for SIFT to tell the blobs apart
        pycolmap.synthesize_images(image_options, rec, str(images))
        rec.write(str(gt))
    return images, gt


def orbit_descriptors(views: int = 16, points: int = 4000, seen: int = 900, noise: float = 8.0, seed: int = 1,
                      name: str = "v{:02d}.png") -> dict[str, np.ndarray]:
    """Views on a closed orbit around `points` scene points, each seeing an arc of `seen` consecutive ones, as
    RootSIFT-like uint8 descriptors with noise, named `name.format(i)`: with the defaults view i shares 650
    points with i +- 1, 400 with i +- 2, 150 with i +- 3 and none with the rest."""
    rng = np.random.default_rng(seed)
    scene = rng.gamma(0.5, 1.0, (points, 128))  # sparse and non-negative, as SIFT histograms
    scene = np.sqrt(scene / scene.sum(axis=1, keepdims=True))
    out = {}
    for i in range(views):
        rows = (np.arange(seen) + i * points // views) % points
        noisy = scene[rows] * 512 + rng.normal(0.0, noise, (seen, 128))
        out[name.format(i)] = np.clip(np.round(noisy), 0, 255).astype(np.uint8)
    return out


def bilinear(image, u, v):
    """Values of image at COLMAP pixel positions (u, v) and whether all 4 neighbours agree within 2 %."""
    x, y = u - 0.5, v - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    h, w = image.shape
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
    fx, fy = x - x0, y - y0
    q = np.stack([image[y0, x0], image[y0, x0 + 1], image[y0 + 1, x0], image[y0 + 1, x0 + 1]])
    smooth = inside & np.all(np.isfinite(q), axis=0)
    with np.errstate(invalid="ignore"):
        smooth &= (q.max(0) - q.min(0)) < 0.02 * q.min(0)
    value = (q[0] * (1 - fx) + q[1] * fx) * (1 - fy) + (q[2] * (1 - fx) + q[3] * fx) * fy
    return value, smooth


def edited_scene(name: str, folder: Path, edits: dict[str, str]) -> Path:
    """The catalog scene `name` with each `old` string of its TOML replaced by `new` (each must be there, so an
    edit of the catalog that drops one fails here, not as a silently different scene), rendered into `folder`."""
    text = load_entry(name)[2].read_text()
    for old, new in edits.items():
        assert old in text, (name, old)
        text = text.replace(old, new)
    toml = folder / f"{folder.name}.toml"
    toml.write_text(text)
    return make_scene(str(toml), folder / "scene")


@contextmanager
def shared_folder(tmp_path_factory: pytest.TempPathFactory, name: str) -> Iterator[Path]:
    """The folder `name` of this test run, held by one process at a time: a worker's own temporary folder lies
    in the run's, which every worker of the run shares. What is made there must be found complete when made
    again (catalog scenes and the COLMAP runners' outputs are)."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    folder = root / name
    folder.mkdir(exist_ok=True)
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield folder
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
