"""Reruns on a finished workspace: stale work is never reused (a mapper snapshot after the front end was redone,
an edited pairs file, a database without our record), good work is never destroyed (a refused camera setup, a
refused or failed re-map), and what a rerun is asked for is done or said (--text, point colours, the report)."""

import json
import logging
import shutil

import numpy as np
import pycolmap
import pytest
from PIL import Image

from mvrecon.cli import main
from mvrecon.io.ply import read_ply_points
from mvrecon.workspace import Workspace


@pytest.fixture(scope="module")
def base(object_orbit_small, tmp_path_factory):
    """object_orbit_small (10 views, 640x480) and a finished `reconstruct` of it (seed 0)."""
    root = tmp_path_factory.mktemp("orbit")
    images = object_orbit_small / "images"
    assert main(["-q", "reconstruct", str(images), "-o", str(root / "run")]) == 0
    assert (root / "run" / "snapshots" / "mapper.pkl").is_file()
    return images, root / "run"


def copy_run(base, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(base[1], ws)
    return base[0], ws


def camera_models(sparse_dir):
    return {c.model.name for c in pycolmap.Reconstruction(str(sparse_dir)).cameras.values()}


def test_redone_features_drop_the_mapper_snapshot(base, tmp_path):
    # the snapshot of the SIMPLE_RADIAL run was resumed after the features were redone with PINHOLE: the model
    # kept the old camera while database.db and the workspace's record said PINHOLE
    images, ws = copy_run(base, tmp_path)
    assert main(["-q", "reconstruct", str(images), "-o", str(ws), "--camera-model", "PINHOLE", "--overwrite",
                 "--resume"]) == 0
    assert camera_models(ws / "sparse" / "0") == {"PINHOLE"}
    # the staged commands: features --overwrite drops the snapshot, map --resume maps the new database
    shutil.rmtree(ws)
    images, ws = copy_run(base, tmp_path)
    assert main(["-q", "features", str(images), "-w", str(ws), "--camera-model", "PINHOLE", "--overwrite"]) == 0
    assert not (ws / "snapshots" / "mapper.pkl").exists()
    assert main(["-q", "match", "-w", str(ws)]) == 0
    assert main(["-q", "map", "-w", str(ws), "--resume"]) == 0
    assert camera_models(ws / "sparse" / "0") == {"PINHOLE"}


def test_the_snapshot_signature_covers_the_cameras(base):
    from mvrecon.database import read_correspondences
    from mvrecon.sfm.config import MapperConfig
    from mvrecon.sfm.incremental import _signature

    corr = read_correspondences(base[1] / "database.db")
    before = _signature(corr, MapperConfig())
    for cam in corr.cameras.values():  # same counts of everything, another camera
        cam.model, cam.params = "PINHOLE", np.array([*cam.params[:1], *cam.params[:3]])
    assert _signature(corr, MapperConfig()) != before


def test_a_refused_camera_setup_changes_nothing(base, tmp_path, capsys):
    # --camera-mode single on images of two sizes deleted database.db and report.json of the finished run and
    # recorded the refused config, so that the corrected command was refused on a fresh folder
    sizes = tmp_path / "sizes"
    shutil.copytree(base[0], sizes)
    for name in ("0000.png", "0005.png"):
        Image.open(sizes / name).resize((800, 600)).save(sizes / name)
    ws = tmp_path / "ws"
    assert main(["-q", "reconstruct", str(sizes), "-o", str(ws)]) == 0
    before = {p.name: p.read_bytes() for p in ws.iterdir() if p.is_file()}
    capsys.readouterr()
    assert main(["-q", "reconstruct", str(sizes), "-o", str(ws), "--camera-mode", "single", "--overwrite"]) == 2
    assert "needs images of one size" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in ws.iterdir() if p.is_file()} == before
    fresh = tmp_path / "fresh"
    assert main(["-q", "features", str(sizes), "-w", str(fresh), "--camera-mode", "single"]) == 2
    assert not Workspace(fresh).record_path.exists()
    assert main(["-q", "features", str(sizes), "-w", str(fresh)]) == 0


