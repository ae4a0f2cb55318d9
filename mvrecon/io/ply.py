"""Binary little-endian PLY point clouds with optional colours and normals, readable by Open3D, MeshLab and
CloudCompare."""

from pathlib import Path

import numpy as np

from ..interrupts import import_open3d


def write_ply(path: Path | str, points: np.ndarray, colors: np.ndarray | None = None,
              normals: np.ndarray | None = None) -> None:
    """points (N,3) float; colors (N,3) uint8 (or floats in [0,1]); normals (N,3) float."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    columns = [points[:, 0], points[:, 1], points[:, 2]]
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float32).reshape(n, 3)
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        columns += [normals[:, 0], normals[:, 1], normals[:, 2]]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype != np.uint8:
            colors = np.clip(np.round(colors * 255.0 if colors.max(initial=0) <= 1.0 else colors), 0, 255)
        colors = colors.astype(np.uint8).reshape(n, 3)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        columns += [colors[:, 0], colors[:, 1], colors[:, 2]]
    data = np.empty(n, dtype=fields)
    for (name, _), col in zip(fields, columns):
        data[name] = col
    ply_types = {"<f8": "double", "<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property {ply_types[t]} {name}" for name, t in fields]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())


def read_ply_points(path: Path | str) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N,3) and colours (N,3) uint8 or None, from a PLY written by `write_ply` (or any Open3D can read)."""
    o3d = import_open3d()

    cloud = o3d.io.read_point_cloud(str(path))
    points = np.asarray(cloud.points)
    colors = (np.asarray(cloud.colors) * 255).round().astype(np.uint8) if cloud.has_colors() else None
    return points, colors
