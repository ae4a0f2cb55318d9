"""A mesh of the fused cloud: Open3D's screened Poisson reconstruction, with the vertices that few points
supported trimmed (Poisson closes the surface everywhere; where its density is low it invents the surface)."""

from pathlib import Path

import numpy as np

from ..interrupts import import_open3d


def poisson_mesh(points: np.ndarray, colors: np.ndarray, normals: np.ndarray, path: Path | str, *,
                 depth: int = 9, trim_quantile: float = 0.05) -> tuple[int, int]:
    """Write the Poisson mesh of the oriented, coloured points to `path` (PLY); returns (vertices, triangles).
    The vertices whose Poisson density is in the lowest `trim_quantile` are removed with their triangles."""
    o3d = import_open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, float)))
    cloud.colors = o3d.utility.Vector3dVector(np.asarray(colors, float) / 255.0)
    normals = np.asarray(normals, float)
    if not (np.linalg.norm(normals, axis=1) > 0).all():
        cloud.estimate_normals()
    else:
        cloud.normals = o3d.utility.Vector3dVector(normals)
    # Poisson at `depth` resolves 2^depth cells along the longest side: more than one point per cell adds time
    # (minutes for millions of fused points), not detail (on room, one point per cell instead of one per half
    # cell: a third of the points, a quarter of the thinning's time, as many mesh vertices)
    extent = float(np.max(np.ptp(np.asarray(points, float), axis=0))) if len(points) else 0.0
    if extent > 0:
        cloud = cloud.voxel_down_sample(extent / 2**depth)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=depth)
    density = np.asarray(density)
    if len(density):
        mesh.remove_vertices_by_mask(density < np.quantile(density, trim_quantile))
    o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False)
    return len(mesh.vertices), len(mesh.triangles)
