"""Ray-cast rendering of textured meshes with Open3D's RaycastingScene (Embree on the CPU).

Each pixel averages s x s rays (supersampling against aliasing); a hit's colour is its texture, looked up
bilinearly at the interpolated UV, times a view-independent shade (Lambertian under a fixed directional light,
or a secondary-electron-like yield for SEM), times the image's exposure and vignetting, plus seeded sensor
noise. Because the shade does not depend on the viewer, the same surface point has the same colour in every
image up to exposure, which is what makes photometric checks of the ground truth meaningful.
"""

from dataclasses import dataclass

import numpy as np

from ..interrupts import import_open3d
from .cameras import CameraRays, OrthographicCamera, PerspectiveCamera
from .meshes import TexturedMesh
from .textures import TextureAtlas, make_texture


@dataclass(frozen=True)
class RenderSettings:
    """Image formation settings.

    supersample: rays per pixel side (2 = 4 rays per pixel).
    shading: "lambertian" (ambient + diffuse under a directional light) or "sem" (brighter where the surface
      is steep to the beam, as secondary-electron images are).
    light: direction the light travels, world frame; ambient: the unlit fraction.
    background: linear RGB of rays that hit nothing.
    noise_sigma: Gaussian sensor noise in 8-bit grey levels; vignetting: relative fall-off at the corners.
    alpha: RGBA images: alpha is the share of a pixel's rays that hit a surface, colour the mean of those
      rays (straight alpha) and 0 where no ray hits, as a renderer with a transparent film writes them (the
      NeRF synthetic sets); the background colour and the noise are then not used outside the object.
      Readers that drop alpha (mvrecon, COLMAP) see the object on black.
    """

    supersample: int = 2
    shading: str = "lambertian"
    light: tuple[float, float, float] = (0.4, 0.3, -1.0)
    ambient: float = 0.35
    background: tuple[float, float, float] = (0.55, 0.6, 0.65)
    noise_sigma: float = 1.0
    vignetting: float = 0.0
    alpha: bool = False


@dataclass
class Hits:
    """Ray-cast results: ray parameter t (inf for misses), triangle id, barycentric uv, normal."""

    t: np.ndarray
    triangle: np.ndarray
    bary: np.ndarray
    normal: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.t)


