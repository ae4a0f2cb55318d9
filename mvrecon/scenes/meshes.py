"""Triangle meshes with per-corner texture coordinates: the geometry of every ground-truth scene.

A mesh carries, per triangle, three UV pairs and the index of its texture, so one ray-casting scene can hold
surfaces with different photographs. Builders cover what the catalog needs (quads, boxes, a room seen from
inside, height fields for facades, terrain and SEM specimens, spheres, cylinders, and copies of any of them
in a grid) plus PLY/OBJ files from disk.
"""

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..interrupts import import_open3d
from .textures import TextureSpec


@dataclass
class TexturedMesh:
    """vertices (V,3); triangles (T,3) vertex ids; uvs (T,3,2) per corner; texture_ids (T,) into textures."""

    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    texture_ids: np.ndarray
    textures: list[TextureSpec] = field(default_factory=list)

    @property
    def num_triangles(self) -> int:
        return len(self.triangles)

    def triangle_areas(self) -> np.ndarray:
        a, b, c = (self.vertices[self.triangles[:, k]] for k in range(3))
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def merge(meshes: list[TexturedMesh]) -> TexturedMesh:
    """One mesh holding all inputs, with vertex and texture indices renumbered."""
    vertices, triangles, uvs, tex_ids, textures = [], [], [], [], []
    v_off = 0
    for m in meshes:
        vertices.append(m.vertices)
        triangles.append(m.triangles + v_off)
        uvs.append(m.uvs)
        tex_ids.append(m.texture_ids + len(textures))
        textures.extend(m.textures)
        v_off += len(m.vertices)
    return TexturedMesh(
        np.concatenate(vertices).astype(float),
        np.concatenate(triangles).astype(np.int64),
        np.concatenate(uvs).astype(float),
        np.concatenate(tex_ids).astype(np.int64),
        textures,
    )


def grid(
    origin: Sequence[float] | np.ndarray,
    u_edge: Sequence[float] | np.ndarray,
    v_edge: Sequence[float] | np.ndarray,
    heights: np.ndarray,
    texture: TextureSpec,
    uv_repeat: tuple[float, float] = (1.0, 1.0),
) -> TexturedMesh:
    """A rectangle origin + s*u_edge + t*v_edge displaced along u_edge x v_edge by heights (rows=t, cols=s).

    heights has shape (nv, nu) >= (2, 2); a flat quad is heights = zeros((2, 2)). Texture u runs along u_edge,
    texture rows run against v_edge (photos stand upright when v_edge points up); both scaled by uv_repeat.
    """
    origin, u_edge, v_edge = (np.asarray(a, dtype=float) for a in (origin, u_edge, v_edge))
    heights = np.asarray(heights, dtype=float)
    nv, nu = heights.shape
    normal = np.cross(u_edge, v_edge)
    normal /= np.linalg.norm(normal)
    s = np.linspace(0.0, 1.0, nu)
    t = np.linspace(0.0, 1.0, nv)
    S, T = np.meshgrid(s, t)
    vertices = (origin + S[..., None] * u_edge + T[..., None] * v_edge + heights[..., None] * normal).reshape(
        -1, 3
    )
    idx = np.arange(nu * nv).reshape(nv, nu)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])  # normal along u x v
    vertex_uv = np.stack(
        [S.ravel() * uv_repeat[0], (1.0 - T.ravel()) * uv_repeat[1]], axis=1
    )  # image top at +v
    return TexturedMesh(
        vertices, triangles, vertex_uv[triangles], np.zeros(len(triangles), np.int64), [texture]
    )


def quad(
    origin: Sequence[float] | np.ndarray,
    u_edge: Sequence[float] | np.ndarray,
    v_edge: Sequence[float] | np.ndarray,
    texture: TextureSpec,
    uv_repeat: tuple[float, float] = (1.0, 1.0),
) -> TexturedMesh:
    """A flat textured rectangle; its front side is u_edge x v_edge."""
    return grid(origin, u_edge, v_edge, np.zeros((2, 2)), texture, uv_repeat)


