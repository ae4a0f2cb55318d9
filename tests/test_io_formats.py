"""PFM, PLY and the COLMAP database round-trip exactly; pycolmap maps a database we wrote."""

from dataclasses import replace

import numpy as np
import pycolmap
import pytest

from mvrecon import database
from mvrecon.io.pfm import read_pfm, write_pfm
from mvrecon.io.ply import read_ply_points, write_ply


def test_pfm_round_trip_keeps_inf(tmp_path):
    a = np.random.default_rng(0).random((7, 9)).astype(np.float32)
    a[2, 3] = np.inf
    write_pfm(tmp_path / "d.pfm", a)
    np.testing.assert_array_equal(read_pfm(tmp_path / "d.pfm"), a)
    (tmp_path / "bad.pfm").write_bytes(b"P6\n1 1\n255\n\0\0\0")
    with pytest.raises(ValueError, match="bad.pfm: not a PFM"):
        read_pfm(tmp_path / "bad.pfm")


def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    pts, cols = rng.normal(size=(50, 3)), rng.integers(0, 256, size=(50, 3)).astype(np.uint8)
    write_ply(tmp_path / "p.ply", pts, cols)
    p2, c2 = read_ply_points(tmp_path / "p.ply")
    np.testing.assert_allclose(p2, pts)
    np.testing.assert_array_equal(c2, cols)


def test_database_round_trip_and_pycolmap_maps_it(tmp_path):
    opts = pycolmap.SyntheticDatasetOptions(num_rigs=1, num_frames_per_rig=6, num_points3D=200,
                                            camera_width=640, camera_height=480,
                                            camera_params=[600.0, 320.0, 240.0, 0.0])
    with database.open_database(tmp_path / "syn.db") as db:
        pycolmap.synthesize_dataset(opts, db)
    src = database.read_correspondences(tmp_path / "syn.db")
    assert len(src.images) == 6 and len(src.pairs) == 15
    # the synthetic pairs carry F and E; give one an H too, so that all three matrices make the round trip
    src.pairs[0] = replace(src.pairs[0], H=np.arange(1.0, 10.0).reshape(3, 3))
    with database.open_database(tmp_path / "ours.db") as db:
        for cam in src.cameras.values():
            database.write_camera(db, cam)
        for im in src.images.values():
            new_id = database.write_image(db, im.name, im.camera_id)
            assert new_id == im.image_id
            kp = src.keypoints[im.image_id]
            database.write_features(db, new_id, np.c_[kp, np.ones(len(kp)), np.zeros(len(kp))],
                                    np.zeros((len(kp), 128), np.uint8))
        for pair in src.pairs:
            database.write_matches(db, pair.image_id1, pair.image_id2, pair.inliers)
            database.write_two_view_geometry(db, pair)
    back = database.read_correspondences(tmp_path / "ours.db")
    assert back.cameras.keys() == src.cameras.keys() and back.images == src.images
    for c, cam in src.cameras.items():
        got = back.cameras[c]
        assert (got.model, got.width, got.height, got.prior_trusted) == (cam.model, cam.width, cam.height,
                                                                         cam.prior_trusted)
        np.testing.assert_array_equal(got.params, cam.params)
    for i in src.keypoints:
        np.testing.assert_array_equal(back.keypoints[i], src.keypoints[i])
    assert [p.config for p in back.pairs] == [p.config for p in src.pairs]
    assert all(p.F is not None and p.E is not None for p in src.pairs)
    for a, b in zip(back.pairs, src.pairs):
        assert (a.image_id1, a.image_id2) == (b.image_id1, b.image_id2)
        np.testing.assert_array_equal(a.inliers, b.inliers)
        for name in ("F", "E", "H"):
            ma, mb = getattr(a, name), getattr(b, name)
            assert (ma is None) == (mb is None), name
            if mb is not None:
                np.testing.assert_array_equal(ma, mb)
    (tmp_path / "sparse").mkdir()
    models = pycolmap.incremental_mapping(str(tmp_path / "ours.db"), str(tmp_path), str(tmp_path / "sparse"))
    assert max(m.num_reg_images() for m in models.values()) == 6
