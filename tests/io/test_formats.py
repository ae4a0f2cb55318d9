"""PFM, PLY, the COLMAP database and models round-trip exactly; pycolmap reads and maps what we wrote."""

import sqlite3
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
    with pycolmap.Database.open(str(tmp_path / "syn.db")) as db:
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


def test_the_database_enumerations_are_pycolmaps():
    assert database.CAMERA_MODEL_IDS == {k: int(v.value) for k, v in pycolmap.CameraModelId.__members__.items()
                                         if k != "INVALID"}
    assert database.TWO_VIEW_CONFIGS == {m.name: int(m.value)
                                         for m in pycolmap.TwoViewGeometryConfiguration.__members__.values()}


def test_our_database_rows_are_the_ones_pycolmap_writes(tmp_path):
    """The same cameras, images, features, matches and geometries written with sqlite3 and with pycolmap give the
    same rows, the same schema and version stamp; a pair given larger image id first is stored COLMAP's way
    round (columns swapped, F and E transposed, H inverted), and an image without keypoints is stored as COLMAP
    stores it."""
    rng = np.random.default_rng(3)
    cameras = [database.CameraInfo(model="SIMPLE_RADIAL", width=640, height=480,
                                   params=np.array([500.0, 320, 240, 0.01])),
               database.CameraInfo(model="OPENCV", width=320, height=240, params=rng.random(8), prior_trusted=True)]
    images = [("a.png", 1), ("b.png", 1), ("c.png", 2)]
    features = {1: rng.random((7, 4)) * 100, 2: np.zeros((0, 4)), 3: rng.random((5, 4)) * 100}
    descriptors = {i: rng.integers(0, 256, (len(k), 128)).astype(np.uint8) for i, k in features.items()}
    F, E, H = (rng.normal(size=(3, 3)) for _ in range(3))
    pairs = [database.PairGeometry(image_id1=3, image_id2=1, config="CALIBRATED",
                                   inliers=np.array([[0, 6], [4, 2]]), F=F, E=E, H=H),
             database.PairGeometry(image_id1=2, image_id2=3, config="DEGENERATE", inliers=np.zeros((0, 2), int))]
    with database.open_database(tmp_path / "ours.db") as db:
        for cam in cameras:
            database.write_camera(db, cam)
        for name, cam in images:
            database.write_image(db, name, cam)
        for i, kp in features.items():
            database.write_features(db, i, kp, descriptors[i])
        for p in pairs:
            database.write_matches(db, p.image_id1, p.image_id2, p.inliers)
            database.write_two_view_geometry(db, p)
    with pycolmap.Database.open(str(tmp_path / "theirs.db")) as db:
        for cam in cameras:
            db.write_camera(pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=cam.params,
                                            has_prior_focal_length=cam.prior_trusted))
        for name, cam in images:
            db.write_image(pycolmap.Image(name=name, camera_id=cam))
        for i, kp in features.items():
            db.write_keypoints(i, kp.astype(np.float32))
            db.write_descriptors(i, pycolmap.FeatureDescriptors(type=pycolmap.FeatureExtractorType.SIFT,
                                                                data=descriptors[i]))
        for p in pairs:
            db.write_matches(p.image_id1, p.image_id2, p.inliers.astype(np.uint32))
            matrices = {k: getattr(p, k) for k in "FEH" if getattr(p, k) is not None}
            db.write_two_view_geometry(p.image_id1, p.image_id2, pycolmap.TwoViewGeometry(
                config=database.TWO_VIEW_CONFIGS[p.config], inlier_matches=p.inliers.astype(np.uint32), **matrices))
    ours, theirs = sqlite3.connect(tmp_path / "ours.db"), sqlite3.connect(tmp_path / "theirs.db")
    for query in ("PRAGMA user_version", "PRAGMA journal_mode"):
        assert ours.execute(query).fetchall() == theirs.execute(query).fetchall()
    tables = [t for (t,) in theirs.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
    assert tables == [t for (t,) in ours.execute(
        "SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
    for table in tables:
        columns = [c[1:] for c in theirs.execute(f'PRAGMA table_info("{table}")')]
        assert [c[1:] for c in ours.execute(f'PRAGMA table_info("{table}")')] == columns, table
        a, b = (con.execute(f'SELECT * FROM "{table}" ORDER BY 1').fetchall() for con in (ours, theirs))
        if table == "two_view_geometries":  # H inverted by numpy and by Eigen: equal to rounding
            h = [c[0] for c in columns].index("H")
            for ra, rb in zip(a, b):
                assert (ra[h] is None) == (rb[h] is None)
                if ra[h] is not None:
                    np.testing.assert_allclose(np.frombuffer(ra[h]), np.frombuffer(rb[h]), rtol=1e-12)
            a, b = [r[:h] + r[h + 1:] for r in a], [r[:h] + r[h + 1:] for r in b]
        assert a == b, table
    assert len(b) == 2 and b[0][0] == database.pair_id(1, 3) and database.pair_images(b[0][0]) == (1, 3)


def _small_model():
    """A model of our own: a SIMPLE_RADIAL and an OPENCV camera (a PINHOLE one only unregistered images use),
    images registered out of id order and two never registered, noisy keypoints with and without points,
    tracks of two to four views, a removed observation and a deleted point."""
    from mvrecon.sfm.model import Camera, Reconstruction

    rng = np.random.default_rng(7)
    cams = {1: Camera("SIMPLE_RADIAL", 640, 480, np.array([600.0, 320.0, 240.0, 0.02])),
            2: Camera("OPENCV", 800, 600, np.array([700.0, 710.0, 400.0, 300.0, 0.01, -0.02, 0.001, 0.002])),
            5: Camera("PINHOLE", 320, 240, np.array([300.0, 300.0, 160.0, 120.0]))}
    ids, cam_of = [3, 1, 7, 4, 9, 2, 6], [1, 2, 1, 2, 5, 5, 1]
    names = ["a.png", "photo 2.png", "sub/c.png", "d.png", "e.png", "f.png", "g.png"]
    keypoints = [rng.uniform(20, 300, (int(n), 2)) for n in rng.integers(40, 60, len(ids))]
    model = Reconstruction(ids, names, cam_of, cams, keypoints, num_tracks=200)
    for i in (2, 0, 3, 1, 6):  # registered; images 4 and 5 are not
        a = 0.4 * i - 1.0
        R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
        model.register(i, R, np.array([0.1 * i, -0.2, 5.0]))
    xyz = rng.normal(0, 0.7, (40, 3))
    images = [rng.choice([2, 0, 3, 1, 6], size=2 + k % 3, replace=False) for k in range(len(xyz))]
    local = np.repeat(np.arange(len(xyz)), [len(v) for v in images])
    obs_image = np.concatenate(images)
    used = {i: iter(rng.permutation(len(keypoints[i]))) for i in range(len(ids))}
    obs_kp = np.array([next(used[i]) for i in obs_image])
    uv, _ = model.project(obs_image, xyz[local])
    for i, k, p in zip(obs_image, obs_kp, uv):  # observed where they project, up to noise
        model.keypoints[i][k] = p + rng.normal(0, 0.5, 2)
    pids = model.add_points(xyz, np.arange(len(xyz)), local, obs_image, obs_kp)
    model.remove_observations(model.observations_of_points(pids[[2]])[:1])  # four views -> three
    model.delete_points(pids[[5]])
    colors = {}
    for i, name in enumerate(names):
        c = rng.uniform(0, 255, (len(keypoints[i]), 3)).astype(np.float32)
        c[::7] = np.nan  # keypoints at the border have no colour
        colors[name] = c
    return model, colors


def _pycolmap_model(model, colors):
    """The model as the writer before this one built it for pycolmap to write: the reference of the bytes."""
    rec = pycolmap.Reconstruction()
    for cid in np.unique(model.camera_of[model.registered]):
        cam = model.cameras[int(cid)]
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height,
                                                        params=cam.params, camera_id=int(cid)))
    for i in model.registration_order:
        image = pycolmap.Image(name=model.names[i], keypoints=model.keypoints[i],
                               camera_id=int(model.camera_of[i]), image_id=int(model.image_ids[i]))
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(model.R[i]), model.t[i]))
    obs = model.alive_observations()
    for p in np.unique(model.obs_point.data[obs]):
        track = pycolmap.Track()
        for o in obs[model.obs_point.data[obs] == p]:
            track.add_element(int(model.image_ids[model.obs_image.data[o]]), int(model.obs_kp.data[o]))
        rec.add_point3D(model.xyz.data[p], track, colors[p])
    rec.update_point_3d_errors()
    return rec


