"""Poses and statistics out of COLMAP models (pycolmap), in the plain form `eval.metrics` works on."""

from pathlib import Path

import numpy as np
import pycolmap

from ..errors import InputError


def load_reconstruction(path) -> pycolmap.Reconstruction:
    """A COLMAP model folder (binary or text); an InputError names the folder when it holds no model or one
    that pycolmap cannot read (a cut-off images.bin raises IndexError there, a garbled cameras.bin ValueError)."""
    path = Path(path)
    if not (path / "images.bin").exists() and not (path / "images.txt").exists():
        raise InputError(f"{path}: no COLMAP model (images.bin or images.txt) here")
    for name, check in (("points3D.bin", _points_problem), ("images.bin", _images_problem)):
        if (path / name).is_file():
            problem = check((path / name).read_bytes())
            if problem:
                raise InputError(f"{path}: cannot read this COLMAP model ({name}: {problem})")
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:
        raise InputError(f"{path}: cannot read this COLMAP model ({type(exc).__name__}: {exc})") from None
    for cam in rec.cameras.values():  # a cut-off cameras.bin reads as zeros
        params = np.asarray(cam.params, float)
        if not len(params) or not np.isfinite(params).all() or min(cam.focal_length_x, cam.focal_length_y) <= 0:
            raise InputError(f"{path}: cannot read this COLMAP model (camera {cam.camera_id}: parameters "
                             f"{params.tolist()})")
    return rec


def _points_problem(data: bytes) -> str | None:
    """Whether points3D.bin's records add up to its size. pycolmap reads a file cut off mid-record as garbage
    lengths and may allocate without end (a compare run hung for minutes), so the sizes are walked first:
    count, then per point id, xyz, rgb, error (43 bytes), a track length and 8 bytes per track element."""
    import struct

    n, offset = struct.unpack_from("<Q", data, 0)[0] if len(data) >= 8 else 0, 8
    for k in range(n):
        if offset + 51 > len(data):
            return f"cut off after {k} of {n} points"
        offset += 51 + 8 * struct.unpack_from("<Q", data, offset + 43)[0]
    return _ending(offset, len(data), n, "points")


def _images_problem(data: bytes) -> str | None:
    """The same for images.bin: per image id, rotation, translation, camera id (64 bytes), a name ending in a
    zero byte, a count of 2D points and 24 bytes per point."""
    import struct

    n, offset = struct.unpack_from("<Q", data, 0)[0] if len(data) >= 8 else 0, 8
    for k in range(n):
        end = data.find(b"\0", offset + 64)
        if end < 0 or end + 9 > len(data):
            return f"cut off after {k} of {n} images"
        offset = end + 9 + 24 * struct.unpack_from("<Q", data, end + 1)[0]
    return _ending(offset, len(data), n, "images")


def _ending(offset: int, size: int, n: int, what: str) -> str | None:
    if offset > size:
        return f"cut off in the last of its {n} {what}"
    return f"{size - offset} bytes after its {n} {what}" if offset < size else None


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


def sparse_models(sparse_dir) -> list[pycolmap.Reconstruction]:
    """All models under `sparse/` (folders 0, 1, ...), largest first."""
    sparse_dir = Path(sparse_dir)
    dirs = sorted((d for d in sparse_dir.iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name)) \
        if sparse_dir.is_dir() else []
    recs = [load_reconstruction(d) for d in dirs]
    return sorted(recs, key=lambda r: r.num_reg_images(), reverse=True)


def reconstruction_from_poses(poses_by_name: dict, width: int = 2, height: int = 2) -> pycolmap.Reconstruction:
    """A camera-only pycolmap model of plain poses, so ground truth in any format meets pycolmap's own tools
    (e.g. `align_reconstructions_via_proj_centers`). Intrinsics are placeholders; only poses carry meaning."""
    from ..geometry.rotation import rotmat_to_quat

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
