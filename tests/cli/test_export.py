"""`mvrecon export --undistort` of photos with an EXIF orientation, and of 16-bit images: mvrecon's cameras are
upright (EXIF applied when reading) while COLMAP's undistorter reads pixels as stored (it aborted the process on
90 deg images and wrote 180 deg ones upside down), and it kept 16 bits (14-bit data came out dark). A model
mapped from a database COLMAP made is in the stored frame, and is exported so; so is a bare model folder whose
cameras have the photos' stored size, or whose sizes cannot tell (COLMAP's convention, with a warning)."""

import subprocess
import sys

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image, ImageOps

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


def _model(path, names, sizes=None):
    """A bare model folder: a SIMPLE_RADIAL camera (with distortion, so pixels are resampled) per image size,
    `sizes` (width, height) per image, else W x H for all (mvrecon's upright frame for the views)."""
    rec, cameras = pycolmap.Reconstruction(), {}
    for image_id, (name, (w, h)) in enumerate(zip(names, sizes or [(W, H)] * len(names)), start=1):
        if (w, h) not in cameras:
            cameras[w, h] = len(cameras) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h,
                                                            params=[180.0, w / 2, h / 2, -0.15],
                                                            camera_id=cameras[w, h]))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=cameras[w, h], image_id=image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(), [0.1 * image_id, 0, 0]))
    path.mkdir(parents=True)
    rec.write(str(path))
    return path


def _export(model, images, out, run=None):
    """The CLI in a child process: an abort (SIGABRT) must fail the test, not end the test run."""
    argv = ["-q", "export", str(run or model), "--model", str(model), "--image-dir", str(images), "--undistort",
            "-o", str(out)]
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
    assert done.stderr == ""  # the 180 deg one is upright as the 90 deg ones are: nothing to warn about
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


def _photos_as_stored(views, folder, orientations, sizes):
    """Photos whose stored pixels are the views (cut to `sizes`), tagged with EXIF orientations, and the same
    pixels without the tag in folder/plain: what COLMAP's features (it ignores the tag) were taken from."""
    plain, tagged = folder / "plain", folder / "tagged"
    plain.mkdir(parents=True), tagged.mkdir()
    names = [f"v{k}.jpg" for k in range(len(orientations))]
    for name, view, orientation, (w, h) in zip(names, views, orientations, sizes):
        exif = Image.Exif()
        exif[ORIENTATION] = orientation
        Image.fromarray(view[:h, :w]).save(plain / name, quality=95)
        Image.fromarray(view[:h, :w]).save(tagged / name, quality=95, exif=exif)
    return names, plain, tagged


def _assert_as_stored(out, reference):
    """Each exported image is its camera's size, untagged, and shows the photo's pixels as stored: within 2-3 grey
    levels of the export of the untagged copies (one JPEG generation), against ~65 turned by 180 deg."""
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    for im in rec.images.values():
        cam, path = rec.cameras[im.camera_id], out / "images" / im.name
        image, expected = _read(path), _read(reference / "images" / im.name)
        assert image.shape == expected.shape == (cam.height, cam.width, 3), im.name
        with Image.open(path) as pil:
            assert pil.getexif().get(ORIENTATION, 1) == 1, im.name
        assert np.abs(image.astype(float) - expected).mean() < 4, im.name


def test_export_of_a_bare_colmap_model_of_exif_rotated_photos_is_as_stored(views, tmp_path):
    """A bare COLMAP model (no database.db) of photos tagged 90/270 deg: its camera has their stored size, not
    their upright one, so it is in COLMAP's frame; the 180 deg photo, whose size says nothing, goes with them.
    Refused before ("is 150x200 upright (EXIF orientation 6) but its camera 1 in the model is 200x150")."""
    names, plain, tagged = _photos_as_stored(views, tmp_path, (1, 3, 6, 8), [(W, H)] * 4)
    model = _model(tmp_path / "model", names)  # COLMAP's camera: the stored size of every photo
    assert _export(model, plain, tmp_path / "reference").returncode == 0
    done = _export(model, tagged, tmp_path / "out")
    assert done.returncode == 0 and done.stderr == "", done.stderr
    _assert_as_stored(tmp_path / "out", tmp_path / "reference")