_BIN = ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin")


def _image_records(path) -> dict:
    """images.bin's records by image id (pycolmap writes a model it read back in id order, not ours)."""
    data, out, at = path.read_bytes(), {}, 8
    for _ in range(int(np.frombuffer(data[:8], "<u8")[0])):
        end = data.index(b"\0", at + 64) + 1
        end += 8 + 24 * int(np.frombuffer(data[end:end + 8], "<u8")[0])
        out[int(np.frombuffer(data[at:at + 4], "<u4")[0])] = data[at:end]
        at = end
    assert at == len(data)
    return out


def test_written_model_is_what_pycolmap_writes_and_reads(tmp_path, caplog):
    from mvrecon.io.colmap_model import point_colors, warn_text_names, write_models, write_points_ply

    model, keypoint_colors = _small_model()
    written = write_models([model], tmp_path / "sparse", keypoint_colors=keypoint_colors)
    ours = tmp_path / "sparse" / "0"
    rgb = point_colors(model, keypoint_colors)
    # the bytes: those pycolmap wrote for the same model built through its API
    _pycolmap_model(model, rgb).write_binary(str(tmp_path))
    for name in _BIN:
        assert (ours / name).read_bytes() == (tmp_path / name).read_bytes(), name
    # what pycolmap reads back
    rec = pycolmap.Reconstruction(str(ours))
    reg = model.registration_order
    assert sorted(rec.cameras) == [1, 2] and rec.num_rigs() == 2 and rec.num_frames() == len(reg) == 5
    for cid, cam in rec.cameras.items():
        ref = model.cameras[cid]
        assert (cam.model.name, cam.width, cam.height) == (ref.model, ref.width, ref.height)
        np.testing.assert_array_equal(cam.params, ref.params)
    assert sorted(rec.reg_image_ids()) == sorted(model.image_ids[reg]) and rec.num_images() == len(reg)
    for i in reg:
        im = rec.images[int(model.image_ids[i])]
        assert (im.name, im.camera_id) == (model.names[i], model.camera_of[i])
        np.testing.assert_allclose(im.cam_from_world().rotation.matrix(), model.R[i], atol=1e-12)
        np.testing.assert_array_equal(im.cam_from_world().translation, model.t[i])
        np.testing.assert_array_equal([p.xy for p in im.points2D], model.keypoints[i])
    obs = model.alive_observations()
    alive = np.unique(model.obs_point.data[obs])
    assert sorted(rec.points3D) == list(range(1, len(alive) + 1)) and len(alive) == 39
    lengths = set()
    for pid, p in zip(range(1, len(alive) + 1), alive):
        point = rec.points3D[pid]
        np.testing.assert_array_equal(point.xyz, model.xyz.data[p])
        np.testing.assert_array_equal(point.color, rgb[p])
        mine = obs[model.obs_point.data[obs] == p]
        track = [(e.image_id, e.point2D_idx) for e in point.track.elements]
        assert track == list(zip(model.image_ids[model.obs_image.data[mine]], model.obs_kp.data[mine]))
        errors = model.reprojection_errors(mine)[0]
        assert point.error == pytest.approx(errors.mean(), rel=1e-9)
        assert all(rec.images[a].points2D[b].point3D_id == pid for a, b in track)
        lengths.add(len(track))
    assert lengths == {2, 3, 4}
    assert sum(im.num_points3D for im in rec.images.values()) == len(obs)
    # pycolmap writes what it read in the same bytes (the images by id: it sorts them when reading)
    again = tmp_path / "again"
    again.mkdir()
    rec.write_binary(str(again))
    for name in _BIN:
        if name == "images.bin":
            assert _image_records(again / name) == _image_records(ours / name)
        else:
            assert (again / name).read_bytes() == (ours / name).read_bytes(), name
    # what write_models hands back, for points.ply and the text-name warning
    assert written[0].names == [model.names[i] for i in reg]
    np.testing.assert_array_equal(written[0].xyz, model.xyz.data[alive])
    np.testing.assert_array_equal(written[0].rgb, rgb[alive])
    assert write_points_ply(written[0], tmp_path / "p.ply") == 39
    p2, c2 = read_ply_points(tmp_path / "p.ply")
    np.testing.assert_allclose(p2, model.xyz.data[alive])
    np.testing.assert_array_equal(c2, rgb[alive])
    with caplog.at_level("WARNING", logger="mvrecon.io"):
        warn_text_names([w.names for w in written], tmp_path / "sparse")
    assert len(caplog.records) == 1 and "'photo 2.png'" in caplog.records[0].getMessage()


