"""Our `sfm.model.Reconstruction` -> `pycolmap.Reconstruction`, written as COLMAP `sparse/N` folders.

Only registered images go into a model (each with a trivial rig and frame, as COLMAP 3.12+ stores them), with
all their keypoints as 2D points so point2D indices stay the database's keypoint indices. Point colours come
from the colours at the keypoints that feature extraction sampled, or else from the images when the image
folder is given.
"""

import logging
from pathlib import Path

import numpy as np
import pycolmap

from .files import require_room, some_names
from .ply import write_ply

log = logging.getLogger("mvrecon.io")


def to_pycolmap(model, colors=None) -> pycolmap.Reconstruction:
    """A pycolmap reconstruction holding the registered images, their cameras and the alive points (coloured
    by `colors`, indexed by point id, when given)."""
    rec = pycolmap.Reconstruction()
    used = np.unique(model.camera_of[model.registered])
    for cid in used:
        cam = model.cameras[int(cid)]
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=cam.model, width=int(cam.width),
                                                        height=int(cam.height), params=np.asarray(cam.params),
                                                        camera_id=int(cid),
                                                        has_prior_focal_length=bool(cam.prior_trusted)))
    for i in model.registration_order:
        image = pycolmap.Image(name=model.names[i],
                               keypoints=np.asarray(model.keypoints[i], dtype=np.float64),
                               camera_id=int(model.camera_of[i]), image_id=int(model.image_ids[i]))
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(model.R[i])), np.asarray(model.t[i]))
        rec.add_image_with_trivial_frame(image, pose)
    obs = model.alive_observations()
    op = model.obs_point.data[obs]
    order = np.argsort(op, kind="stable")
    obs, op = obs[order], op[order]
    uniq, start = np.unique(op, return_index=True)
    ends = np.r_[start[1:], len(op)]
    img_ids = model.image_ids[model.obs_image.data[obs]]
    kps = model.obs_kp.data[obs]
    xyz = model.xyz.data
    black = np.zeros(3, np.uint8)
    for p, s, e in zip(uniq, start, ends):
        track = pycolmap.Track()
        for a, b in zip(img_ids[s:e], kps[s:e]):
            track.add_element(int(a), int(b))
        rec.add_point3D(xyz[p], track, black if colors is None else colors[p])
    rec.update_point_3d_errors()
    return rec


def point_colors(model, keypoint_colors: dict) -> np.ndarray | None:
    """RGB (uint8) of every point id: the mean of the colours at its alive observations' keypoints (from
    `keypoint_colors`: image name -> io.images.colors_at of its keypoints), rounded, as COLMAP's
    `extract_colors_for_all_images` averages its samples; black without any. None when an image of the model
    has no keypoint colours."""
    obs = model.alive_observations()
    img, kp, pt = model.obs_image.data[obs], model.obs_kp.data[obs], model.obs_point.data[obs]
    rgb = np.empty((len(obs), 3))
    for i in np.unique(img):
        samples = keypoint_colors.get(model.names[i])
        if samples is None:
            return None
        m = img == i
        rgb[m] = samples[kp[m]]
    valid = np.isfinite(rgb).all(axis=1)  # keypoints at the border have no colour (NaN), as in COLMAP
    n = len(model.xyz.data)
    counts = np.bincount(pt[valid], minlength=n)
    sums = np.stack([np.bincount(pt[valid], weights=rgb[valid, c], minlength=n) for c in range(3)], axis=1)
    return np.round(sums / np.maximum(counts, 1)[:, None]).clip(0, 255).astype(np.uint8)


def write_models(models, sparse_dir, image_dir=None, text: bool = False,
                 keypoint_colors=None) -> list[pycolmap.Reconstruction]:
    """Write models (largest first) to sparse_dir/0, 1, ...; point colours from `keypoint_colors` (see
    point_colors) when it covers a model's images, otherwise from the images in image_dir when given."""
    sparse_dir = Path(sparse_dir)
    out = []
    for k, model in enumerate(models):
        colors = point_colors(model, keypoint_colors) if keypoint_colors else None
        rec = to_pycolmap(model, colors)
        if colors is None and image_dir is not None:
            rec.extract_colors_for_all_images(str(image_dir))
        d = sparse_dir / str(k)
        require_room(d, model_bytes(rec) * (4 if text else 1))
        d.mkdir(parents=True, exist_ok=True)
        rec.write_binary(str(d))
        if text:
            rec.write_text(str(d))
        out.append(rec)
    return out


def model_bytes(rec: pycolmap.Reconstruction) -> int:
    """About the size of a binary model's files (the text ones take up to three times as much): pycolmap writes
    models without reporting a failed write (on a full disk it left points3D.bin empty), so room is checked
    first. Every keypoint of an image is a 2D point of 24 bytes, a 3D point 51 bytes and 8 per observation."""
    num_points2d = sum(im.num_points2D() for im in rec.images.values())
    return 24 * num_points2d + 256 * rec.num_images() + 64 * rec.num_points3D() + 8 * rec.compute_num_observations()


def write_text_models(sparse_dir) -> int:
    """Add the COLMAP text files to every binary model sparse_dir/N (a finished run asked for --text again);
    returns the number of models."""
    dirs = [d for d in sorted(Path(sparse_dir).iterdir()) if (d / "cameras.bin").is_file()]
    recs = [pycolmap.Reconstruction(str(d)) for d in dirs]
    require_room(sparse_dir, 3 * sum(model_bytes(rec) for rec in recs))
    for rec, d in zip(recs, dirs):
        rec.write_text(str(d))
    warn_text_names(recs, sparse_dir)
    return len(dirs)


def warn_text_names(recs, sparse_dir) -> None:
    """Warn when an image name of the text models sparse_dir/N holds white space: the text format ends a name at
    its first space, so COLMAP's reader (pycolmap read 'photo 2.png' back as 'photo') and nerfstudio's lose
    those names; the binary files next to them keep them whole."""
    for k, rec in enumerate(recs):
        spaced = sorted(im.name for im in rec.images.values() if any(c.isspace() for c in im.name))
        if spaced:
            log.warning("%s: image names with spaces (%s) cannot be read back from images.txt, which ends a "
                        "name at its first space; read the binary model in the same folder, or rename the images",
                        Path(sparse_dir) / str(k) / "images.txt", some_names(map(repr, spaced)))


def write_points_ply(rec: pycolmap.Reconstruction, path) -> int:
    """Coloured PLY of a model's points; returns the number of points."""
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts]).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    write_ply(path, xyz, rgb)
    return len(pts)
