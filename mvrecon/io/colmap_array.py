"""COLMAP's dense arrays (`stereo/depth_maps/*.bin`, `stereo/normal_maps/*.bin`): the text header `W&H&C&`, then
W*H*C little-endian float32 values, channel by channel, each channel row by row (x fastest). This is the layout
of COLMAP's `Mat<float>::Write` and of its scripts' `read_array` (`reshape((W, H, C), order="F")` then a
transpose to (H, W, C)), so COLMAP's `stereo_fusion` and pycolmap's `DepthMap.read` read what is written here.
"""

from pathlib import Path

import numpy as np

from .files import replace_whole


def write_colmap_array(path: Path | str, array: np.ndarray) -> None:
    """Write an (H, W) or (H, W, C) array (a depth map, a normal map) as a COLMAP `.bin` array, whole or not at
    all."""
    array = np.asarray(array, dtype=np.float32)
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3:
        raise ValueError(f"a COLMAP array is (H, W) or (H, W, C), got shape {array.shape}")
    height, width, channels = array.shape
    header = f"{width}&{height}&{channels}&".encode("ascii")
    body = np.ascontiguousarray(array.transpose(2, 0, 1)).astype("<f4").tobytes()  # (C, H, W), x fastest

    def write(tmp: Path) -> None:
        tmp.write_bytes(header + body)

    replace_whole(path, write)


def read_colmap_array(path: Path | str) -> np.ndarray:
    """Read a COLMAP `.bin` array into float32 (H, W) (one channel) or (H, W, C). ValueError names the file when
    its header or size is not that of a COLMAP array."""
    path = Path(path)
    data = path.read_bytes()
    fields, rest = [], 0
    for _ in range(3):  # three '&'-ended integers
        end = data.find(b"&", rest, rest + 32)
        if end < 0:
            raise ValueError(f"{path}: not a COLMAP array (no 'W&H&C&' header)")
        try:
            fields.append(int(data[rest:end]))
        except ValueError:
            raise ValueError(f"{path}: not a COLMAP array (header {data[:end + 1][:40]!r})") from None
        rest = end + 1
    width, height, channels = fields
    expected = width * height * channels
    values = np.frombuffer(data, dtype="<f4", offset=rest)  # ValueError when the rest is not whole floats
    if width <= 0 or height <= 0 or channels <= 0 or values.size != expected:
        raise ValueError(f"{path}: COLMAP array of {width}x{height}x{channels} holds {values.size} values")
    array = values.reshape(channels, height, width).transpose(1, 2, 0).astype(np.float32)
    return array[:, :, 0] if channels == 1 else array