def test_export_of_a_bare_model_whose_size_cannot_tell_is_as_stored_with_a_warning(views, tmp_path):
    """A 180 deg photo and a square one turned by 90 deg have the same size upright and as stored, and no other
    photo of the model tells its frame: exported as stored (COLMAP's convention), with one warning line naming
    them. Before, both were exported upright without a word (the 180 deg one upside down for COLMAP's model)."""
    sizes = [(W, H), (W, H), (H, H), (H, H)]
    names, plain, tagged = _photos_as_stored(views, tmp_path, (1, 3, 6, 1), sizes)
    model = _model(tmp_path / "model", names, sizes)
    assert _export(model, plain, tmp_path / "reference").returncode == 0
    done = _export(model, tagged, tmp_path / "out")
    assert done.returncode == 0, done.stderr
    assert done.stderr == (f"{model}: cannot tell the frame of v1.jpg, v2.jpg in the model (no database says, and the "
                           f"size is the same upright and as stored): exported as stored, as COLMAP reads images\n")
    _assert_as_stored(tmp_path / "out", tmp_path / "reference")


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


def test_export_needs_no_flag_and_refuses_a_run_folder_another_run_holds(views, tmp_path, capsys):
    """`export` ran beside a `reconstruct --overwrite` of its run folder (which `map` refuses), reading a model
    that was being rewritten; and it wanted --undistort, its only kind of export."""
    names = [f"v{k}.png" for k in range(4)]
    run = tmp_path / "run"
    _model(run / "sparse" / "0", names)
    images = tmp_path / "images"
    images.mkdir()
    for name, view in zip(names, views):
        Image.fromarray(view).save(images / name)
    argv = ["-q", "export", str(run), "--image-dir", str(images), "-o", str(tmp_path / "splat")]
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time; fd = os.open(sys.argv[1], "
                               "os.O_RDONLY); fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); "
                               "time.sleep(60)", str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        assert main(argv) == 2
        assert capsys.readouterr().err == f"mvrecon: error: {run}: another mvrecon run is using this folder; " \
            "wait for it to end, or choose another folder\n"
        assert not (tmp_path / "splat").exists()
    finally:
        holder.kill()
        holder.wait()
    assert main(argv) == 0
    assert sorted(p.name for p in (tmp_path / "splat" / "images").iterdir()) == names
    rec = pycolmap.Reconstruction(str(tmp_path / "splat" / "sparse" / "0"))
    assert {cam.model.name for cam in rec.cameras.values()} == {"PINHOLE"} and rec.num_reg_images() == 4


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


SCENE = """
# five 480x360 views on an 80 deg orbit around textured objects on a gravel floor (object_orbit_small, smaller)
name = "export_exif"
kind = "perspective"
seed = 11
units = "m"
points = 3000
[camera]
model = "SIMPLE_RADIAL"
width = 480
height = 360
params = [420.0, 240.0, 180.0, -0.03]
[render]
supersample = 1
noise_sigma = 1.0
[trajectory]
type = "orbit"
count = 5
radius = 3.6
height = 2.0
target = [0.0, 0.0, 0.4]
arc_deg = 80.0
[[objects]]
type = "quad"
origin = [-4.0, -4.0, 0.0]
u = [8.0, 0.0, 0.0]
v = [0.0, 8.0, 0.0]
texture = { photo = "gravel", size = 2048, detail = 0.5 }
[[objects]]
type = "box"
center = [0.0, 0.0, 0.5]
size = [1.0, 1.0, 1.0]
yaw_deg = 20.0
textures = ["astronaut", "coffee", "chelsea", "rocket", "brick", "immunohistochemistry"]
[[objects]]
type = "sphere"
center = [1.2, 0.6, 0.4]
radius = 0.4
texture = "coffee"
"""


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Five rendered views (PNG) that both COLMAP's features and ours map whole."""
    from mvrecon.scenes import make_scene

    folder = tmp_path_factory.mktemp("rendered")
    (folder / "scene.toml").write_text(SCENE)
    return sorted((make_scene(str(folder / "scene.toml"), folder / "scene") / "images").glob("*.png"))


def _grey_at(image, xy):
    """Bilinear grey levels at COLMAP pixel coordinates (top-left pixel centre at (0.5, 0.5))."""
    grey = np.asarray(Image.fromarray(image).convert("L"), dtype=np.float32)
    x, y = (xy[:, 0] - 0.5).astype(np.float32), (xy[:, 1] - 0.5).astype(np.float32)
    return cv2.remap(grey, x[None], y[None], cv2.INTER_LINEAR)[0]


@pytest.mark.parametrize("extractor,orientations", [
    ("colmap", (1, 3, 3, 1, 3)), ("colmap", (1, 6, 3, 8, 6)), ("mvrecon", (1, 6, 3, 8, 6))])
def test_export_is_in_the_frame_the_features_were_extracted_in(rendered, tmp_path, extractor, orientations):
    """Photos whose stored pixels are the rendered views, tagged with EXIF orientations. COLMAP ignores the tag:
    the model mapped from its database (`mvrecon map -w`) is in the stored frame, and the export must be too;
    mvrecon applies it: its model and export are upright. Checked against the model: at the projection of each
    3D point, the exported image shows what the photo (in the model's frame) shows at the point's observation.
    Before, 90 deg photos of a COLMAP database were refused (size mismatch), and 180 deg ones exported upside
    down (mean |grey difference| 62 instead of 0.8-1.1)."""
    images = tmp_path / "photos"
    images.mkdir()
    for path, orientation in zip(rendered, orientations):
        exif = Image.Exif()
        exif[ORIENTATION] = orientation
        Image.open(path).convert("RGB").save(images / f"{path.stem}.jpg", quality=95, exif=exif)
    ws = tmp_path / "ws"
    if extractor == "colmap":
        ws.mkdir()
        threads = pycolmap.FeatureExtractionOptions(num_threads=1)
        pycolmap.extract_features(ws / "database.db", images, camera_mode=pycolmap.CameraMode.SINGLE,
                                  extraction_options=threads)
        pycolmap.match_exhaustive(ws / "database.db", matching_options=pycolmap.FeatureMatchingOptions(
            num_threads=1))
        assert main(["-q", "map", "-o", str(ws), "--image-dir", str(images)]) == 0
    else:
        assert main(["-q", "reconstruct", str(images), "-o", str(ws), "--workers", "1"]) == 0
    model = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
    assert model.num_reg_images() == 5
    done = _export(ws / "sparse" / "0", images, tmp_path / "out", run=ws)
    assert done.returncode == 0, done.stderr
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    for image_id, im in rec.images.items():
        with Image.open(images / im.name) as photo:
            original = np.asarray(photo if extractor == "colmap" else ImageOps.exif_transpose(photo))
        with Image.open(tmp_path / "out" / "images" / im.name) as pil:
            assert pil.getexif().get(ORIENTATION, 1) == 1, im.name  # viewers show it as the model describes it
            exported = np.asarray(pil)
        cam = rec.cameras[im.camera_id]
        assert exported.shape == (cam.height, cam.width, 3)
        ids = [p.point3D_id for p in model.images[image_id].points2D if p.has_point3D()]
        seen = np.array([p.xy for p in model.images[image_id].points2D if p.has_point3D()])
        xyz = np.array([rec.points3D[i].xyz for i in ids])
        projected = np.asarray(cam.img_from_cam(im.cam_from_world() * xyz))
        difference = np.abs(_grey_at(exported, projected) - _grey_at(original, seen)).mean()
        assert len(ids) > 50 and difference < 8, (im.name, difference)