def test_writing_a_model_does_not_load_pycolmap(tmp_path):
    """pycolmap's import took 110 ms of CPU in every run; only --text needs it."""
    import pickle
    import subprocess
    import sys

    model, colors = _small_model()
    with open(tmp_path / "model.pkl", "wb") as f:
        pickle.dump((model.state(), model.keypoints, colors), f)
    script = ("import pickle, sys\n"
              "from mvrecon.io.colmap_model import write_models\n"
              "from mvrecon.sfm.model import Reconstruction\n"
              "state, keypoints, colors = pickle.load(open(sys.argv[1], 'rb'))\n"
              "model = Reconstruction.from_state(state, keypoints)\n"
              "write_models([model], sys.argv[2], keypoint_colors=colors)\n"
              "print('pycolmap' in sys.modules)\n"
              "write_models([model], sys.argv[3], keypoint_colors=colors, text=True)\n"
              "print('pycolmap' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", script, str(tmp_path / "model.pkl"), str(tmp_path / "bin"),
                          str(tmp_path / "text")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "True"]
    for name in _BIN:
        assert (tmp_path / "bin" / "0" / name).read_bytes() == (tmp_path / "text" / "0" / name).read_bytes()
    assert pycolmap.Reconstruction(str(tmp_path / "text" / "0")).num_points3D() == 39
    assert (tmp_path / "text" / "0" / "points3D.txt").is_file()