class Renderer:
    """Renders one mesh from many cameras; textures and the Embree scene are built once."""

    def __init__(
        self,
        mesh: TexturedMesh,
        settings: RenderSettings = RenderSettings(),
        texture_arrays: list[np.ndarray] | None = None,
    ):
        """texture_arrays (float RGB in [0, 1]) replace the mesh's texture specs (targets)."""
        o3d = self._o3d = import_open3d()  # once: its Ctrl-C guard need not run on every cast

        self.mesh = mesh
        self.settings = settings
        if texture_arrays is None:
            texture_arrays = [make_texture(spec) for spec in mesh.textures]
        self.atlas = TextureAtlas(texture_arrays)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
        )
        self._rays: dict = {}
        # per triangle, in texel units of its texture: corner 0, edges 0->1 and 0->2, texture width and height
        size = np.stack([self.atlas.widths, self.atlas.heights], 1)[mesh.texture_ids].astype(np.float64)
        uv = mesh.uvs * size[:, None, :]
        self._tri_table = np.concatenate(
            [uv[:, 0], uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0], size], 1
        ).astype(np.float32)
        self._tri_offsets = self.atlas.offsets[mesh.texture_ids]

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """World-frame rays (N,3) + (N,3); t is in units of the direction's length."""
        return self._cast(np.concatenate([origins, directions], axis=1, dtype=np.float32))

    def _cast(self, rays: np.ndarray) -> Hits:
        ans = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        # copy out of Open3D's buffers: the arrays must not outlive `ans` as views
        t = ans["t_hit"].numpy().copy()
        tri = np.where(np.isfinite(t), ans["primitive_ids"].numpy().astype(np.int64), -1)
        return Hits(t, tri, ans["primitive_uvs"].numpy().copy(), ans["primitive_normals"].numpy().copy())

    def occluded(self, origins: np.ndarray, targets: np.ndarray, rel_tol: float = 1e-4) -> np.ndarray:
        """True where the segment origin -> target hits a surface clearly before the target."""
        hits = self.cast(origins, targets - origins)
        return hits.t < 1.0 - rel_tol

    def albedo(self, hits: Hits) -> np.ndarray:
        """Texture colour (N,3) at each hit (rows of misses are garbage; callers overwrite them)."""
        tri = np.maximum(hits.triangle, 0)
        row = np.take(self._tri_table, tri, axis=0)
        b0, b1 = hits.bary[:, 0], hits.bary[:, 1]
        x = row[:, 0] + b0 * row[:, 2] + b1 * row[:, 4]
        y = row[:, 1] + b0 * row[:, 3] + b1 * row[:, 5]
        return self.atlas.lookup(x, y, row[:, 6], row[:, 7], np.take(self._tri_offsets, tri))

    def shade(self, hits: Hits, view_dirs: np.ndarray) -> np.ndarray:
        """Scalar shade (N,) of each valid hit; surfaces are lit from both sides."""
        s = self.settings
        n = hits.normal
        if s.shading == "lambertian":
            light = np.asarray(s.light, np.float32)
            light /= np.linalg.norm(light)
            return s.ambient + (1 - s.ambient) * np.abs(n @ light)
        if s.shading == "sem":
            d = view_dirs / np.linalg.norm(view_dirs, axis=1, keepdims=True)
            cos = np.clip(np.abs(np.sum(n * d, axis=1)), 0.25, 1.0)
            # secondary-electron yield grows like 1/cos of the incidence angle: steep flanks and edges glow
            return s.ambient + (1 - s.ambient) * 3.0 * (1.0 / cos - 1.0)
        raise ValueError(f"unknown shading {s.shading!r}; expected lambertian or sem")

    def render(
        self,
        cam: PerspectiveCamera | OrthographicCamera,
        pose: tuple[np.ndarray, np.ndarray],
        exposure: float = 1.0,
        seed: int = 0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(image uint8 (H,W,3), or (H,W,4) with `settings.alpha`; z-depth float32 (H,W) with inf where no
        surface) of `cam` at pose (R, t).

        Depth is cast through the pixel centres; the image averages the supersampled rays.
        """
        s = self.settings
        key = (cam, s.supersample)
        if key not in self._rays:
            self._rays[key] = CameraRays(cam, s.supersample)
        rays = self._rays[key]
        R, t = (np.asarray(a, float) for a in pose)
        centre_cam = -R.T @ t

        def world_rays(origins_cam, dirs_cam):
            """(N,6) float32 world rays, column by column (much faster than an (N,3) @ (3,3) product)."""
            out = np.empty((len(dirs_cam), 6), np.float32)
            for j in range(3):
                out[:, j] = centre_cam[j]
                if origins_cam is not None:
                    out[:, j] += origins_cam[:, 0] * R[0, j] + origins_cam[:, 1] * R[1, j]
                out[:, 3 + j] = dirs_cam[:, 0] * R[0, j] + dirs_cam[:, 1] * R[1, j] + dirs_cam[:, 2] * R[2, j]
            return out

        world = world_rays(*rays.samples)
        hits = self._cast(world)
        d = world[:, 3:]
        colour = self.albedo(hits) * self.shade(hits, d)[:, None].astype(np.float32)
        h, w, ss = cam.height, cam.width, s.supersample
        colour[~hits.valid] = 0.0 if s.alpha else s.background
        image = colour.reshape(h, ss, w, ss, 3).mean(axis=(1, 3)) * exposure
        if s.alpha:  # the mean of the rays that hit
            coverage = hits.valid.reshape(h, ss, w, ss).mean(axis=(1, 3))
            image /= np.maximum(coverage, 1e-12)[..., None]
        if s.vignetting:
            v, u = np.mgrid[0:h, 0:w]
            r2 = ((u + 0.5 - w / 2) ** 2 + (v + 0.5 - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
            image = image * (1.0 - s.vignetting * r2)[..., None]
        image = image * 255.0
        if s.noise_sigma > 0:
            image = image + np.random.default_rng(seed).normal(0.0, s.noise_sigma, image.shape)
        image = np.clip(np.round(image), 0, 255).astype(np.uint8)
        if s.alpha:
            image[coverage == 0] = 0
            image = np.concatenate([image, np.round(255 * coverage).astype(np.uint8)[..., None]], axis=2)

        depth_hits = self._cast(world_rays(*rays.centres))
        depth = np.where(depth_hits.valid, depth_hits.t, np.inf).reshape(h, w).astype(np.float32)
        return image, depth
