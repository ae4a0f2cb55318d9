"""Poses and statistics out of COLMAP models (pycolmap), in the plain form `eval.metrics` works on."""

from pathlib import Path

import numpy as np
import pycolmap

from ..geometry.rotation import rotmat_to_quat
from ..io.colmap_model import load_reconstruction


def poses(rec: pycolmap.Reconstruction) -> dict:
    """image name -> (R, t) world-to-camera, for registered images."""
    out = {}
    for image in rec.images.values():
        if image.has_pose:
            T = image.cam_from_world()
            out[image.name] = (np.asarray(T.rotation.matrix()), np.asarray(T.translation))
    return out


def model_stats(rec: pycolmap.Reconstruction) -> dict:
    """Registered images, points, mean track length, mean reprojection error (px)."""
    n_points = rec.num_points3D()
    return {"registered": rec.num_reg_images(), "points": n_points,
            "mean_track_length": float(rec.compute_mean_track_length()) if n_points else 0.0,
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()) if n_points else float("nan")}


def sparse_models(sparse_dir: Path | str) -> list[pycolmap.Reconstruction]:
    """All models under `sparse/` (folders 0, 1, ...), largest first."""
    sparse_dir = Path(sparse_dir)
    dirs = sorted((d for d in sparse_dir.iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name)) \
        if sparse_dir.is_dir() else []
    recs = [load_reconstruction(d) for d in dirs]
    return sorted(recs, key=lambda r: r.num_reg_images(), reverse=True)


def reconstruction_from_poses(poses_by_name: dict, width: int = 2, height: int = 2) -> pycolmap.Reconstruction:
    """A camera-only pycolmap model of plain poses, so ground truth in any format meets pycolmap's own tools
    (e.g. `align_reconstructions_via_proj_centers`). Intrinsics are placeholders; only poses carry meaning."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=width, height=height, params=[1.0, width / 2, height / 2])
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    for image_id, name in enumerate(sorted(poses_by_name), start=1):
        R, t = poses_by_name[name]
        w, x, y, z = rotmat_to_quat(R)
        image = pycolmap.Image(name=name, camera_id=1)
        image.image_id = image_id
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d([x, y, z, w]),
                                                                 np.asarray(t, dtype=float)))
    return rec
