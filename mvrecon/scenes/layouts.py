"""Sites: whole layouts of many objects laid out under or along a scene's cameras, so that they grow with it.

A catalog entry names a site as one `[[objects]]` table (`survey_site`, `street_site`); the site covers the
camera centres with a margin, so a scene made with more views (`mvrecon scene make NAME --count N`) gets a
larger site of the same kind. Every surface has its own seeded procedural texture (or a photograph used once),
so no pattern repeats anywhere in the scene: a repeat would let a pipeline register a view in the wrong place,
and that would be the renderer's fault, not the pipeline's.
"""

from collections.abc import Callable

import numpy as np

from . import meshes
from .textures import PHOTOS, TextureSpec

# land-cover and material tints, multiplied with coloured fractal noise
GROUND_TINTS = ((0.55, 0.8, 0.4), (0.75, 0.65, 0.45), (0.85, 0.8, 0.55), (0.5, 0.7, 0.45), (0.7, 0.7, 0.65))
WALL_TINTS = ((1.0, 0.9, 0.8), (0.9, 0.9, 0.95), (1.0, 0.8, 0.7), (0.85, 0.85, 0.8), (0.95, 1.0, 0.9))
ROUGHNESS = 0.8  # `TextureSpec.roughness`: grain down to 2 texels, so every surface has detail for SIFT
ROOF_TINTS = ((0.9, 0.5, 0.4), (0.6, 0.6, 0.65), (0.5, 0.45, 0.4), (0.8, 0.7, 0.6))


