"""Textures for the ground-truth scenes: scikit-image's bundled photographs times seeded procedural noise.

A photograph alone is too smooth at the scale a surface is seen (SIFT finds few blobs in a magnified 512 px
photo), and noise alone is self-similar; the product of the two gives both large landmarks and fine detail, so
feature detectors find thousands of keypoints per frame and matching still has distinctive context.
Everything is generated from names and seeds, so textures are identical on every machine with no download.
"""

from dataclasses import dataclass

import cv2
import numpy as np

from ..interrupts import ctrl_c_deferred

# Photographs that scikit-image ships inside the wheel (no network fetch needed).
PHOTOS = (
    "astronaut",
    "coffee",
    "chelsea",
    "brick",
    "gravel",
    "grass",
    "rocket",
    "camera",
    "moon",
    "immunohistochemistry",
    "coins",
    "page",
    "text",
    "clock",
    "cell",
)


@dataclass(frozen=True)
class TextureSpec:
    """How to make one texture.

    photo: a name from PHOTOS, or "noise" for pure procedural noise.
    seed: seeds the noise (different surfaces should use different seeds so they do not repeat).
    size: side of the square texture in texels; near the on-screen size, so texels are not magnified much.
    detail: weight of the multiplicative noise in [0, 1]: 0 keeps the photo, 1 is full-contrast modulation.
    tint: per-channel gain, to tell similar surfaces apart.
    roughness: when given, the noise's octaves go down to a 2-texel period and each octave keeps this share
      of the one before, and pure noise is mostly grey at a higher contrast (SIFT sees grey levels only):
      with 0.8, a green-tinted 512 px noise texture gives ~2000 SIFT keypoints where the default gives ~100.
      For large procedural surfaces (terrain, walls) without photographs.
    """

    photo: str = "noise"
    seed: int = 0
    size: int = 512
    detail: float = 0.6
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    roughness: float | None = None

    @classmethod
    def parse(cls, value: "str | dict | TextureSpec", default_seed: int = 0) -> "TextureSpec":
        """A spec from a catalog entry: a photo name string or a table with the fields above."""
        if isinstance(value, TextureSpec):
            return value
        if isinstance(value, str):
            return cls(photo=value, seed=default_seed)
        if isinstance(value, dict):
            unknown = set(value) - {"photo", "seed", "size", "detail", "tint", "roughness"}
            if unknown:
                raise ValueError(f"unknown texture fields {sorted(unknown)}")
            fields = dict(value)
            fields.setdefault("seed", default_seed)
            if "tint" in fields:
                fields["tint"] = tuple(float(x) for x in fields["tint"])
            return cls(**fields)
        raise ValueError(f"a texture is a photo name or a table, got {value!r}")


def load_photo(name: str) -> np.ndarray:
    """A bundled scikit-image photograph as float32 RGB in [0, 1]."""
    if name not in PHOTOS:
        raise ValueError(f"unknown photo {name!r}; expected one of {', '.join(PHOTOS)} or 'noise'")
    with ctrl_c_deferred():  # the first photo imports skimage.io and scipy
        import skimage.data  # noqa: PLC0415 - heavy (scipy), photo textures only, Ctrl-C held back

        image = np.asarray(getattr(skimage.data, name)())
    if image.dtype == bool:
        image = image.astype(np.uint8) * 255
    image = image.astype(np.float32) / 255.0
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    return np.ascontiguousarray(image[..., :3])


