"""--masks: no features where a mask is black, in COLMAP's layout (IMAGES/a.png -> MASKS/a.png.png), for mvrecon and,
in `compare`, for COLMAP too; masks drawn on an EXIF-rotated photo as stored are turned with it; a mask that does
not fit, a missing folder and a changed mask are refused in one line."""

import json
import logging

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image

from mvrecon.cli import main

W, H, CUT = 320, 240, 120  # masks black out x < CUT of the upright image


@pytest.fixture()
def photos(tmp_path):
    """Three views of one smooth random texture, shifted, and their masks (black left of CUT)."""
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 256, (40, 60), dtype=np.uint8), (480, 320), interpolation=cv2.INTER_CUBIC)
    images, masks = tmp_path / "images", tmp_path / "masks"
    images.mkdir()
    masks.mkdir()
    for k in range(3):
        cv2.imwrite(str(images / f"{k}.png"), texture[20:20 + H, 20 * k:20 * k + W])
        mask = np.full((H, W), 255, np.uint8)
        mask[:, :CUT] = 0
        cv2.imwrite(str(masks / f"{k}.png.png"), mask)
    return images, masks


def _keypoints(workspace):
    db = pycolmap.Database.open(str(workspace / "database.db"))
    try:
        return {im.name: np.asarray(db.read_keypoints(im.image_id))[:, :2] for im in db.read_all_images()}
    finally:
        db.close()


def test_masked_regions_have_no_keypoints_and_a_missing_mask_is_a_warning(photos, tmp_path, caplog):
    images, masks = photos
    (masks / "2.png.png").unlink()
    with caplog.at_level(logging.WARNING):
        assert main(["-q", "features", str(images), "-w", str(tmp_path / "ws"), "--masks", str(masks)]) == 0
    kp = _keypoints(tmp_path / "ws")
    assert all(len(kp[n]) > 50 and kp[n][:, 0].min() >= CUT for n in ("0.png", "1.png"))
    assert kp["2.png"][:, 0].min() < CUT / 2  # no mask: features everywhere
    assert "no mask for 1 of 3 images (2.png, looked for" in caplog.text
    # a mask that changed since is refused, and so is leaving the masks out
    cv2.imwrite(str(masks / "2.png.png"), np.full((H, W), 255, np.uint8))
    assert main(["-q", "features", str(images), "-w", str(tmp_path / "ws"), "--masks", str(masks)]) == 2
    assert main(["-q", "features", str(images), "-w", str(tmp_path / "ws")]) == 2


def test_a_mask_that_does_not_fit_or_a_missing_folder_is_one_line(photos, tmp_path, capsys):
    images, masks = photos
    cv2.imwrite(str(masks / "1.png.png"), np.zeros((10, 10), np.uint8))
    assert main(["-q", "features", str(images), "-w", str(tmp_path / "ws"), "--masks", str(masks)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{masks / '1.png.png'}: the mask is 10x10 but" in err
    assert not (tmp_path / "ws" / "database.db").exists()
    # compare checks the masks before either engine runs (COLMAP's run would be spent first)
    assert main(["-q", "compare", str(images), "-o", str(tmp_path / "cmp"), "--masks", str(masks)]) == 2
    assert f"{masks / '1.png.png'}: the mask is 10x10" in capsys.readouterr().err
    assert not (tmp_path / "cmp" / "runs").exists()
    assert main(["-q", "reconstruct", str(images), "-o", str(tmp_path / "out"), "--masks",
                 str(tmp_path / "nope")]) == 2
    assert "nope: no such folder (--masks)" in capsys.readouterr().err


def test_a_mask_of_an_exif_rotated_photo_is_turned_with_it(photos, tmp_path):
    """A photo stored on its side (EXIF orientation 6: turn 90 deg clockwise to view) with a mask drawn on the
    stored pixels, as COLMAP reads masks; mvrecon works upright, so the mask is turned as the photo is. The
    stored mask blacks out the top rows, which are the right columns once upright."""
    images, masks = photos
    upright = cv2.imread(str(images / "0.png"), cv2.IMREAD_GRAYSCALE)
    stored = np.ascontiguousarray(np.rot90(upright, 1))  # orientation 6 turns this back to `upright`
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(stored).save(images / "0.png", exif=exif)
    mask = np.full(stored.shape, 255, np.uint8)
    mask[:W - CUT] = 0  # the stored top rows: upright, the columns x >= CUT
    cv2.imwrite(str(masks / "0.png.png"), mask)
    assert main(["-q", "features", str(images), "-w", str(tmp_path / "ws"), "--masks", str(masks)]) == 0
    kp = _keypoints(tmp_path / "ws")["0.png"]
    assert len(kp) > 50 and kp[:, 0].max() <= CUT


def test_compare_gives_the_masks_to_colmap_too(photos, tmp_path):
    from mvrecon.eval.runners import RunOptions, run_colmap

    images, masks = photos
    run_colmap(images, tmp_path / "colmap", RunOptions(masks=str(masks)))
    kp = _keypoints(tmp_path / "colmap")
    assert len(kp) == 3 and all(len(k) > 50 and k[:, 0].min() >= CUT for k in kp.values())
    # runs made without masks keep their identity (no "masks" key), so they are not redone
    assert "masks" not in RunOptions().identity("colmap")
    assert json.loads(json.dumps(RunOptions(masks="m").identity("colmap")))["masks"] == "m"


def test_study_gives_the_masks_to_every_cell_but_not_to_smaller_copies(photos, tmp_path, capsys):
    images, masks = photos
    out = tmp_path / "study"
    assert main(["-q", "study", str(images), "-o", str(out), "--noise", "0,5", "--engines", "mvrecon",
                 "--masks", str(masks)]) == 0
    for cell in ("clean", "noise-5"):
        kp = _keypoints(out / "runs" / "mvrecon" / cell)
        assert len(kp) == 3 and all(len(k) > 50 and k[:, 0].min() >= CUT for k in kp.values())
    assert main(["-q", "study", str(images), "-o", str(tmp_path / "s2"), "--downscale", "1,2",
                 "--masks", str(masks)]) == 2
    assert "--masks with --downscale 1,2: the masks fit the clean images' size" in capsys.readouterr().err