class _Textures:
    """Texture specs with seeds that no other surface of the site shares."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.next_seed = int(rng.integers(1 << 40))

    def noise(self, size: int, tints) -> TextureSpec:
        self.next_seed += 1
        tint = np.asarray(tints[int(self.rng.integers(len(tints)))]) * self.rng.uniform(0.85, 1.1)
        tint = tuple(float(c) for c in np.clip(tint, 0.0, 1.0))
        return TextureSpec(photo="noise", seed=self.next_seed, size=size, tint=tint, roughness=ROUGHNESS)

    def photo(self, name: str, size: int) -> TextureSpec:
        self.next_seed += 1
        return TextureSpec(photo=name, seed=self.next_seed, size=size, detail=0.6, roughness=ROUGHNESS)


def terrain(seed: int, amplitude: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A smooth seeded height function h(x, y) in metres, within about +-amplitude: 24 plane waves of random
    directions and wavelengths 40-400 m whose periods share no common multiple, so the hills never repeat."""
    rng = np.random.default_rng(seed)
    n = 24
    angle = rng.uniform(0, np.pi, n)
    wavelength = np.exp(rng.uniform(np.log(40.0), np.log(400.0), n))
    k = 2 * np.pi / wavelength
    kx, ky = k * np.cos(angle), k * np.sin(angle)
    phase = rng.uniform(0, 2 * np.pi, n)
    weight = wavelength / wavelength.sum() * amplitude * 2.0  # long waves carry the relief

    def height(x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        return np.sum(weight * np.sin(np.multiply.outer(x, kx) + np.multiply.outer(y, ky) + phase), axis=-1)

    return height


def survey_site(
    centres: np.ndarray,
    seed: int,
    margin: float = 70.0,
    tile: float = 50.0,
    texture_size: int = 512,
    relief: float = 5.0,
    building_spacing: float = 30.0,
    buildings: float = 0.4,
    trees_per_hectare: float = 12.0,
) -> meshes.TexturedMesh:
    """Rolling terrain under a drone survey, with buildings and trees, covering the cameras' x-y extent plus
    `margin`: terrain tiles of `tile` metres (each its own texture of `texture_size` texels, one texel about
    tile / texture_size metres), a box building in a share `buildings` of the cells of a `building_spacing`
    grid (walls and roof each their own texture, half as many texels) and trees (a crown on a trunk) scattered
    between them."""
    rng = np.random.default_rng(seed)
    textures = _Textures(rng)
    height = terrain(int(rng.integers(1 << 31)), relief)
    lo = centres[:, :2].min(0) - margin
    hi = centres[:, :2].max(0) + margin
    counts = np.maximum(np.ceil((hi - lo) / tile).astype(int), 1)
    lo = (lo + hi) / 2 - counts * tile / 2
    parts = []
    cells = max(int(tile / 3.0), 2)  # terrain vertices about 3 m apart
    s = np.linspace(0.0, tile, cells + 1)
    for i in range(counts[0]):
        for j in range(counts[1]):
            x0, y0 = lo + [i * tile, j * tile]
            X, Y = np.meshgrid(x0 + s, y0 + s)
            parts.append(meshes.grid((x0, y0, 0.0), (tile, 0, 0), (0, tile, 0), height(X, Y),
                                     textures.noise(texture_size, GROUND_TINTS)))
    footprints = []
    half = max(texture_size // 2, 16)
    n_cells = np.maximum(((hi - lo) / building_spacing).astype(int), 1)
    for i in range(n_cells[0]):
        for j in range(n_cells[1]):
            if rng.random() >= buildings:
                continue
            size = rng.uniform(8.0, 0.7 * building_spacing, 2)
            tall = rng.uniform(4.0, 16.0)
            cx, cy = lo + (np.array([i, j]) + rng.uniform(0.35, 0.65, 2)) * building_spacing
            corners = np.array([[cx, cy]]) + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * size / 2 * 1.42
            ground = height(corners[:, 0], corners[:, 1])
            base, top = ground.min() - 0.5, ground.max() + tall
            faces = [textures.noise(half, WALL_TINTS) for _ in range(4)] + [textures.noise(half, ROOF_TINTS),
                                                                              textures.noise(16, WALL_TINTS)]
            parts.append(meshes.box((cx, cy, (base + top) / 2), (size[0], size[1], top - base), faces,
                                    yaw_deg=float(rng.uniform(0, 90))))
            footprints.append((cx, cy, 0.75 * np.hypot(*size)))
    area_ha = np.prod(hi - lo) / 1e4
    placed = np.array(footprints).reshape(-1, 3)
    for _ in range(int(round(trees_per_hectare * area_ha))):
        x, y = rng.uniform(lo, hi)
        if len(placed) and np.any(np.hypot(placed[:, 0] - x, placed[:, 1] - y) < placed[:, 2] + 3.0):
            continue
        r = rng.uniform(1.5, 3.5)
        trunk = rng.uniform(1.5, 3.0)
        z = float(height(x, y))
        bark = textures.noise(max(texture_size // 8, 16), WALL_TINTS)
        leaves = textures.noise(max(texture_size // 4, 16), GROUND_TINTS[:2])
        parts.append(meshes.cylinder((x, y, z - 0.3), 0.3, trunk + r + 0.3, bark, 8))
        parts.append(meshes.uv_sphere((x, y, z + trunk + 0.8 * r), r, leaves, 12))
    return meshes.merge(parts)


def street_site(
    centres: np.ndarray,
    seed: int,
    width: float = 10.0,
    segment: tuple[float, float] = (8.0, 16.0),
    heights: tuple[float, float] = (6.0, 12.0),
    texture_size: int = 1024,
    ground_tile: float = 10.0,
    ground_texture_size: int = 512,
    relief: float = 0.25,
) -> meshes.TexturedMesh:
    """A street of `width` around a block, under a camera path that goes once round it (`cameras.loop`): the
    block's facades on the inner side, a closed row of facades on the outer side, each side cut into facades
    `segment` metres long and `heights` tall with relief (`relief` metres), and the road in `ground_tile`
    squares. Each facade and road square has its own texture: each bundled photograph once (times seeded
    noise), then seeded noise in varied tints."""
    rng = np.random.default_rng(seed)
    textures = _Textures(rng)
    lo, hi = centres[:, :2].min(0), centres[:, :2].max(0)
    inner_lo, inner_hi = lo + width / 2, hi - width / 2
    if np.any(inner_hi - inner_lo <= 0.5):
        raise ValueError(f"street_site: a street {width} m wide leaves no block inside the cameras' loop "
                         f"({hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} m)")
    outer_lo, outer_hi = lo - width / 2, hi + width / 2
    photos = list(rng.permutation(PHOTOS))
    parts = []
    for (a, b), facing_out in (((inner_lo, inner_hi), True), ((outer_lo, outer_hi), False)):
        ring = np.array([[a[0], a[1]], [b[0], a[1]], [b[0], b[1]], [a[0], b[1]]])
        if not facing_out:  # clockwise: the facades' fronts (u x up) face into the street
            ring = ring[::-1]
        for k in range(4):
            p, q = ring[k], ring[(k + 1) % 4]
            length = float(np.linalg.norm(q - p))
            direction = (q - p) / length
            cuts = [0.0]
            while length - cuts[-1] > segment[1]:
                cuts.append(cuts[-1] + rng.uniform(*segment))
            cuts.append(length)
            for s0, s1 in zip(cuts[:-1], cuts[1:]):
                tall = rng.uniform(*heights)
                u = np.r_[(s1 - s0) * direction, 0.0]
                shape = (max(int(tall * 6), 2), max(int((s1 - s0) * 6), 2))
                bumps = meshes.relief("bumps", shape, (s1 - s0, tall), relief, int(rng.integers(1 << 31)))
                texture = (textures.photo(photos.pop(), texture_size) if photos and rng.random() < 0.5
                           else textures.noise(texture_size, WALL_TINTS))
                parts.append(meshes.grid(np.r_[p + s0 * direction, 0.0], u, (0, 0, tall), bumps, texture))
    counts = np.maximum(np.ceil((outer_hi - outer_lo) / ground_tile).astype(int), 1)
    step = (outer_hi - outer_lo) / counts
    for i in range(counts[0]):
        for j in range(counts[1]):
            x0, y0 = outer_lo + step * [i, j]
            if np.all(inner_lo <= (x0, y0)) and np.all((x0, y0) + step <= inner_hi):
                continue  # under the block: never seen
            road = textures.noise(ground_texture_size, ((0.6, 0.6, 0.62), (0.7, 0.65, 0.6)))
            parts.append(meshes.quad((x0, y0, 0.0), (step[0], 0, 0), (0, step[1], 0), road))
    return meshes.merge(parts)


SITES = {"survey_site": survey_site, "street_site": street_site}