def fractal_noise(
    size: int, seed: int, channels: int = 3, octaves: int = 6, base_cells: int = 4, persistence: float = 0.6
) -> np.ndarray:
    """Seeded multi-octave value noise in [0, 1], (size, size, channels); each octave doubles the frequency.

    The finest octave has a period of a few texels, which gives SIFT corners and blobs at every scale.
    """
    rng = np.random.default_rng(seed)
    total = np.zeros((size, size, channels), np.float32)
    weight, norm = 1.0, 0.0
    cells = base_cells
    for _ in range(octaves):
        grid = rng.random((cells, cells, channels), dtype=np.float32)
        total += weight * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC).reshape(
            size, size, channels
        )
        norm += weight
        weight *= persistence
        cells = min(cells * 2, size // 2)
    total /= norm
    mean, std = float(total.mean()), float(total.std())
    return np.clip((total - mean) / max(4.4 * std, 1e-6) + 0.5, 0.0, 1.0)  # about +-2.2 sigma onto [0, 1]


def make_texture(spec: TextureSpec) -> np.ndarray:
    """The texture of a spec, float32 RGB (size, size, 3) in [0, 1]."""
    rough = {}
    if spec.roughness is not None:
        rough = {"octaves": max(int(np.log2(spec.size / 8)) + 1, 1), "persistence": float(spec.roughness)}
    if spec.photo == "noise" and rough:
        noise = fractal_noise(spec.size, spec.seed, channels=4, **rough)  # grey grain, then a colour cast
        texture = np.clip(0.5 + 1.5 * (0.75 * noise[..., :1] + 0.25 * noise[..., 1:] - 0.5), 0.0, 1.0)
    elif spec.photo == "noise":
        texture = fractal_noise(spec.size, spec.seed, channels=3)
    else:
        photo = cv2.resize(load_photo(spec.photo), (spec.size, spec.size), interpolation=cv2.INTER_CUBIC)
        grey_noise = fractal_noise(spec.size, spec.seed, channels=1, **rough)
        texture = photo * ((1.0 - spec.detail) + spec.detail * 1.6 * grey_noise)
    texture = texture * np.asarray(spec.tint, np.float32)
    return np.ascontiguousarray(np.clip(texture, 0.0, 1.0).astype(np.float32))


class TextureAtlas:
    """All textures of a mesh in one flat array, so a frame's texture lookups are one vectorised gather.

    Each texture is stored with a copy of its first row and column appended, so bilinear filtering that wraps
    around the edge needs no modulo on the integer indices.
    """

    def __init__(self, textures: list[np.ndarray]):
        flat, offsets, widths, heights = [], [], [], []
        offset = 0
        for tex in textures:
            h, w = tex.shape[:2]
            padded = np.concatenate([tex, tex[:1]], axis=0)
            padded = np.concatenate([padded, padded[:, :1]], axis=1)
            flat.append(padded.reshape(-1, 3).astype(np.float32))
            offsets.append(offset)
            widths.append(w)
            heights.append(h)
            offset += (h + 1) * (w + 1)
        self.texels = np.concatenate(flat) if flat else np.zeros((0, 3), np.float32)
        if offset >= 2**31:
            raise ValueError(f"textures too large for one atlas ({offset} texels)")
        self.offsets = np.asarray(offsets, np.int32)
        self.widths = np.asarray(widths, np.float32)
        self.heights = np.asarray(heights, np.float32)

    def sample(self, texture_ids: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Bilinear colours (N,3) at uv (N,2) of texture texture_ids (N,), repeating outside [0, 1).

        u runs along columns, v along rows; texel (i, j) has its centre at ((j + 0.5)/W, (i + 0.5)/H).
        """
        w, h = self.widths[texture_ids], self.heights[texture_ids]
        return self.lookup(uv[:, 0] * w, uv[:, 1] * h, w, h, self.offsets[texture_ids])

    def lookup(
        self, x: np.ndarray, y: np.ndarray, w: np.ndarray, h: np.ndarray, offsets: np.ndarray
    ) -> np.ndarray:
        """Bilinear colours at texel coordinates (x, y) = (u * W, v * H) of the textures at `offsets`. A coordinate
        a hair below a texel centre wraps to W (or H) itself in float32, past the padded last texel: it is taken
        as 0, where it repeats to."""
        x = np.mod(x - 0.5, w)
        y = np.mod(y - 0.5, h)
        x = np.where(x >= w, x - w, x)
        y = np.where(y >= h, y - h, y)
        x0, y0 = np.floor(x), np.floor(y)
        fx = (x - x0)[:, None]
        fy = (y - y0)[:, None]
        stride = w.astype(np.int32) + 1
        i00 = offsets + y0.astype(np.int32) * stride + x0.astype(np.int32)
        i10 = i00 + stride
        t = self.texels
        top = np.take(t, i00, axis=0)
        top += (np.take(t, i00 + 1, axis=0) - top) * fx
        bottom = np.take(t, i10, axis=0)
        bottom += (np.take(t, i10 + 1, axis=0) - bottom) * fx
        top += (bottom - top) * fy
        return top
