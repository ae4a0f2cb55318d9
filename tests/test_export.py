"""`mvrecon export --undistort` of photos with an EXIF orientation, and of 16-bit images: mvrecon's cameras are
upright (EXIF applied when reading) while COLMAP's undistorter reads pixels as stored (it aborted the process on
90 deg images and wrote 180 deg ones upside down), and it kept 16 bits (14-bit data came out dark)."""

import subprocess
import sys

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image

from mvrecon.cli import main
from mvrecon.io.images import image_metadata

W, H = 200, 150
ORIENTATION = 0x0112
STORED = {3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270}


@pytest.fixture(scope="module")
def views():
    """Four upright RGB views of smooth random texture (an upside-down one differs by ~65 grey levels)."""
    rng = np.random.default_rng(0)
    return [cv2.resize(rng.integers(0, 256, (H // 10, W // 10, 3), dtype=np.uint8), (W, H),
                       interpolation=cv2.INTER_CUBIC) for _ in range(4)]


def _model(path, names):
    """A model as mvrecon makes it: one upright SIMPLE_RADIAL camera (with distortion, so pixels are resampled)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H,
                                                    params=[180.0, W / 2, H / 2, -0.15], camera_id=1))
    for image_id, name in enumerate(names, start=1):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(), [0.1 * image_id, 0, 0]))
    path.mkdir(parents=True)
    rec.write(str(path))
    return path


def _export(model, images, out):
    """The CLI in a child process: an abort (SIGABRT) must fail the test, not end the test run."""
    argv = ["-q", "export", str(model), "--model", str(model), "--image-dir", str(images), "--undistort", "-o",
            str(out)]
    return subprocess.run([sys.executable, "-m", "mvrecon.cli", *argv], capture_output=True, text=True, timeout=120)


def _read(path):
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def test_export_of_exif_rotated_photos_is_upright(views, tmp_path):
    names = [f"v{k}.jpg" for k in range(4)]
    model = _model(tmp_path / "model", names)
    plain, turned = tmp_path / "plain", tmp_path / "turned"
    plain.mkdir(), turned.mkdir()
    for name, view, orientation in zip(names, views, (1, 3, 6, 8)):
        Image.fromarray(view).save(plain / name, quality=95)
        stored = Image.fromarray(view).transpose(STORED[orientation]) if orientation != 1 else Image.fromarray(view)
        exif = Image.Exif()
        exif[ORIENTATION] = orientation
        stored.save(turned / name, quality=95, exif=exif)
        meta = image_metadata(turned / name)  # what mvrecon's cameras are made from: the upright size
        assert (meta.width, meta.height, meta.orientation) == (W, H, orientation)
    assert _export(model, plain, tmp_path / "reference").returncode == 0
    done = _export(model, turned, tmp_path / "out")
    assert done.returncode == 0, done.stderr  # 134 (SIGABRT) before, on the 90 deg images
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["images", "sparse"]
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    for im in rec.images.values():
        cam, path = rec.cameras[im.camera_id], tmp_path / "out" / "images" / im.name
        image, reference = _read(path), _read(tmp_path / "reference" / "images" / im.name)
        assert image.shape == reference.shape == (cam.height, cam.width, 3)
        with Image.open(path) as pil:
            assert pil.getexif().get(ORIENTATION, 1) == 1
        # upright: 2.2 grey levels (one more JPEG generation); upside down (orientation 3 before) 66
        assert np.abs(image.astype(float) - reference).mean() < 4, im.name


def test_export_of_16_bit_images_is_8_bit_and_as_bright(views, tmp_path):
    names = [f"v{k}.png" for k in range(4)]
    model = _model(tmp_path / "model", names)
    plain, deep = tmp_path / "plain", tmp_path / "deep"
    plain.mkdir(), deep.mkdir()
    for name, view in zip(names, views):
        bgr = cv2.cvtColor(view, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(plain / name), bgr)
        cv2.imwrite(str(deep / name), bgr.astype(np.uint16) * 64)  # 14-bit sensor data in 16 bits
    assert main(["-q", "export", str(model), "--model", str(model), "--image-dir", str(plain), "--undistort",
                 "-o", str(tmp_path / "reference")]) == 0
    assert main(["-q", "export", str(model), "--model", str(model), "--image-dir", str(deep), "--undistort",
                 "-o", str(tmp_path / "out")]) == 0
    for name in names:
        image, reference = _read(tmp_path / "out" / "images" / name), _read(tmp_path / "reference" / "images" / name)
        assert image.dtype == np.uint8  # uint16 holding the 14-bit values before (dark in 8-bit readers)
        assert np.abs(image.astype(float) - reference).mean() < 0.5


def test_export_of_images_of_another_size_is_one_error_line(views, tmp_path):
    """pycolmap aborts the process (SIGABRT) on an image whose size is not its camera's: refused before."""
    names = [f"v{k}.jpg" for k in range(4)]
    model = _model(tmp_path / "model", names)
    images = tmp_path / "images"
    images.mkdir()
    for name, view in zip(names, views):
        Image.fromarray(view).save(images / name)
    Image.fromarray(views[2][:, :H]).save(images / names[2])
    done = _export(model, images, tmp_path / "out")
    assert done.returncode == 2
    assert done.stderr == (f"mvrecon: error: {images / names[2]}: is {H}x{H} but its camera 1 in the model is "
                           f"{W}x{H}: not the image the model was made from; pass --image-dir\n")
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()
