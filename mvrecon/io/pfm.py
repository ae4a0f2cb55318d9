"""Portable float maps (PFM), the Middlebury format for disparities: grey (Pf) or colour (PF), bottom row first."""

from pathlib import Path

import numpy as np


def write_pfm(path: Path | str, image: np.ndarray) -> None:
    """Write a float32 (H,W) or (H,W,3) array; `inf` marks unknown values, as Middlebury does."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"PFM holds (H,W) or (H,W,3) images, got shape {image.shape}")
    header = "PF" if image.ndim == 3 else "Pf"
    with open(path, "wb") as f:
        f.write(f"{header}\n{image.shape[1]} {image.shape[0]}\n-1\n".encode("ascii"))  # negative scale: little endian
        f.write(np.ascontiguousarray(np.flipud(image)).astype("<f4").tobytes())


def read_pfm(path: Path | str) -> np.ndarray:
    """Read a PFM file into a float32 array, top row first. ValueError names the file when it is not PFM."""
    path = Path(path)
    with open(path, "rb") as f:
        header = f.readline().strip()
        if header not in (b"PF", b"Pf"):
            raise ValueError(f"{path}: not a PFM file (header {header[:8]!r})")
        dims = f.readline().split()
        while not dims:  # tolerate blank lines
            dims = f.readline().split()
        width, height = int(dims[0]), int(dims[1])
        scale = float(f.readline().strip())
        channels = 3 if header == b"PF" else 1
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    expected = width * height * channels
    if data.size < expected:
        raise ValueError(f"{path}: truncated PFM ({data.size} of {expected} values)")
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.flipud(data[:expected].reshape(shape)).astype(np.float32)
