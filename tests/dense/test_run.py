"""`run_dense` end to end on a small synthetic model: a textured plane seen by four views, and a fifth view that
sees too few sparse points. The depth maps are COLMAP arrays that read back, the fused points lie on the plane,
the view without a depth map is named with its reason, and a folder without a model is refused."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from mvrecon.dense import DenseSettings, run_dense
from mvrecon.dense.run import view_threads
from mvrecon.dense.select import MIN_POINTS
from mvrecon.errors import InputError
from mvrecon.io.colmap_array import read_colmap_array
from mvrecon.io.ply import read_ply_points
from mvrecon.scenes.writers import write_colmap_model, write_image

from .test_sweep import DEPTH, K, _render_plane


def _plane_model(folder):
    """Images and a PINHOLE model of the plane z = DEPTH; returns (model folder, image folder)."""
    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur(rng.random((1200, 1600)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    scale = 3 * DEPTH / 300 / 1200 * 240 / 2
    poses = [(np.eye(3), np.zeros(3))]
    for angle, shift in ((4.0, [0.4, 0.0, 0.0]), (-3.0, [-0.35, 0.1, 0.05]), (2.0, [0.0, -0.3, 0.0]),
                         (1.0, [0.2, 0.2, 0.0])):
        poses.append((cv2.Rodrigues(np.radians([0.0, angle, 0.0]))[0], np.asarray(shift, float)))
    images = folder / "images"
    images.mkdir()
    names = [f"{i}.png" for i in range(len(poses))]
    for name, (R, t) in zip(names, poses):
        grey = (255 * _render_plane(R, t, texture, scale)).astype(np.uint8)
        write_image(images / name, np.dstack([grey] * 3))
    points = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-0.8, 0.8, 200), np.full(200, DEPTH)])
    observations = []
    for k, (R, t) in enumerate(poses):
        cam = points @ R.T + t
        uv = cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        seen = np.nonzero((uv[:, 0] > 0) & (uv[:, 0] < 320) & (uv[:, 1] > 0) & (uv[:, 1] < 240))[0]
        if k == len(poses) - 1:
            seen = seen[: MIN_POINTS - 2]  # the last view sees too few points for a depth range
        observations.append((seen, uv[seen]))
    camera = SimpleNamespace(model="PINHOLE", width=320, height=240, params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    write_colmap_model(folder / "sparse", camera, names, poses, points, np.full((200, 3), 128), observations)
    return folder / "sparse", images


@pytest.mark.slow
def test_dense_on_a_plane(tmp_path):
    model, images = _plane_model(tmp_path)
    out = tmp_path / "dense"
    settings = DenseSettings(coarse_size=160)  # coarse to fine, as larger views are
    summary = run_dense(model, images, out, workers=1, views=4, settings=settings)
    assert set(summary.views) == {"0.png", "1.png", "2.png", "3.png"}
    assert "sees 10 sparse points (needs 12)" in summary.skipped["4.png"]
    depth = read_colmap_array(out / "stereo" / "depth_maps" / "0.png.geometric.bin")
    assert depth.shape == (240, 320)
    err = np.abs(depth[depth > 0] - DEPTH) / DEPTH
    assert (depth > 0).mean() > 0.8 and (err <= 0.005).mean() > 0.95
    # the PFM preview beside the PNG: Middlebury's layout, little-endian float32 rows bottom first, inf = none
    raw = (out / "previews" / "0.png.depth.pfm").read_bytes()
    header = b"Pf\n320 240\n-1\n"
    assert raw[: len(header)] == header and len(raw) == len(header) + 320 * 240 * 4
    values = np.frombuffer(raw[len(header):], "<f4").reshape(240, 320)[::-1]
    assert np.array_equal(values, np.where(depth > 0, depth, np.inf))
    assert (out / "previews" / "0.png.depth.png").is_file()
    normals = read_colmap_array(out / "stereo" / "normal_maps" / "0.png.geometric.bin")
    assert np.median(normals[depth > 0][:, 2]) < -0.99  # facing the camera
    points, colors = read_ply_points(out / "fused.ply")
    assert len(points) == summary.fused_points > 30000 and colors is not None
    assert np.mean(np.abs(points[:, 2] - DEPTH) <= 0.005 * DEPTH) > 0.95
    assert (out / "mesh.ply").is_file() and summary.mesh_triangles > 1000
    assert (out / "sparse" / "cameras.bin").is_file() and (out / "images" / "0.png").is_file()
    # a rerun reuses every depth map
    again = run_dense(model, images, out, workers=1, views=4, settings=settings)
    assert again.views == summary.views and again.fused_points == summary.fused_points


def test_a_folder_without_a_model_is_refused(tmp_path):
    with pytest.raises(InputError, match="no COLMAP model"):
        run_dense(tmp_path, tmp_path, tmp_path / "dense")


def test_the_command_refuses_a_folder_without_a_run_or_model(tmp_path, capsys):
    from mvrecon.cli import main

    assert main(["-q", "dense", str(tmp_path / "missing")]) == 2
    assert "missing: no such run folder" in capsys.readouterr().err
    assert main(["-q", "dense", str(tmp_path)]) == 2
    assert f"{tmp_path / 'sparse' / '0'}: no sparse model here" in capsys.readouterr().err


def test_the_last_views_share_the_cores_the_finished_ones_leave():
    # 10 views, 2 worker processes on 2 cores: a core each until the last view, which takes both
    assert [view_threads(i, 10, 2, 2) for i in range(10)] == [1] * 9 + [2]
    # one view left to redo (a resumed run): the whole machine's cores; 3 views on 4 cores: 1, 2, then 4
    assert view_threads(0, 1, 1, 2) == 2
    assert [view_threads(i, 3, 3, 4) for i in range(3)] == [1, 2, 4]
