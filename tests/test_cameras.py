"""Camera grouping and focal priors: EXIF focal lengths, the grouping modes, known intrinsics checked."""


import pytest
from PIL import Image

from mvrecon.cameras import CameraConfig, focal_prior, group_cameras, parse_camera_params
from mvrecon.errors import InputError
from mvrecon.io.images import image_metadata
from tests.helpers import pattern


def test_focal_priors_and_camera_grouping(tmp_path):
    sub = tmp_path / "left"
    sub.mkdir()
    Image.fromarray(pattern(60, 80)).save(tmp_path / "noexif.jpg")
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "Cam", "X1"
    exif.get_ifd(0x8769)[0xA405] = 28  # FocalLengthIn35mmFilm
    exif.get_ifd(0x8769)[0x920A] = 4.0  # FocalLength
    for name in ("a.jpg", "b.jpg", "left/c.jpg"):
        Image.fromarray(pattern(60, 80)).save(tmp_path / name, exif=exif)
    Image.fromarray(pattern(60, 80)).save(tmp_path / "plain.jpg")
    Image.fromarray(pattern(40, 80)).save(tmp_path / "small.jpg")
    names = ["a.jpg", "b.jpg", "noexif.jpg", "left/c.jpg", "plain.jpg", "small.jpg"]
    metas = {n: image_metadata(tmp_path / n) for n in names}
    assert metas["a.jpg"].focal_35mm == 28 and metas["a.jpg"].make == "Cam"
    assert focal_prior(metas["a.jpg"]) == (pytest.approx(28 / 36 * 80), True)
    assert focal_prior(metas["plain.jpg"]) == (pytest.approx(1.2 * 80), False)

    auto = group_cameras(names, metas, CameraConfig())
    assert sorted(sorted(m) for _, m in auto) == [["a.jpg", "b.jpg", "left/c.jpg"], ["noexif.jpg", "plain.jpg"],
                                                  ["small.jpg"]]
    exif_camera = next(c for c, m in auto if "a.jpg" in m)
    assert exif_camera.prior_trusted and exif_camera.params[0] == pytest.approx(28 / 36 * 80)
    folders = group_cameras(names[:5], metas, CameraConfig(mode="per-folder"))
    assert sorted(len(m) for _, m in folders) == [1, 4]
    assert len(group_cameras(names, metas, CameraConfig(mode="per-image"))) == 6
    with pytest.raises(InputError, match="needs images of one size"):
        group_cameras(names, metas, CameraConfig(mode="single"))
    known = group_cameras(names[:2], metas, CameraConfig(model="PINHOLE", params=parse_camera_params("50,51,40,30")))
    assert known[0][0].prior_trusted and list(known[0][0].params) == [50, 51, 40, 30]
    # known intrinsics of one size given to images of two: the other size's principal point would be off centre
    for mode in ("auto", "per-image"):
        with pytest.raises(InputError, match=r"^small.jpg: is 80x40 but a.jpg is 80x60, and --camera-params"):
            group_cameras(names, metas, CameraConfig(mode=mode, model="PINHOLE", params=(50, 51, 40, 30)))
    with pytest.raises(InputError, match="PINHOLE takes 4 parameters"):
        CameraConfig(model="PINHOLE", params=(1.0, 2.0)).validate()