def test_quaternions_are_pycolmaps_to_the_bit():
    """The poses in images.bin and frames.bin are Eigen's quaternions of our rotation matrices; one addition in
    another order changed the last bit of 4% of these."""
    from mvrecon.geometry.rotation import eigen_quaternions

    q, r = np.linalg.qr(np.random.default_rng(3).normal(size=(3000, 3, 3)))
    R = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    R[np.linalg.det(R) < 0] *= -1
    ours = eigen_quaternions(R)
    theirs = np.array([pycolmap.Rotation3d(m).quat for m in R])[:, [3, 0, 1, 2]]
    assert (np.trace(R, axis1=1, axis2=2) < 0).sum() > 1000  # both of Eigen's branches
    np.testing.assert_array_equal(ours, theirs)


def test_keypoint_scales_read_from_both_colmap_layouts():
    """A keypoint's detection scale: our (N,4) rows carry it in column 3; COLMAP's (N,6) affine rows as the
    mean length of the frame's columns (a frame scaled by 3 and turned reads 3, a sheared one the mean)."""
    turned = 3.0 * np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]])
    six = np.array([[10.0, 20.0, *turned.ravel()], [1.0, 2.0, 2.0, 0.0, 0.0, 4.0]])
    assert np.allclose(database.keypoint_scales(six), [3.0, 3.0])
    four = np.array([[10.0, 20.0, 2.5, 0.3], [1.0, 2.0, 7.0, -1.0]])
    assert np.allclose(database.keypoint_scales(four), [2.5, 7.0])
    assert np.allclose(database.keypoint_scales(np.zeros((3, 2))), 0.0)
