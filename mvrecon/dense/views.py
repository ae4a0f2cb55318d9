"""The dense workspace's views: undistorted PINHOLE images and their poses, read from the sparse model, with the
sparse points each view sees (its depth range and its source views come from them).

The workspace is COLMAP's (`colmap image_undistorter` output, read by its `patch_match_stereo` and
`stereo_fusion`):

    DENSE/images/<name>                         undistorted images (io.undistort.export_undistorted)
    DENSE/sparse/{cameras,images,points3D}.bin  the PINHOLE model of those images
    DENSE/stereo/depth_maps/<name>.{photometric,geometric}.bin, stereo/normal_maps/<name>.*.bin
"""

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.colmap_model import load_reconstruction
from ..io.undistort import export_undistorted

EXPORT = ".undistorted"  # the export is written here inside the dense folder, then moved into COLMAP's layout


@dataclass
class View:
    """One undistorted image: x_cam = R @ X + t, pixel = K @ x_cam / z. `points`: the sparse points it sees
    (N, 3, world frame)."""

    index: int
    name: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    points: np.ndarray
    point_ids: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    def depths(self, xyz: np.ndarray) -> np.ndarray:
        return xyz @ self.R[2] + self.t[2]


def undistort_into(model_dir: Path, image_dir: Path, dense_dir: Path, max_image_size: int,
                   database: Path | None = None) -> None:
    """Write DENSE/images/ and DENSE/sparse/ (PINHOLE) with the project's export, in COLMAP's dense layout
    (sparse/ flat, as `image_undistorter` leaves it). An earlier workspace's images and model are replaced."""
    staging = dense_dir / EXPORT
    export_undistorted(model_dir, image_dir, staging, max_image_size=max_image_size, database=database)
    for old in (dense_dir / "images", dense_dir / "sparse"):
        if old.exists():
            shutil.rmtree(old)
    (staging / "images").replace(dense_dir / "images")
    (staging / "sparse" / "0").replace(dense_dir / "sparse")
    shutil.rmtree(staging)


def read_views(sparse_dir: Path) -> list[View]:
    """The registered images of the PINHOLE model in `sparse_dir`, in name order."""
    rec = load_reconstruction(sparse_dir)
    xyz = {pid: p.xyz for pid, p in rec.points3D.items()}
    views = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        if cam.model.name != "PINHOLE":
            raise InputError(f"{sparse_dir}: camera {cam.camera_id} is {cam.model.name}, not the PINHOLE of an "
                             "undistorted model")
        fx, fy, cx, cy = cam.params
        pose = image.cam_from_world()
        ids = np.array(sorted({p.point3D_id for p in image.points2D if p.has_point3D()}), dtype=np.int64)
        points = np.array([xyz[i] for i in ids], float).reshape(-1, 3)
        views.append(View(len(views), image.name, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
                          np.asarray(pose.rotation.matrix(), float), np.asarray(pose.translation, float),
                          int(cam.width), int(cam.height), points, ids))
    return views
