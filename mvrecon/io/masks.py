"""Image masks, COLMAP's way (`ImageReader.mask_path`): no features where a mask is black.

The mask of IMAGES/sub/a.jpg is MASKS/sub/a.jpg.png, grey or colour, and a keypoint is dropped where the mask's
pixel is 0 (COLMAP drops the features it detects there). What to leave out is the user's choice: people or cars
that move, the sky, the photographer's shadow, a lens hood, or an overlay that is not on half the images
(matching/overlay.py finds those that are). A mask is read in its image's stored frame, as COLMAP reads it, and
turned as the image is by its EXIF orientation (mvrecon works upright); only a mask of an image turned by 90
degrees that already has the upright size (width and height swapped) is taken as drawn upright.
"""

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import InputError
from .images import TRANSPOSED, _orientation, apply_orientation, read_image


def mask_path(masks_dir: Path | str, name: str) -> Path:
    """COLMAP's name for the mask of image `name` (a path relative to the image folder)."""
    return Path(masks_dir) / f"{name}.png"


def find_masks(masks_dir: Path | str, names: Iterable[str]) -> tuple[dict, list]:
    """({name: mask file} of the images that have one, [names without one]); an InputError when `masks_dir` is
    not a folder."""
    folder = Path(masks_dir)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder (--masks)")
    found = {name: mask_path(folder, name) for name in names}
    missing = [name for name, path in found.items() if not path.is_file()]
    return {name: path for name, path in found.items() if name not in missing}, missing


def check_masks(masks: dict, folder: Path, metas: dict) -> None:
    """`check_mask` for every image of `masks` that has its `metas` (io.images.ImageMeta)."""
    for name, path in masks.items():
        if name in metas:
            check_mask(path, folder / name, (metas[name].width, metas[name].height), metas[name].orientation)


def check_mask(path: Path, image: Path, upright_size: tuple[int, int], orientation: int) -> None:
    """Refuse, naming the mask, one that cannot be read or has neither the image's upright nor its stored size."""
    try:
        with Image.open(path) as im:
            size = im.size
    except Exception as exc:  # Pillow raises many types for a broken file; its message is what the user needs
        raise InputError(f"{path}: cannot read the mask ({type(exc).__name__}: {exc})") from None
    stored = upright_size[::-1] if orientation in TRANSPOSED else upright_size
    if size not in (tuple(upright_size), tuple(stored)):
        raise InputError(f"{path}: the mask is {size[0]}x{size[1]} but {image} is {upright_size[0]}x"
                         f"{upright_size[1]}; a mask must have its image's size")


def keypoints_outside_mask(path: Path, image_path: Path, keypoints: np.ndarray,
                           upright_shape: tuple[int, int]) -> np.ndarray:
    """Bool per keypoint (x, y in COLMAP pixels, the upright frame): True where the mask keeps it."""
    mask = read_image(path, upright=False)
    if mask.ndim == 3:
        mask = mask.max(axis=2)
    orientation = _orientation(image_path)
    drawn_upright = orientation in TRANSPOSED and mask.shape[0] != mask.shape[1] \
        and mask.shape[:2] == tuple(upright_shape[:2])
    if not drawn_upright:
        mask = apply_orientation(mask, orientation)
    h, w = mask.shape
    col = np.clip(np.floor(keypoints[:, 0]).astype(np.int64), 0, w - 1)  # COLMAP pixel x lies in pixel floor(x)
    row = np.clip(np.floor(keypoints[:, 1]).astype(np.int64), 0, h - 1)
    return mask[row, col] != 0
