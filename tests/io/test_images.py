"""Images in: discovery, decoding, EXIF orientation, the grey conversion, truncated and odd files."""

import logging

import numpy as np
import pytest
from PIL import ExifTags, Image

from mvrecon.errors import InputError
from mvrecon.features.sift import SiftConfig, extract_sift
from mvrecon.io.images import image_metadata, list_images, read_image, to_gray, write_image
from tests.helpers import pattern


@pytest.mark.parametrize("orientation,expected", [
    (1, lambda a: a), (3, lambda a: np.rot90(a, 2)), (6, lambda a: np.rot90(a, -1)), (8, lambda a: np.rot90(a, 1)),
    (2, lambda a: a[:, ::-1]), (5, lambda a: np.swapaxes(a, 0, 1)),
])
def test_exif_orientation_is_applied(tmp_path, orientation, expected):
    stored = pattern()
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(stored).save(tmp_path / "a.png", exif=exif)
    image = read_image(tmp_path / "a.png")
    np.testing.assert_array_equal(image, expected(stored))
    meta = image_metadata(tmp_path / "a.png")
    assert (meta.width, meta.height) == (image.shape[1], image.shape[0])


def test_16_bit_grey_rgba_and_tiff_are_read(tmp_path):
    cv2 = pytest.importorskip("cv2")
    grey16 = (np.arange(60 * 80, dtype=np.uint16).reshape(60, 80) * 13)
    cv2.imwrite(str(tmp_path / "g16.png"), grey16)
    rgb16 = np.stack([grey16, grey16 // 2, grey16 // 3], axis=-1)
    cv2.imwrite(str(tmp_path / "c16.tif"), rgb16[:, :, ::-1])  # OpenCV writes BGR
    rgba = np.dstack([pattern(), np.full((60, 80), 7, np.uint8)])
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    Image.fromarray(pattern()[:, :, 0]).save(tmp_path / "grey.jpg", quality=100)

    a = read_image(tmp_path / "g16.png")
    assert a.dtype == np.uint16 and a.shape == (60, 80) and np.array_equal(a, grey16)
    b = read_image(tmp_path / "c16.tif")
    assert b.dtype == np.uint16 and np.array_equal(b, rgb16)
    c = read_image(tmp_path / "rgba.png")
    assert c.shape == (60, 80, 3) and np.array_equal(c, pattern())
    d = read_image(tmp_path / "grey.jpg")
    assert d.shape == (60, 80) and d.dtype == np.uint8
    names, skipped = list_images(tmp_path)
    assert names == ["c16.tif", "g16.png", "grey.jpg", "rgba.png"] and not skipped


def test_one_grey_conversion_in_8_bits_and_in_float():
    """to_gray's two forms weigh the channels alike (BT.601): the 8-bit grey is the float one rounded, within
    OpenCV's fixed-point rounding; 16-bit data is stretched to the full 8 bits; alpha is ignored."""
    rgb = np.random.default_rng(3).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    exact = rgb.astype(np.float64) @ [0.299, 0.587, 0.114]
    assert np.abs(to_gray(rgb, np.float32) - exact).max() < 1e-3
    assert np.abs(to_gray(rgb).astype(np.float64) - exact).max() <= 0.51
    assert np.array_equal(to_gray(np.dstack([rgb, np.zeros((40, 50), np.uint8)])), to_gray(rgb))
    deep = to_gray(rgb.astype(np.uint16) * 4)  # 10-bit data in 16 bits: stretched by the maximum of its grey
    stretched = exact * 255 / exact.max()
    assert deep.dtype == np.uint8 and deep.max() == 255 and np.abs(deep - stretched).max() <= 1
    with pytest.raises(ValueError):
        to_gray(rgb, np.float64)


def test_listing_is_recursive_and_reports_non_images_and_corrupt_files(tmp_path, caplog):
    (tmp_path / "sub" / "deeper").mkdir(parents=True)
    Image.fromarray(pattern()).save(tmp_path / "b.jpg")
    Image.fromarray(pattern()).save(tmp_path / "sub" / "deeper" / "a.PNG")
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / "sub" / "calib.yml").write_text("k: 1")
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg at all")
    with caplog.at_level(logging.WARNING):
        names, skipped = list_images(tmp_path)
    assert names == ["b.jpg", "sub/deeper/a.PNG"]
    assert set(skipped) == {"notes.txt", "sub/calib.yml", "broken.jpg"}
    non_image_warnings = [r for r in caplog.records if "non-image" in r.getMessage()]
    assert len(non_image_warnings) == 1 and "notes.txt" in non_image_warnings[0].getMessage()
    assert any("broken.jpg" in r.getMessage() for r in caplog.records)
    # outputs written inside the image folder (a workspace, an export, a scene, degraded copies) are not read back
    for out, mark in (("run", "database.db"), ("run/splat", "sparse"), ("scene", "scene.json"),
                      ("noisy", ".mvrecon-degrade.json")):
        (tmp_path / out / "images").mkdir(parents=True)
        Image.fromarray(pattern()).save(tmp_path / out / "images" / "c.png")
        (tmp_path / out / mark).touch()
    assert list_images(tmp_path)[0] == ["b.jpg", "sub/deeper/a.PNG"]
    (tmp_path / "scene" / "scene.json").unlink()  # an ordinary sub-folder again
    assert list_images(tmp_path)[0] == ["b.jpg", "scene/images/c.png", "sub/deeper/a.PNG"]


def test_bmp_and_pnm_are_read_and_cut_off_ones_skipped(tmp_path, caplog):
    """BMP and PGM/PPM, which COLMAP reads too: whole files are listed and decode as the PNG does; files cut off
    before their last row are skipped by name (OpenCV decodes a short BMP without an error)."""
    import cv2

    rgb = pattern()
    cv2.imwrite(str(tmp_path / "a.bmp"), rgb[:, :, ::-1])
    cv2.imwrite(str(tmp_path / "b.ppm"), rgb[:, :, ::-1])
    grey16 = pattern()[:, :, 2].astype(np.uint16) * 257
    cv2.imwrite(str(tmp_path / "c.pgm"), grey16)
    for name in ("a.bmp", "c.pgm"):
        data = (tmp_path / name).read_bytes()
        (tmp_path / f"cut_{name}").write_bytes(data[:len(data) * 2 // 3])
    with caplog.at_level(logging.WARNING):
        names, skipped = list_images(tmp_path)
    assert names == ["a.bmp", "b.ppm", "c.pgm"]
    assert set(skipped) == {"cut_a.bmp", "cut_c.pgm"} and all("truncated" in r for r in skipped.values())
    assert np.array_equal(read_image(tmp_path / "a.bmp"), rgb) and np.array_equal(read_image(tmp_path / "b.ppm"), rgb)
    assert read_image(tmp_path / "c.pgm").dtype == np.uint16 and np.array_equal(read_image(tmp_path / "c.pgm"), grey16)


def _png_header_only(path, width, height):
    """A valid PNG whose header claims `width` x `height` grey pixels, with one short row of data: enough for
    every check that reads headers and chunk CRCs, without making gigabytes."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 9))
                     + chunk(b"IEND", b""))


def test_photos_over_pillows_bomb_limit_are_read_and_shrunk_for_sift(tmp_path, caplog):
    """Pillow refuses images over 179 megapixels as "decompression bombs", so a stitched panorama or a 200 MP
    photo was skipped with that message; COLMAP reads them. They are read now (SIFT works on them shrunk to
    max_image_size, keypoints in the file's pixels); only what OpenCV cannot decode (over 2^30 pixels) is skipped,
    saying so."""
    import cv2

    big = np.full((13400, 13500), 200, np.uint8)  # 180.9 megapixels
    centres = [(2000, 3000), (9000, 7000), (12000, 11000)]  # (x, y) of dark blobs, 400 px across
    for x, y in centres:
        cv2.circle(big, (x, y), 200, 20, -1)
    cv2.imwrite(str(tmp_path / "big.png"), big, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    del big
    _png_header_only(tmp_path / "giant.png", 40000, 30000)
    with caplog.at_level(logging.WARNING):
        names, skipped = list_images(tmp_path)
    assert names == ["big.png"] and list(skipped) == ["giant.png"]
    assert "too large to decode (40000x30000, 1200 megapixels" in skipped["giant.png"]
    assert not [r for r in caplog.records if "DecompressionBomb" in r.getMessage()]
    image = read_image(tmp_path / "big.png")
    assert image.shape == (13400, 13500)
    keypoints, _ = extract_sift(image, SiftConfig(max_image_size=3200))
    for x, y in centres:  # each blob found where it is in the full-size image (a shrunk pixel is 4.2 px)
        assert np.min(np.hypot(keypoints[:, 0] - x, keypoints[:, 1] - y)) < 10


def test_images_are_written_and_read_in_a_folder_whose_name_is_not_utf8(tmp_path):
    """OpenCV's imwrite and imread crash the process (SIGSEGV) on such a path: a study's contact sheet, a
    stereo run's rectified images and a degraded 16-bit colour TIFF went through them. They go through bytes."""
    import os

    folder = tmp_path / os.fsdecode(b"r\xe9sultats")
    folder.mkdir()
    rgb16 = pattern().astype(np.uint16) * 257
    for suffix in (".png", ".tif"):
        write_image(folder / f"a{suffix}", rgb16[:, :, ::-1])
        back = read_image(folder / f"a{suffix}")
        assert back.dtype == np.uint16 and np.array_equal(back, rgb16)


def test_links_are_followed_but_a_loop_of_links_is_read_once(tmp_path, caplog):
    """A link back up the tree (`ln -s .. up`) made the listing walk the loop until the path grew too long:
    `features` ran for over a minute on 4 images. Each folder is now read once, by its first path."""
    (tmp_path / "photos" / "day1").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    Image.fromarray(pattern()).save(tmp_path / "photos" / "day1" / "a.png")
    Image.fromarray(pattern()).save(tmp_path / "elsewhere" / "b.png")
    (tmp_path / "photos" / "day1" / "up").symlink_to("..")
    (tmp_path / "photos" / "again").symlink_to("day1")
    (tmp_path / "photos" / "day2").symlink_to(tmp_path / "elsewhere")  # an ordinary link: followed
    with caplog.at_level(logging.WARNING):
        names, _ = list_images(tmp_path / "photos")
    assert names == ["day1/a.png", "day2/b.png"]
    warned = sorted(r.getMessage() for r in caplog.records if "read already" in r.getMessage())
    assert len(warned) == 2 and "photos/again: the same folder as" in warned[0] and "photos/day1/up: the same " \
        "folder as" in warned[1]


def test_a_broken_link_or_a_pipe_named_as_an_image_is_named_in_a_warning(tmp_path, caplog):
    """They were left out without a word, so an image was missing from the run with no reason given (a pipe
    is never opened: reading one would wait for ever)."""
    import os

    Image.fromarray(pattern()).save(tmp_path / "a.png")
    (tmp_path / "b.png").symlink_to(tmp_path / "moved" / "b.png")
    os.mkfifo(tmp_path / "c.jpg")
    (tmp_path / "notes").symlink_to(tmp_path / "gone.txt")  # not named as an image: not worth a line
    with caplog.at_level(logging.WARNING):
        names, _ = list_images(tmp_path)
    assert names == ["a.png"]
    warned = sorted(r.getMessage() for r in caplog.records)
    assert warned == [f"skipping {tmp_path}/b.png: a link to {tmp_path}/moved/b.png, which does not exist",
                      f"skipping {tmp_path}/c.jpg: not a regular file (a pipe, socket or device)"]


def test_bad_folders_raise_input_errors(tmp_path):
    with pytest.raises(InputError, match="no such folder"):
        list_images(tmp_path / "missing")
    with pytest.raises(InputError, match="no readable JPEG, PNG, TIFF, BMP or PNM"):
        list_images(tmp_path)
    (tmp_path / "x.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(InputError, match="cannot decode image"):
        read_image(tmp_path / "x.png")


TRUNCATED = "truncated JPEG: the file ends before its end-of-image marker"


def _texture(h=240, w=320, seed=0):
    """Smooth random RGB texture: enough entropy-coded data that a cut falls well inside the pixels."""
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(seed)
    return cv2.resize(rng.integers(0, 256, (h // 10, w // 10, 3), dtype=np.uint8), (w, h),
                      interpolation=cv2.INTER_CUBIC)


def _exif_with_thumbnail(thumbnail: bytes, orientation: int) -> bytes:
    """An APP1 EXIF block as cameras write it: IFD0 (orientation), then IFD1 pointing at a JPEG thumbnail, which
    brings its own SOI and EOI markers into the main image's header."""
    import struct

    ifd1 = 8 + 2 + 12 + 4
    data = ifd1 + 2 + 2 * 12 + 4
    tiff = b"II*\x00" + struct.pack("<I", 8)
    tiff += struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack("<I", ifd1)
    tiff += struct.pack("<H", 2) + struct.pack("<HHII", 0x0201, 4, 1, data)
    tiff += struct.pack("<HHII", 0x0202, 4, 1, len(thumbnail)) + struct.pack("<I", 0)
    return b"Exif\x00\x00" + tiff + thumbnail


@pytest.mark.parametrize("kind", ["baseline", "progressive", "restart-markers"])
def test_cut_off_jpegs_are_skipped_as_truncated(tmp_path, kind, caplog):
    """An interrupted copy keeps the JPEG header, so the EXIF walk passed it, and OpenCV decoded it with its
    missing part grey. Every cut, from 60% of the bytes to all but the last one, is reported and skipped."""
    cv2 = pytest.importorskip("cv2")
    from mvrecon.io.images import image_problem

    image = _texture()
    if kind == "restart-markers":  # RSTn markers inside the scan must not end it
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_RST_INTERVAL, 4])
        data = data.tobytes()
        assert ok and b"\xff\xd3" in data
    else:
        import io

        buffer = io.BytesIO()
        Image.fromarray(image).save(buffer, "JPEG", quality=90, progressive=kind == "progressive")
        data = buffer.getvalue()
        assert data.count(b"\xff\xda") == (1 if kind == "baseline" else 10)  # one scan, or ten
    (tmp_path / "whole.jpg").write_bytes(data)
    (tmp_path / "other.png").write_bytes(b"")  # unrelated: listed as unreadable, not as truncated
    assert image_problem(tmp_path / "whole.jpg") is None
    for keep in (int(len(data) * 0.6), int(len(data) * 0.95), len(data) - 2, len(data) - 1):
        (tmp_path / "cut.jpg").write_bytes(data[:keep])
        assert image_problem(tmp_path / "cut.jpg") == TRUNCATED, keep
    with caplog.at_level(logging.WARNING):
        names, skipped = list_images(tmp_path)
    assert names == ["whole.jpg"] and skipped["cut.jpg"] == TRUNCATED
    assert any(r.getMessage() == f"skipping {tmp_path / 'cut.jpg'}: {TRUNCATED}" for r in caplog.records)


def test_a_featureless_image_is_reported_not_a_crash(tmp_path):
    """A blank frame has no SIFT keypoint: writing its empty features raised (reshape of 0 rows), so the whole
    run ended in a traceback. It is now kept with no keypoints, and its report says so."""
    import json

    from mvrecon.cli import main

    for k in range(3):
        Image.fromarray(_texture(seed=k % 2)).save(tmp_path / f"tex{k}.png")  # tex0 and tex2 alike: a pair
    Image.fromarray(np.full((240, 320, 3), 128, np.uint8)).save(tmp_path / "blank.png")
    out = tmp_path / "out"
    code = main(["-q", "reconstruct", str(tmp_path), "-o", str(out)])
    report = json.loads((out / "report.json").read_text())
    assert code in (0, 1) and report["images"]["blank.png"] == {
        "status": "unregistered", "model": None, "reason": "no keypoints: a featureless image (blank, or out of focus)"}


def test_jpegs_with_a_thumbnail_or_data_after_their_end_are_whole(tmp_path):
    """An EXIF thumbnail holds an EOI marker of its own, and phone Motion Photos append a video after the EOI
    (MPO files more pictures): neither may count as truncated, nor hide a cut in the main image."""
    import io

    from mvrecon.io.images import image_problem

    image = _texture()
    buffer = io.BytesIO()
    Image.fromarray(image).resize((80, 60)).save(buffer, "JPEG")
    thumbnail = buffer.getvalue()
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, "JPEG", quality=90, exif=_exif_with_thumbnail(thumbnail, 6))
    data = buffer.getvalue()
    video = b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40 + thumbnail  # with markers, FFD9 included
    (tmp_path / "motion.jpg").write_bytes(data + video)
    with Image.open(tmp_path / "motion.jpg") as im:  # a real EXIF thumbnail, as Pillow reads it
        assert im.getexif().get_ifd(ExifTags.IFD.IFD1) == {0x0201: 56, 0x0202: len(thumbnail)}
    assert image_problem(tmp_path / "motion.jpg") is None
    assert image_metadata(tmp_path / "motion.jpg").orientation == 6
    (tmp_path / "cut.jpg").write_bytes(data[:int(len(data) * 0.6)])  # still holds the thumbnail's EOI
    assert b"\xff\xd9" in data[:int(len(data) * 0.6)]
    assert image_problem(tmp_path / "cut.jpg") == TRUNCATED
    Image.fromarray(image).save(tmp_path / "pair.mpo", "MPO", save_all=True,
                                append_images=[Image.fromarray(image[::-1])])
    with Image.open(tmp_path / "pair.mpo") as im:
        assert im.format == "MPO" and im.n_frames == 2
    assert image_problem(tmp_path / "pair.mpo") is None
    first_picture = (tmp_path / "pair.mpo").read_bytes()
    (tmp_path / "pair.mpo").write_bytes(first_picture[:len(first_picture) // 4])
    assert image_problem(tmp_path / "pair.mpo") is not None