def test_changed_mapper_settings_are_refused_and_a_failed_remap_keeps_the_model(base, tmp_path, capsys):
    images, ws = copy_run(base, tmp_path)
    model = (ws / "sparse" / "0" / "images.bin").read_bytes()
    # --seed 1 silently replaced the seed-0 model. The workspace's stage check refuses it (the one check of
    # every stage), with the hint of the command that redoes only the mapping.
    hint = (f"rerun with --overwrite to map again (`mvrecon map -o {ws} --overwrite` redoes only the mapping), "
            "or use another workspace")
    assert main(["-q", "reconstruct", str(images), "-o", str(ws), "--seed", "1"]) == 2
    assert capsys.readouterr().err == (f"mvrecon: error: {ws}: made with a different mapping config "
                                       f"(seed: 0 -> 1); {hint}\n")
    assert (ws / "sparse" / "0" / "images.bin").read_bytes() == model
    assert json.loads((ws / "report.json").read_text())["seed"] == 0
    toml = tmp_path / "hi.toml"
    toml.write_text("[mapper]\ninit_min_inliers = 5000\nglobal_fallback = false\n")
    assert main(["-q", "map", "-w", str(ws), "--config", str(toml)]) == 2
    assert capsys.readouterr().err == (f"mvrecon: error: {ws}: made with a different mapping config "
                                       f"(global_fallback: True -> False; init_min_inliers: 100 -> 5000); {hint}\n")
    # with --overwrite the re-map runs and makes no model (the global mapper, which would map these views, is
    # switched off): the earlier model was deleted before that was known
    assert main(["-q", "map", "-w", str(ws), "--config", str(toml), "--overwrite"]) == 1
    assert (ws / "sparse" / "0" / "images.bin").read_bytes() == model and (ws / "points.ply").is_file()
    assert not (ws / "sparse.new").exists()


def test_a_database_without_our_record_is_refused(base, tmp_path, capsys):
    # reconstruct mapped the features and matches of a database it had no record of (COLMAP's, or one whose
    # record was lost) and recorded its own SIFT settings for them
    images, ws = copy_run(base, tmp_path)
    record = Workspace(ws).record_path
    record.unlink()
    database = (ws / "database.db").read_bytes()
    assert main(["-q", "reconstruct", str(images), "-o", str(ws)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "without mvrecon's record" in err and "mvrecon map -o" in err
    assert (ws / "database.db").read_bytes() == database and not record.exists()
    # mapped as advised, then started over: the mapping record of the foreign database is not kept (it stayed,
    # ahead of the new features, and refused a later `map` with other settings for a config never mapped)
    assert main(["-q", "map", "-w", str(ws)]) == 0
    assert list(json.loads(record.read_text())) == ["mapping"]
    assert main(["-q", "reconstruct", str(images), "-o", str(ws), "--overwrite"]) == 0
    assert list(json.loads(record.read_text())) == ["features", "matching", "mapping"]
    assert main(["-q", "map", "-w", str(ws), "--seed", "1"]) == 2  # refused against this run's own mapping
    assert "(seed: 0 -> 1)" in capsys.readouterr().err


def test_an_edited_pairs_file_is_a_different_matching_config(base, tmp_path, capsys):
    _, ws = copy_run(base, tmp_path)
    pairs = tmp_path / "pl.txt"
    pairs.write_text("0000.png 0001.png\n0001.png 0002.png\n")
    assert main(["-q", "match", "-w", str(ws), "--pairs", str(pairs), "--overwrite"]) == 0
    assert main(["-q", "match", "-w", str(ws), "--pairs", str(pairs)]) == 0  # unchanged: resumes
    pairs.write_text("0005.png 0006.png\n")
    capsys.readouterr()
    assert main(["-q", "match", "-w", str(ws), "--pairs", str(pairs)]) == 2
    assert "different matching config (pairs_file_sha256" in capsys.readouterr().err


def test_text_on_a_finished_run_writes_the_text_model(base, tmp_path):
    images, ws = copy_run(base, tmp_path)
    assert main(["-q", "reconstruct", str(images), "-o", str(ws), "--text"]) == 0
    text = pycolmap.Reconstruction(str(ws / "sparse" / "0"))  # reads the .bin: compare with the .txt
    assert (ws / "sparse" / "0" / "cameras.txt").is_file() and (ws / "sparse" / "0" / "points3D.txt").is_file()
    assert len((ws / "sparse" / "0" / "points3D.txt").read_text().splitlines()) >= text.num_points3D()


def test_map_colours_the_points_from_the_recorded_folder_or_says_why_not(base, tmp_path, caplog):
    images, ws = copy_run(base, tmp_path)
    assert main(["-q", "map", "-w", str(ws), "--overwrite"]) == 0
    _, rgb = read_ply_points(ws / "points.ply")
    assert rgb.any()  # was all black without --image-dir
    record = json.loads(Workspace(ws).record_path.read_text())
    record["features"]["config"]["images"] = str(tmp_path / "moved")
    Workspace(ws).record_path.write_text(json.dumps(record))
    with caplog.at_level(logging.WARNING):
        assert main(["-q", "map", "-w", str(ws), "--overwrite"]) == 0
    assert "point colours are not sampled" in caplog.text and "--image-dir" in caplog.text


def test_map_keeps_the_front_end_stages_in_the_report_and_says_whose_database(base, tmp_path):
    _, ws = copy_run(base, tmp_path)
    assert main(["-q", "map", "-w", str(ws), "--overwrite"]) == 0
    report = json.loads((ws / "report.json").read_text())
    assert {"features", "matching", "mapping"} <= set(report["stages"])
    assert report["database"]["made_by"] == "mvrecon"
