"""The comparison report shows a run's dense workspace (depth-map thumbnails, the fused cloud) when it has one, and
nothing more when it has none."""

import base64
import io
import re

import numpy as np
import pycolmap
from PIL import Image

from mvrecon.eval.compare import compare_models
from mvrecon.eval.models import reconstruction_from_poses
from mvrecon.eval.report import write_report
from mvrecon.io.colmap_array import write_colmap_array
from mvrecon.io.ply import write_ply


def ring(n: int = 6) -> dict:
    """n cameras on a ring of radius 4 round the origin, looking at it (name -> (R, t))."""
    out = {}
    for k in range(n):
        a = 2 * np.pi * k / n
        centre = np.array([4 * np.cos(a), 4 * np.sin(a), 0.0])
        z = -centre / 4
        x = np.cross([0.0, 0.0, 1.0], z)
        R = np.stack([x, np.cross(z, x), z])
        out[f"{k:03d}.png"] = (R, -R @ centre)
    return out


def dense_workspace(folder, poses: dict) -> None:
    """A dense workspace of a red ball of radius 1 at the origin: PINHOLE 80x60 views, each's depth map (4 - 1
    in its middle, none elsewhere) and the ball's points as fused.ply."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=80, height=60,
                                                    params=[60.0, 60.0, 40.0, 30.0], camera_id=1))
    maps = folder / "stereo" / "depth_maps"
    maps.mkdir(parents=True)
    for image_id, (name, (R, t)) in enumerate(sorted(poses.items()), start=1):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
        depth = np.zeros((60, 80), np.float32)
        depth[22:38, 32:48] = 3.0
        write_colmap_array(maps / f"{name}.geometric.bin", depth)
    (folder / "sparse").mkdir()
    rec.write_binary(str(folder / "sparse"))
    ball = np.random.default_rng(0).normal(size=(20000, 3))
    ball /= np.linalg.norm(ball, axis=1, keepdims=True)
    write_ply(folder / "fused.ply", ball, np.tile([[220, 20, 20]], (len(ball), 1)).astype(np.uint8))


def pictures(page: str, alt: str) -> list[np.ndarray]:
    found = re.findall(rf"<img alt='{alt}' src='data:image/png;base64,([^']+)'>", page)
    return [np.asarray(Image.open(io.BytesIO(base64.b64decode(b)))) for b in found]


def test_a_dense_workspace_shows_its_depth_maps_and_fused_cloud_and_none_shows_nothing(tmp_path):
    poses = ring()
    for engine in ("mv", "cm"):
        (tmp_path / engine / "sparse" / "0").mkdir(parents=True)
        reconstruction_from_poses(poses).write(str(tmp_path / engine / "sparse" / "0"))
    before = compare_models([tmp_path / "mv", tmp_path / "cm"]).metrics
    assert all(e["dense"] is None for e in before["engines"].values())
    page = write_report(compare_models([tmp_path / "mv", tmp_path / "cm"]), tmp_path / "plain").read_text()
    assert "id='dense'" not in page and "depth map" not in page

    dense_workspace(tmp_path / "mv" / "dense", poses)
    comparison = compare_models([tmp_path / "mv", tmp_path / "cm"])
    summary = comparison.metrics["engines"]["mv"]["dense"]
    assert summary == {"folder": str(tmp_path / "mv" / "dense"), "depth_maps": 6, "fused_points": 20000,
                       "mesh": False}
    assert comparison.metrics["engines"]["cm"]["dense"] is None
    page = write_report(comparison, tmp_path / "report").read_text()
    assert "id='dense'" in page and "20,000 fused points" in page
    for name in poses:
        thumbs = pictures(page, f"depth map {name}")
        assert len(thumbs) == 1
        thumb = thumbs[0]
        assert thumb.shape[:2] == (60, 80)
        assert np.all(thumb[0, 0] == 255) and not np.all(thumb[30, 40] == 255)  # no depth: white
    (cloud,) = pictures(page, "fused cloud")
    red = (cloud[..., 0] > 200) & (cloud[..., 1] < 60)
    ys, xs = np.nonzero(red)
    # the ball (radius 1 at 4 units, f = 60) fills a disc of radius ~15 px round the image centre
    assert 500 < red.sum() < 900
    assert abs(xs.mean() - 40) < 1.5 and abs(ys.mean() - 30) < 1.5
