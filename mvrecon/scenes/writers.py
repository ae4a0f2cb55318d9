"""Writers for a scene folder: images, the ground-truth COLMAP model, depth maps, stereo and SEM ground truth.

Files are written so that the same inputs give the same bytes (no timestamps, fixed PNG/JPEG settings), which
is what lets `make_scene` promise deterministic, cached output.
"""

from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from ..io.files import replace_whole
from ..io.pfm import write_pfm
from .cameras import PerspectiveCamera


def write_image(path: Path | str, image: np.ndarray, jpeg_quality: int = 95, exif: Image.Exif | None = None) -> None:
    """PNG or JPEG by the file suffix; RGB uint8 (H,W,3) or grey (H,W), with an EXIF block when given (a
    drone's GPS position: `io.gps.gps_exif`). Whole or not at all, as a rerun after Ctrl-C keeps the views on
    disk."""
    pil = Image.fromarray(image)
    extra = {} if exif is None else {"exif": exif}
    if Path(path).suffix.lower() in (".jpg", ".jpeg"):
        replace_whole(path, lambda tmp: pil.save(tmp, quality=jpeg_quality, subsampling=0, optimize=False,
                                                 **extra))
    else:
        replace_whole(path, lambda tmp: pil.save(tmp, compress_level=6, optimize=False, **extra))


def write_colmap_model(
    path: Path | str,
    cam: PerspectiveCamera | list[PerspectiveCamera],
    names: list[str],
    poses: list,
    points: np.ndarray,
    colors: np.ndarray,
    observations: list[tuple[np.ndarray, np.ndarray]],
) -> None:
    """A binary COLMAP model: one camera (cam.model, cam.params) for all images, or with a list `cam`, a camera
    per image unless they are all equal; one trivial rig/frame per image, the points.

    observations[i] = (indices into `points`, pixels (N,2)) for image i; each becomes a Point2D of that image
    in the order given, and the points' tracks link back to them. Points seen in fewer than two images are
    skipped.
    """
    rec = pycolmap.Reconstruction()
    cams = cam if isinstance(cam, list) else [cam]
    if all(c == cams[0] for c in cams):
        cams = cams[:1]
    for camera_id, c in enumerate(cams, start=1):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            model=c.model, width=c.width, height=c.height, params=list(c.params), camera_id=camera_id
        ))
    tracks: dict[int, list] = {}
    for image_id, (name, (R, t), (idx, uv)) in enumerate(zip(names, poses, observations), start=1):
        image = pycolmap.Image(
            name=name, keypoints=np.asarray(uv, float).reshape(-1, 2),
            camera_id=image_id if len(cams) > 1 else 1, image_id=image_id
        )
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(R, float)), np.asarray(t, float))
        )
        for k, p in enumerate(idx):
            tracks.setdefault(int(p), []).append((image_id, k))
    for p in sorted(tracks):
        elements = tracks[p]
        if len(elements) < 2:
            continue
        track = pycolmap.Track()
        for image_id, k in elements:
            track.add_element(image_id, k)
        rec.add_point3D(np.asarray(points[p], float), track, np.asarray(colors[p], np.uint8))
    rec.update_point_3d_errors()
    Path(path).mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(path))


def write_depth(path: Path | str, depth: np.ndarray) -> None:
    """float32 z-depth (H,W), inf where no surface; whole or not at all, as images."""
    replace_whole(path, lambda tmp: np.save(tmp, np.asarray(depth, np.float32)))


def write_middlebury_calib(
    path: Path | str, fx: float, cx: float, cy: float, baseline: float, width: int, height: int, ndisp: int
) -> None:
    """Middlebury calib.txt for a `baseline` in metres (the stereo scenes' unit), written in millimetres as the
    format specifies, so depth from it (Z = f B / (d + doffs)) is in mm as with Middlebury's own pairs.
    Middlebury's pixel origin is the top-left pixel centre, so cx, cy here are COLMAP's minus 0.5; the same
    principal point in both images means doffs = 0."""
    cam = f"[{fx:.6f} 0 {cx - 0.5:.6f}; 0 {fx:.6f} {cy - 0.5:.6f}; 0 0 1]"
    text = (
        f"cam0={cam}\ncam1={cam}\ndoffs=0\nbaseline={1000 * baseline:.6f}\nwidth={width}\nheight={height}\n"
        f"ndisp={ndisp}\nisint=0\nvmin=0\nvmax={ndisp - 1}\n"
    )
    Path(path).write_text(text)


def write_disparity(path: Path | str, disparity: np.ndarray) -> None:
    write_pfm(path, np.asarray(disparity, np.float32))
