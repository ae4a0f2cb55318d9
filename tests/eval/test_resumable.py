"""COLMAP's reference runs go on where they were cut off: features and matches from the run's database, mapping
from its newest snapshot; each stage's time is counted once, and the result is that of a whole run."""

import json
import logging
import os
import shutil
import sqlite3

import pycolmap
import pytest

from mvrecon.eval import runners
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses
from mvrecon.eval.resumable import SnapshotSealer, StageProgress
from mvrecon.eval.runners import RunOptions, run_colmap
from tests.helpers import synthetic_scene

OPTIONS = RunOptions()  # auto cameras: one SINGLE-camera extraction per group, which a resumed one must join


def cameras_and_descriptors(db) -> tuple[set[int], dict[str, bytes]]:
    with sqlite3.connect(db) as con:
        cameras = {row[0] for row in con.execute("SELECT camera_id FROM images")}
        blobs = dict(con.execute("SELECT images.name, descriptors.data FROM images JOIN descriptors "
                                 "ON descriptors.image_id = images.image_id"))
    return cameras, blobs


def accuracy(models, gt_path) -> dict:
    return accuracy_summary([poses(m) for m in models], load_ground_truth(gt_path))


def test_a_colmap_run_cut_off_in_its_features_goes_on_with_one_camera_and_counts_each_stage_once(tmp_path):
    images, gt_path = synthetic_scene(tmp_path)
    out = tmp_path / "colmap"
    out.mkdir()
    names = sorted(p.name for p in images.iterdir())
    # the first attempt, killed after half its images: its heartbeat had counted the stage, which had not ended
    first = StageProgress(out)
    with first.stage("features"):
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = OPTIONS.camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.use_gpu = False
        pycolmap.extract_features(out / "database.db", images, image_names=names[:4],
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
    first.data["stages"]["features"]["done"] = False
    first._save()
    counted = first.data["stages"]["features"]["wall_s"]
    _, before = cameras_and_descriptors(out / "database.db")

    run = run_colmap(images, out, OPTIONS)

    assert run.error is None
    cameras, after = cameras_and_descriptors(out / "database.db")
    assert cameras == {1}  # the images extracted next joined the first attempt's camera
    assert set(after) == set(names) and all(after[n] == before[n] for n in before)  # none extracted again
    report = json.loads((out / "report.json").read_text())
    assert report["total"]["attempts"] == 2
    assert report["stages"]["features"]["wall_s"] > counted  # the first attempt's share, then the rest
    assert run.wall_s > counted  # the caller's wall time holds the earlier attempt's counted part
    summary = accuracy(run.models, gt_path)
    assert summary["registered"] == 8 and summary["auc@5"] > 0.9
    assert not (out / "snapshots").exists()  # a finished mapping leaves no snapshots behind


def test_a_snapshot_counts_as_whole_once_it_stays_the_same_between_two_checks(tmp_path):
    _, gt_path = synthetic_scene(tmp_path)
    folder = tmp_path / "snapshots"
    folder.mkdir()
    stale = folder / "100"  # an earlier attempt's, cut off while it was written: older than this attempt
    stale.mkdir()
    (stale / "points3D.bin").write_bytes(b"partial")
    os.utime(stale, (1000.0, 1000.0))
    sealer = SnapshotSealer(folder, since=2000.0)
    assert sealer.check() is None and sealer.check() is None
    first = folder / "200"
    shutil.copytree(gt_path, first)
    assert sealer.check() is None  # seen once: it may still be being written
    assert sealer.check() == first
    assert sealer.sealed_time == pytest.approx((first / "points3D.bin").stat().st_mtime, abs=1e-3)
    assert not stale.exists()  # the snapshots older than the sealed one are deleted
    second = folder / "300"
    second.mkdir()
    (second / "cameras.bin").write_bytes((first / "cameras.bin").read_bytes())
    assert sealer.check() is None and sealer.check() is None  # no points yet: never whole
    (second / "points3D.bin").write_bytes(b"half")
    assert sealer.check() is None  # changed since the last check
    assert sealer.sealed == first


def test_incremental_mapping_goes_on_from_a_snapshot(tmp_path, monkeypatch, caplog):
    images, gt_path = synthetic_scene(tmp_path)
    whole = run_colmap(images, tmp_path / "whole", OPTIONS)
    db = tmp_path / "database.db"
    db.write_bytes((whole.out_dir / "database.db").read_bytes())
    options = OPTIONS.identity("colmap")
    snapshots = tmp_path / "snapshots"
    monkeypatch.setattr(runners, "SNAPSHOT_FRAMES", 3)
    runners._map(db, images, tmp_path, options, False, snapshots)  # a snapshot every 3 images after the first pair
    written = sorted(snapshots.iterdir(), key=lambda p: p.stat().st_mtime)
    sizes = [pycolmap.Reconstruction(str(p)).num_reg_images() for p in written]
    assert len(sizes) == 2 and sizes[0] < sizes[1] == 8

    (tmp_path / "mapper-cut-off").mkdir()  # the scratch folder a killed attempt leaves behind
    with caplog.at_level(logging.INFO, logger="mvrecon.eval.runners"):
        models = runners._map(db, images, tmp_path, options, False, tmp_path / "again", start=written[0])

    assert f"resumes from the snapshot {written[0]}" in caplog.text
    assert not list(tmp_path.glob("mapper-*"))
    summary = accuracy(models, gt_path)
    assert summary["registered"] == 8 and summary["auc@5"] > 0.9
