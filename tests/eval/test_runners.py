"""COLMAP's own runs with its sequential and spatial matching (`RunOptions.colmap_matching`): the pairs it
examines are those the mode promises, and the option only counts for COLMAP's own runs."""

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mvrecon.errors import InputError
from mvrecon.eval.runners import RunOptions, run_colmap
from mvrecon.io.gps import from_enu, gps_exif

ORIGIN = np.array([47.3769, 8.5417, 420.0])


def views_with_gps(folder: Path, east_m: list[float]) -> Path:
    """Small JPEGs of one texture, each with a GPS position `east_m` metres east of ORIGIN."""
    rng = np.random.default_rng(0)
    texture = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
    folder.mkdir(parents=True)
    positions = from_enu(np.array([[e, 0.0, 50.0] for e in east_m]), ORIGIN)
    for k, (lat, lon, alt) in enumerate(positions):
        Image.fromarray(texture).save(folder / f"view{k:02d}.jpg", exif=gps_exif(lat, lon, alt))
    return folder


def examined_pairs(database: Path) -> set[tuple[str, str]]:
    """The image pairs the run matched (a row of the matches table each, with or without matches)."""
    with sqlite3.connect(database) as con:
        names = dict(con.execute("SELECT image_id, name FROM images"))
        ids = [row[0] for row in con.execute("SELECT pair_id FROM matches")]
    return {tuple(sorted((names[p // 2147483647], names[p % 2147483647]))) for p in ids}


def test_spatial_matching_pairs_images_near_by_their_exif_gps(tmp_path):
    # two groups 500 m apart: COLMAP's spatial pairs (up to 100 m) never join them
    images = views_with_gps(tmp_path / "images", [0.0, 10.0, 20.0, 500.0, 510.0])
    run = run_colmap(images, tmp_path / "spatial", RunOptions(camera_mode="single", colmap_matching="spatial"))
    assert run.error is None
    assert examined_pairs(run.out_dir / "database.db") == {
        ("view00.jpg", "view01.jpg"), ("view00.jpg", "view02.jpg"), ("view01.jpg", "view02.jpg"),
        ("view03.jpg", "view04.jpg")}


def test_sequential_matching_pairs_each_image_with_the_next_ones(tmp_path):
    images = views_with_gps(tmp_path / "images", [0.0] * 13)
    run = run_colmap(images, tmp_path / "sequential",
                     RunOptions(camera_mode="single", colmap_matching="sequential"))
    pairs = examined_pairs(run.out_dir / "database.db")
    assert {(f"view{k:02d}.jpg", f"view{k + 1:02d}.jpg") for k in range(12)} <= pairs
    assert ("view00.jpg", "view12.jpg") not in pairs  # 12 apart: beyond the 10 next and the 2, 4, 8 further
    assert len(pairs) < 13 * 12 // 2


def test_colmap_matching_is_checked_and_counts_only_for_colmaps_own_runs():
    with pytest.raises(InputError, match="COLMAP matching 'vocab'"):
        RunOptions(colmap_matching="vocab")
    spatial = RunOptions(colmap_matching="spatial")
    assert spatial.identity("colmap")["colmap_matching"] == "spatial"
    assert spatial.identity("mvrecon") == RunOptions().identity("mvrecon")
    assert "colmap_matching" not in RunOptions().identity("colmap")  # runs made before it keep their identity