def _rotation_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def box(
    center: Sequence[float] | np.ndarray,
    size: Sequence[float] | np.ndarray,
    textures: list[TextureSpec],
    yaw_deg: float = 0.0,
    inward: bool = False,
    tile: float | None = None,
) -> TexturedMesh:
    """An axis-aligned box turned by yaw about z; face k uses textures[k % len]. inward: normals inside.

    tile: the texture repeats every `tile` scene units on each face (a moulded or tiled surface) instead of
    stretching once over it."""
    c = np.asarray(center, dtype=float)
    hx, hy, hz = np.asarray(size, dtype=float) / 2
    R = _rotation_z(yaw_deg)
    # (origin, u, v) per face with u x v pointing outward: +x, -x, +y, -y, +z, -z
    faces = [
        ([hx, -hy, -hz], [0, 2 * hy, 0], [0, 0, 2 * hz]),
        ([-hx, hy, -hz], [0, -2 * hy, 0], [0, 0, 2 * hz]),
        ([hx, hy, -hz], [-2 * hx, 0, 0], [0, 0, 2 * hz]),
        ([-hx, -hy, -hz], [2 * hx, 0, 0], [0, 0, 2 * hz]),
        ([-hx, -hy, hz], [2 * hx, 0, 0], [0, 2 * hy, 0]),
        ([-hx, hy, -hz], [2 * hx, 0, 0], [0, -2 * hy, 0]),
    ]
    meshes = []
    for k, (o, u, v) in enumerate(faces):
        o, u, v = np.asarray(o, float), np.asarray(u, float), np.asarray(v, float)
        if inward:
            o, u = o + u, -u
        repeat = (1.0, 1.0) if tile is None else (np.linalg.norm(u) / tile, np.linalg.norm(v) / tile)
        meshes.append(quad(c + R @ o, R @ u, R @ v, textures[k % len(textures)], repeat))
    return merge(meshes)


def uv_sphere(
    center: Sequence[float] | np.ndarray, radius: float, texture: TextureSpec, segments: int = 64
) -> TexturedMesh:
    """A sphere with latitude-longitude texture coordinates (u around z, v from top to bottom)."""
    rings = segments // 2
    lon = np.linspace(0.0, 2 * np.pi, segments + 1)
    lat = np.linspace(0.0, np.pi, rings + 1)
    LON, LAT = np.meshgrid(lon, lat)
    pts = np.stack([np.sin(LAT) * np.cos(LON), np.sin(LAT) * np.sin(LON), np.cos(LAT)], -1)
    vertices = (np.asarray(center, float) + radius * pts).reshape(-1, 3)
    idx = np.arange((rings + 1) * (segments + 1)).reshape(rings + 1, segments + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    triangles = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])  # outward normals
    area_ok = (
        np.linalg.norm(
            np.cross(
                vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                vertices[triangles[:, 2]] - vertices[triangles[:, 0]],
            ),
            axis=1,
        )
        > 1e-12
    )
    triangles = triangles[area_ok]  # drop the degenerate triangles at the poles
    vertex_uv = np.stack([LON.ravel() / (2 * np.pi), LAT.ravel() / np.pi], 1)
    return TexturedMesh(
        vertices, triangles, vertex_uv[triangles], np.zeros(len(triangles), np.int64), [texture]
    )


def cylinder(
    base_center: Sequence[float] | np.ndarray,
    radius: float,
    height: float,
    texture: TextureSpec,
    segments: int = 32,
) -> TexturedMesh:
    """An upright (z) cylinder standing on `base_center`, with its top cap (a stud, a post, a can).

    The side's texture wraps once around it, u around z and image rows downwards; the top cap shows the
    texture's centred disc (the cylinder seen from above, as a planar projection of its x-y extent).
    """
    c = np.asarray(base_center, float)
    angles = np.linspace(0.0, 2 * np.pi, segments + 1)
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], 1)
    bottom, top = c + radius * ring, c + radius * ring + [0.0, 0.0, height]
    vertices = np.concatenate([bottom, top, [c + [0.0, 0.0, height]]])
    n = segments + 1
    k = np.arange(segments)
    side = np.concatenate([np.stack([k, k + 1, n + k + 1], 1), np.stack([k, n + k + 1, n + k], 1)])
    cap = np.stack([n + k, n + k + 1, np.full(segments, 2 * n)], 1)  # counter-clockwise from above: up
    vertex_uv = np.concatenate([np.stack([angles / (2 * np.pi), np.ones(n)], 1),
                                np.stack([angles / (2 * np.pi), np.zeros(n)], 1), [[0.5, 0.5]]])
    cap_uv = 0.5 + 0.5 * np.stack([np.cos(angles), -np.sin(angles)], 1)
    cap_uvs = np.stack([cap_uv[k], cap_uv[k + 1], np.full((segments, 2), 0.5)], 1)
    uvs = np.concatenate([vertex_uv[side], cap_uvs])
    return TexturedMesh(vertices, np.concatenate([side, cap]), uvs,
                        np.zeros(len(side) + segments, np.int64), [texture])


