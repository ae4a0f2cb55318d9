"""The matching stage's pair selection from the images themselves: GPS positions read from the EXIF of the
images the features came from, `auto` resolved and recorded as what it chose."""

import shutil

import numpy as np
from PIL import Image

from mvrecon import database as dbmod
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.io.gps import from_enu, gps_exif
from mvrecon.stages.common import FrontendConfig
from mvrecon.stages.features import extract_features
from mvrecon.stages.matching import match
from mvrecon.workspace import Workspace


def test_spatial_pairs_come_from_the_gps_in_the_images(object_orbit_small, tmp_path):
    gt = load_ground_truth(object_orbit_small / "gt" / "sparse")
    names = sorted(gt)
    centres = {n: -gt[n][0].T @ gt[n][1] for n in names}  # camera centres in metres
    images = tmp_path / "images"
    images.mkdir()
    origin = np.array([46.5, 6.6, 500.0])
    for name in names:  # JPEG copies carrying each view's true position
        lla = from_enu((centres[name] * 10.0)[None], origin)[0]  # a 10x larger orbit: GPS keeps 3 mm
        with Image.open(object_orbit_small / "images" / name) as im:
            im.convert("RGB").save(images / name.replace(".png", ".jpg"), quality=95, exif=gps_exif(*lla))
    shutil.copy(images / "0005.jpg", images / "0005-nogps.jpg")
    with Image.open(images / "0005-nogps.jpg") as im:
        im.save(images / "0005-nogps.jpg", quality=95)  # the same view, without EXIF
    config = FrontendConfig(workers=1, pairs="spatial:2")
    extract_features(config, images, tmp_path / "ws")
    summary = match(config, tmp_path / "ws")
    assert summary.strategy == "spatial:2" and summary.strategy_reason == "given"
    jpgs = {n.replace(".png", ".jpg"): c for n, c in centres.items()}
    expected = set()
    for a, ca in jpgs.items():
        nearest = sorted(jpgs, key=lambda b: (np.linalg.norm(jpgs[b] - ca) if b != a else np.inf, b))[:2]
        expected |= {tuple(sorted((a, b))) for b in nearest}
    # the copy without a position is paired by retrieval: with the view it copies, and one other
    with_copy = {p for p in summary_pairs(tmp_path / "ws") if "0005-nogps.jpg" in p}
    assert summary_pairs(tmp_path / "ws") - with_copy == expected and len(with_copy) == 2
    assert ("0005-nogps.jpg", "0005.jpg") in with_copy
    # auto on 11 images matches every pair, and is recorded as the exhaustive matching it chose
    auto = match(FrontendConfig(workers=1), tmp_path / "ws", overwrite=True)
    assert auto.strategy == "exhaustive" and auto.num_pairs == 55 and "11 images, fewer than" in auto.text()
    assert Workspace(tmp_path / "ws").stage_config("matching")["pairs"] == "exhaustive"


def summary_pairs(workspace) -> set[tuple[str, str]]:
    """The pairs the workspace's matching matched (each has a two-view geometry, verified or not), by name."""
    with dbmod.open_database(workspace / "database.db") as db:
        names = {i.image_id: i.name for i in dbmod.read_images(db).values()}
        ids = sorted(names)
        return {tuple(sorted((names[i], names[j]))) for k, i in enumerate(ids) for j in ids[k + 1:]
                if dbmod.has_two_view_geometry(db, i, j)}