def tile(mesh: TexturedMesh, offsets: np.ndarray) -> TexturedMesh:
    """Copies of `mesh` moved by each of `offsets` (N,3), sharing its textures: identical parts in a row or a
    grid (studs on a brick, windows on a facade), whose repetition is exact as a moulded or built one is."""
    offsets = np.asarray(offsets, float).reshape(-1, 3)
    nv = len(mesh.vertices)
    return TexturedMesh(
        np.concatenate([mesh.vertices + o for o in offsets]),
        np.concatenate([mesh.triangles + k * nv for k in range(len(offsets))]),
        np.tile(mesh.uvs, (len(offsets), 1, 1)),
        np.tile(mesh.texture_ids, len(offsets)),
        list(mesh.textures),
    )


def relief(
    kind: str,
    shape: tuple[int, int],
    extent: tuple[float, float],
    amplitude: float,
    seed: int,
    features: int = 40,
) -> np.ndarray:
    """A seeded height map (rows, cols) over a rectangle of `extent` (width, height) in scene units.

    kind "flat": zeros. "bumps": Gaussian bumps and pits plus ridges (an SEM specimen, a facade with relief),
    heights within about +-amplitude. "terrain": smooth fractal noise in [0, amplitude].
    """
    rows, cols = shape
    if kind == "flat":
        return np.zeros(shape)
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, extent[0], cols)
    y = np.linspace(0.0, extent[1], rows)
    X, Y = np.meshgrid(x, y)
    if kind == "bumps":
        h = np.zeros(shape)
        size = min(extent)
        for _ in range(features):
            cx, cy = rng.random() * extent[0], rng.random() * extent[1]
            sigma = size * rng.uniform(0.03, 0.1)
            h += (
                rng.choice([1.0, -0.7])
                * rng.uniform(0.4, 1.0)
                * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * sigma**2))
            )
        for _ in range(max(features // 10, 1)):
            theta = rng.uniform(0, np.pi)
            cx, cy = rng.random() * extent[0], rng.random() * extent[1]
            dist = (X - cx) * np.sin(theta) - (Y - cy) * np.cos(theta)
            h += 0.6 * np.exp(-(dist**2) / (2 * (size * 0.02) ** 2))
        return amplitude * h / max(np.abs(h).max(), 1e-12)
    if kind == "terrain":
        h = np.zeros(shape)
        weight = 1.0
        for octave in range(5):
            n = 3 * 2**octave
            h += weight * cv2.resize(rng.random((n, n)), (cols, rows), interpolation=cv2.INTER_CUBIC)
            weight *= 0.45
        h -= h.min()
        return amplitude * h / max(h.max(), 1e-12)
    raise ValueError(f"unknown relief {kind!r}; expected flat, bumps or terrain")


def load_mesh(
    path: Path | str,
    texture: TextureSpec,
    scale: float = 1.0,
    translate: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
) -> TexturedMesh:
    """A PLY/OBJ triangle mesh; its own UVs are kept, else UVs are a planar projection on its x-y extent."""
    o3d = import_open3d()

    m = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(m.vertices, dtype=float) * scale + np.asarray(translate, float)
    triangles = np.asarray(m.triangles, dtype=np.int64)
    if len(triangles) == 0:
        raise ValueError(f"{path}: no triangles in this mesh")
    if m.has_triangle_uvs() and len(m.triangle_uvs) == 3 * len(triangles):
        uvs = np.asarray(m.triangle_uvs, dtype=float).reshape(-1, 3, 2)
    else:
        lo, hi = vertices[:, :2].min(0), vertices[:, :2].max(0)
        uvs = ((vertices[:, :2] - lo) / np.maximum(hi - lo, 1e-12))[triangles]
    return TexturedMesh(vertices, triangles, uvs, np.zeros(len(triangles), np.int64), [texture])


def sample_surface(mesh: TexturedMesh, count: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`count` points spread uniformly over the mesh area (seeded).

    Returns positions (N,3), triangle ids (N,) and barycentric (u, v) (N,2) in Open3D's convention
    (point = (1-u-v) a + u b + v c), so texture colours can be looked up like a ray hit's.
    """
    rng = np.random.default_rng(seed)
    areas = mesh.triangle_areas()
    tri = rng.choice(len(areas), size=count, p=areas / areas.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    a, b, c = (mesh.vertices[mesh.triangles[tri, k]] for k in range(3))
    bu, bv = s * (1 - r2), s * r2
    return (1 - s)[:, None] * a + bu[:, None] * b + bv[:, None] * c, tri, np.stack([bu, bv], axis=1)
