"""Ground-truth scenes: the renderer puts points where the cameras say, depth/disparity/height agree with the
geometry, the catalog is deterministic and cached, COLMAP reconstructs a small scene to within 0.5 degrees."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from mvrecon.commands import scene as scene_command
from mvrecon.errors import InputError
from mvrecon.eval.models import load_reconstruction
from mvrecon.geometry.rotation import rotation_error_deg
from mvrecon.io.pfm import read_pfm
from mvrecon.scenes import cameras, list_scenes, make_scene, meshes
from mvrecon.scenes.build import build_camera, build_mesh
from mvrecon.scenes.catalog import load_entry
from mvrecon.scenes.render import Renderer, RenderSettings
from mvrecon.scenes.textures import TextureAtlas, TextureSpec
from tests.helpers import bilinear


@pytest.fixture(scope="module")
def small_scene(object_orbit_small):
    return object_orbit_small


@pytest.fixture(scope="module")
def small_renderer():
    entry, _, path = load_entry("object_orbit_small")
    return Renderer(build_mesh(entry, path.parent)), build_camera(entry)


def shrunk_entry(name, tmp_path, replacements):
    """A catalog entry's TOML with text replaced (smaller images and textures) written next to the test."""
    text = load_entry(name)[2].read_text()
    for old, new in replacements.items():
        assert old in text, f"{name}.toml no longer contains {old!r}"
        text = text.replace(old, new)
    path = tmp_path / f"{name}_test.toml"
    path.write_text(text)
    return str(path)


def test_catalog_has_the_required_scenes():
    names = set(list_scenes())
    assert {
        "object_orbit",
        "room",
        "street",
        "planar",
        "wide_orbit",
        "stereo_pair",
        "sem_tilt",
        "synthetic_colmap",
        "object_orbit_small",
    } <= names
    counts = {n: load_entry(n)[0]["trajectory"]["count"] for n in ("object_orbit", "room", "street")}
    assert counts == {"object_orbit": 24, "room": 30, "street": 40}
    assert load_entry("wide_orbit")[0]["camera"]["model"] in ("OPENCV", "SIMPLE_RADIAL")
    assert len(load_entry("sem_tilt")[0]["trajectory"]["angles_deg"]) == 5
    for name in names - {"video_orbit"}:  # small images: no side over 1024 px, no more pixels than 1024x768
        camera = load_entry(name)[0].get("camera", {})
        width, height = camera.get("width", 0), camera.get("height", 0)
        assert max(width, height) <= 1024 and width * height <= 1024 * 768, name
    # phone video as users bring it is portrait full HD; its tests use video_orbit_small (540x960)
    camera = load_entry("video_orbit")[0]["camera"]
    assert (camera["width"], camera["height"]) == (1080, 1920)
    assert {"toy_object", "toy_object_small", "video_orbit_small", "facade", "facade_small"} <= names


def test_rendered_blobs_sit_where_the_distorted_camera_projects_them():
    """Dark Gaussian dots on a tilted plane, rendered through an OPENCV lens: centroids vs projections."""
    size, sigma = 512, 3.5
    centres_uv = np.array([(s, t) for s in np.linspace(0.15, 0.85, 5) for t in np.linspace(0.15, 0.85, 4)])
    texture = np.full((size, size), 0.9, np.float32)
    offsets = np.arange(-20, 21)
    for s, t in centres_uv:  # each dot drawn in a window of +-20 texels (5.7 sigma)
        cx, cy = int(s * size), int(t * size)
        yy, xx = np.meshgrid(cy + offsets + 0.5, cx + offsets + 0.5, indexing="ij")
        dot = 0.8 * np.exp(-((xx - s * size) ** 2 + (yy - t * size) ** 2) / (2 * sigma**2))
        texture[cy - 20 : cy + 21, cx - 20 : cx + 21] -= dot.astype(np.float32)
    origin, u_edge, v_edge = np.array([-1.0, -0.75, 0.0]), np.array([2.0, 0, 0]), np.array([0, 1.5, 0])
    mesh = meshes.quad(origin, u_edge, v_edge, TextureSpec())
    settings = RenderSettings(supersample=2, ambient=1.0, noise_sigma=0.0)
    renderer = Renderer(mesh, settings, texture_arrays=[np.repeat(texture[..., None], 3, axis=2)])
    cam = cameras.PerspectiveCamera(
        "OPENCV", 320, 240, (270.0, 273.0, 163.0, 118.0, -0.15, 0.03, 0.002, -0.001)
    )
    R, t = cameras.look_at([0.7, -0.9, 2.2], [0.05, 0.0, 0.0], roll_deg=8.0)
    image, _ = renderer.render(cam, (R, t))
    grey = image[..., 0].astype(np.float64)
    points = (
        origin + centres_uv[:, :1] * u_edge + (1 - centres_uv[:, 1:]) * v_edge
    )  # texture rows run against v
    projected = cam.project(points @ R.T + t)
    errors = []
    for pu, pv in projected:
        c, r = int(pu), int(pv)
        win = grey[r - 6 : r + 7, c - 6 : c + 7]
        weight = np.clip(0.9 * 255 - win, 0, None)
        rows, cols = np.mgrid[r - 6 : r + 7, c - 6 : c + 7] + 0.5
        centroid = np.array([(weight * cols).sum(), (weight * rows).sum()]) / weight.sum()
        errors.append(np.linalg.norm(centroid - [pu, pv]))
    assert len(errors) == 20
    assert max(errors) < 0.05, f"max centroid error {max(errors):.4f} px"


def test_model_observations_lie_on_rendered_rays(small_scene, small_renderer):
    """The renderer's ray through each stored observation hits the surface at the model's 3D point."""
    renderer, cam = small_renderer
    rec = load_reconstruction(small_scene / "gt" / "sparse")
    assert rec.num_images() == 10 and rec.num_points3D() > 1000
    worst = []
    for image in rec.images.values():
        T = image.cam_from_world()
        R, t = np.asarray(T.rotation.matrix()), np.asarray(T.translation)
        idx = [k for k, p in enumerate(image.points2D) if p.has_point3D()]
        assert len(idx) > 300, f"{image.name}: only {len(idx)} observations"
        uv = np.array([image.points2D[k].xy for k in idx])
        X = np.array([rec.points3D[image.points2D[k].point3D_id].xyz for k in idx])
        np.testing.assert_allclose(cam.project(X @ R.T + t), uv, atol=1e-6)
        centre = -R.T @ t
        dirs = cam.ray_directions(uv) @ R
        hits = renderer.cast(np.tile(centre, (len(uv), 1)), dirs)
        hit_points = centre + hits.t[:, None].astype(np.float64) * dirs
        z = (X @ R.T + t)[:, 2]
        worst.append(np.max(np.linalg.norm(hit_points - X, axis=1) * cam.params[0] / z))
    assert max(worst) < 0.05, f"worst ray/point disagreement {max(worst):.4f} px"


def test_depth_maps_agree_with_model_points(small_scene):
    rec = load_reconstruction(small_scene / "gt" / "sparse")
    rel = []
    for image in rec.images.values():
        depth = np.load(small_scene / "gt" / "depth" / (image.name.rsplit(".", 1)[0] + ".npy"))
        assert depth.shape == (480, 640) and depth.dtype == np.float32
        assert np.isinf(depth).any() and np.isfinite(depth).mean() > 0.5  # sky is inf, the scene is finite
        T = image.cam_from_world()
        pts = [p for p in image.points2D if p.has_point3D()]
        uv = np.array([p.xy for p in pts])
        z = np.array([T * rec.points3D[p.point3D_id].xyz for p in pts])[:, 2]
        value, smooth = bilinear(depth, uv[:, 0], uv[:, 1])
        assert smooth.mean() > 0.8
        rel.append(np.abs(value[smooth] - z[smooth]) / z[smooth])
    rel = np.concatenate(rel)
    assert np.median(rel) < 1e-4 and np.percentile(rel, 99) < 2e-3, (np.median(rel), np.percentile(rel, 99))


def test_textures_are_rich_enough_for_sift(small_scene):
    import cv2

    counts = [
        len(cv2.SIFT_create().detect(cv2.imread(str(small_scene / "images" / f"{k:04d}.png"), 0)))
        for k in (0, 5, 9)
    ]
    assert min(counts) > 1500, counts


def test_pycolmap_reconstructs_the_small_scene(small_scene, tmp_path):
    from mvrecon.scenes.validate import colmap_reconstruct, compare_with_ground_truth

    run = colmap_reconstruct(small_scene, tmp_path / "colmap", num_threads=2)
    summary = compare_with_ground_truth(small_scene, run["models"])
    assert summary["registered"] == summary["images"] == 10
    assert summary["components"] == 1
    assert summary["max_rotation_error_deg"] < 0.5, summary


def test_stereo_warp_leaves_only_noise(tmp_path):
    import cv2

    toml = shrunk_entry(
        "stereo_pair_small",
        tmp_path,
        {
            "width = 640": "width = 320",
            "height = 480": "height = 240",
            "params = [560.0, 560.0, 320.0, 240.0]": "params = [280.0, 280.0, 160.0, 120.0]",
            "size = 2048": "size = 1024",
        },
    )
    out = make_scene(toml, tmp_path / "stereo")
    left = cv2.imread(str(out / "images" / "im0.png")).astype(np.float32)
    right = cv2.imread(str(out / "images" / "im1.png")).astype(np.float32)
    disparity = read_pfm(out / "disp0GT.pfm")
    mask = cv2.imread(str(out / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE)
    calib = dict(line.split("=", 1) for line in (out / "calib.txt").read_text().splitlines())
    assert float(calib["baseline"]) == pytest.approx(160.0) and int(calib["width"]) == 320  # mm, as Middlebury
    assert float(np.nanmax(disparity[np.isfinite(disparity)])) < int(calib["ndisp"])
    nocc = mask == 255
    assert 0.8 < nocc.mean() < 0.99 and (mask == 128).any()
    depth = np.load(out / "gt" / "depth" / "im0.npy")
    f = float(calib["cam0"].strip("[").split()[0])
    np.testing.assert_allclose(float(calib["baseline"]) * f / disparity[nocc], 1000 * depth[nocc], rtol=1e-5)
    h, w = disparity.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    d = np.where(np.isfinite(disparity), disparity, 0).astype(np.float32)

    def warp_error(shift):
        warped = cv2.remap(right, u - d + shift, v, cv2.INTER_LINEAR)
        return np.abs(warped - left).mean(axis=2)[nocc]

    sigma = load_entry("stereo_pair_small")[0]["render"]["noise_sigma"]
    floor = 2 * sigma / np.sqrt(np.pi)  # mean |difference| of two independent N(0, sigma) noises
    err = warp_error(0.0)
    # the median pixel is at the noise floor; the mean also carries bilinear resampling error at texture edges
    assert np.median(err) < 1.2 * floor and err.mean() < 1.8 * floor, (np.median(err), err.mean(), floor)
    # the true disparity is the best one: shifting it by a tenth of a pixel either way makes the warp worse
    assert warp_error(-0.1).mean() > err.mean() < warp_error(0.1).mean()
    assert warp_error(1.0).mean() > 2 * err.mean()


def test_sem_tilt_depths_agree_with_the_height_map(tmp_path):
    toml = shrunk_entry(
        "sem_tilt_small",
        tmp_path,
        {
            "width = 480": "width = 240",
            "height = 480": "height = 240",
            "pixel_size = 0.2": "pixel_size = 0.4",
            "size = 2048": "size = 512",
        },
    )
    out = make_scene(toml, tmp_path / "sem")
    meta = json.loads((out / "gt" / "height.json").read_text())
    height = np.load(out / "gt" / "height.npy")
    ps, w, h = meta["pixel_size_um"], meta["width"], meta["height"]
    assert meta["units"] == "micrometres" and meta["tilt_angles_deg"] == [-10.0, -5.0, 0.0, 5.0, 10.0]
    assert height.shape == (h, w) and 3.0 < np.nanmax(height) - np.nanmin(height) < 9.0
    names = sorted(meta["images"])
    assert sorted(os.listdir(out / "images")) == names
    v, u = np.mgrid[0:h:2, 0:w:2] + 0.5
    hv = height[0:h:2, 0:w:2]
    # the 0-degree camera looks down -z with image y along -y: pixel (u, v) sees world (x, y, height)
    X = np.stack([(u - w / 2) * ps, -(v - h / 2) * ps, hv], -1).reshape(-1, 3)
    R0 = np.array(meta["images"]["tilt_+0.0.png"]["cam_from_world_R"])
    for name in names:
        R, t = (
            np.array(meta["images"][name]["cam_from_world_R"]),
            np.array(meta["images"][name]["cam_from_world_t"]),
        )
        angle = float(name[5:-4])
        assert rotation_error_deg(R, R0) == pytest.approx(abs(angle), abs=1e-9)
        p = X @ R.T + t
        pu, pv = p[:, 0] / ps + w / 2, p[:, 1] / ps + h / 2
        depth = np.load(out / "gt" / "depth" / (name[:-4] + ".npy"))
        value, smooth = bilinear(depth, pu, pv)
        assert smooth.mean() > 0.7
        err = np.abs(value[smooth] - p[smooth, 2])
        assert np.median(err) < 0.01 * ps, (name, np.median(err))  # micrometres


def test_synthetic_colmap_scene_wraps_colmaps_generator(tmp_path):
    toml = shrunk_entry(
        "synthetic_colmap",
        tmp_path,
        {
            "num_frames_per_rig = 12": "num_frames_per_rig = 4",
            "camera_width = 1024": "camera_width = 320",
            "camera_height = 768": "camera_height = 240",
            "[1280.0, 512.0, 384.0, 0.05]": "[400.0, 160.0, 120.0, 0.05]",
        },
    )
    out = make_scene(toml, tmp_path / "syn")
    rec = load_reconstruction(out / "gt" / "sparse")
    names = sorted(im.name for im in rec.images.values())
    assert len(names) == 4 and sorted(os.listdir(out / "images")) == names
    assert rec.num_points3D() == 1500 and rec.compute_mean_reprojection_error() < 1e-6
    assert next(iter(rec.cameras.values())).width == 320
    assert _files(make_scene(toml, tmp_path / "again")) == _files(out)  # seeded: the same bytes again


TINY = """
name = "tiny"
kind = "perspective"
seed = 5
points = 300
[camera]
model = "SIMPLE_RADIAL"
width = 96
height = 72
params = [80.0, 48.0, 36.0, 0.01]
[trajectory]
type = "orbit"
count = 3
radius = 3.0
height = 1.5
[[objects]]
type = "box"
center = [0.0, 0.0, 0.0]
size = [1.0, 1.0, 1.0]
texture = { photo = "coffee", size = 128 }
"""


def _files(folder):
    """The scene's files and bytes; its record (.stages/, with the seconds the work took) is not the scene's."""
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
        if p.is_file() and ".stages" not in p.relative_to(folder).parts
    }


def test_a_scene_made_by_an_older_version_is_made_again(tmp_path):
    """A complete scene.json without the record (an older mvrecon's scene) is not taken as up to date: the
    scene is rendered again, to the same bytes."""
    toml = tmp_path / "tiny.toml"
    toml.write_text(TINY)
    made = _files(make_scene(str(toml), tmp_path / "a"))
    old = tmp_path / "a"
    shutil.rmtree(old / ".stages")
    (old / "images" / "0000.png").write_bytes(b"older")
    make_scene(str(toml), old)
    assert _files(old) == made and json.loads((old / "scene.json").read_text())["complete"] is True
    stamp = (old / "images" / "0000.png").stat().st_mtime_ns
    make_scene(str(toml), old)  # recorded now: up to date
    assert (old / "images" / "0000.png").stat().st_mtime_ns == stamp


def test_make_scene_is_deterministic_and_cached(tmp_path):
    toml = tmp_path / "tiny.toml"
    toml.write_text(TINY)
    a, b = make_scene(str(toml), tmp_path / "a"), make_scene(str(toml), tmp_path / "b")
    files_a, files_b = _files(a), _files(b)
    assert (
        "images/0002.png" in files_a
        and "gt/sparse/points3D.bin" in files_a
        and "gt/depth/0000.npy" in files_a
    )
    assert files_a == files_b
    stamp = (a / "images" / "0000.png").stat().st_mtime_ns
    make_scene(str(toml), a)
    assert (a / "images" / "0000.png").stat().st_mtime_ns == stamp  # up to date: nothing rewritten
    toml.write_text(TINY.replace("count = 3", "count = 2"))
    make_scene(str(toml), a)
    assert sorted(os.listdir(a / "images")) == [
        "0000.png",
        "0001.png",
    ]  # changed entry: rebuilt, stale files gone
    assert json.loads((a / "scene.json").read_text())["complete"] is True


def test_make_scene_resumes_after_ctrl_c(tmp_path, monkeypatch):
    """Ctrl-C while view 2's depth is being written: the rerun renders views 2 and 3 only, same bytes."""
    toml = tmp_path / "tiny.toml"
    toml.write_text(TINY.replace("count = 3", "count = 4"))
    whole = _files(make_scene(str(toml), tmp_path / "whole"))
    renders, saves, save = [], [], np.save
    render = Renderer.render
    monkeypatch.setattr(Renderer, "render", lambda self, *a, **k: renders.append(1) or render(self, *a, **k))

    def cut_save(path, array):
        saves.append(path)
        if len(saves) == 3:  # the third depth map is cut off
            with open(path, "wb") as f:
                f.write(b"\x93NUMPY")
            raise KeyboardInterrupt
        save(path, array)

    monkeypatch.setattr(np, "save", cut_save)
    with pytest.raises(KeyboardInterrupt):
        make_scene(str(toml), tmp_path / "cut")
    monkeypatch.setattr(np, "save", save)
    assert json.loads((tmp_path / "cut" / "scene.json").read_text())["complete"] is False
    renders.clear()
    make_scene(str(toml), tmp_path / "cut")
    assert len(renders) == 2 and _files(tmp_path / "cut") == whole
    toml.write_text(TINY.replace("count = 3", "count = 4").replace("seed = 5", "seed = 6"))
    renders.clear()
    make_scene(str(toml), tmp_path / "cut")  # other settings: all views again
    assert len(renders) == 4 and _files(tmp_path / "cut") != whole


@pytest.mark.parametrize("module, event, count", [("open3d.pybind", "builtins.id", 12),
                                                  ("scipy._lib._ccallback_c", "register", 1)])
def test_ctrl_c_while_libraries_initialise_exits_130(tmp_path, module, event, count):
    """Ctrl-C inside Open3D's C++ initialisation left it counting unfreed memory: its exit check printed
    a page of statistics and made the process exit 1. Inside scipy's Cython initialisation (imported by
    the first photo texture) it was swallowed: exit 0 after the whole scene. SIGINT at a fixed point of
    each (the count-th `event`, audit event or Python call, after `module` starts importing)."""
    toml = tmp_path / "tiny.toml"
    toml.write_text(TINY)
    script = """
import os, signal, sys
module, event, count = sys.argv[3], sys.argv[4], int(sys.argv[5])
seen = []
def tick():
    seen.append(1)
    if len(seen) == count + 1:
        os.kill(os.getpid(), signal.SIGINT)
def audit(name, args):
    if name == "import" and args[0] == module and not seen:
        seen.append(0)
    elif seen and name == event:
        tick()
def profile(frame, what, arg):
    if seen and what == "call" and frame.f_code.co_name == event:
        tick()
sys.addaudithook(audit)
if event == "register":
    sys.setprofile(profile)
from mvrecon.cli import main
sys.exit(main(["scene", "make", sys.argv[1], "-o", sys.argv[2]]))
"""
    args = [str(toml), str(tmp_path / "out"), module, event, str(count)]
    run = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=120)
    assert (run.returncode, run.stdout) == (130, ""), run.stdout[-500:] + run.stderr[-500:]
    assert run.stderr.splitlines() == [f"mvrecon: interrupted; {scene_command.ON_INTERRUPT}"]


def test_bad_scene_requests_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="no such scene"):
        make_scene("no_such_scene", tmp_path / "x")
    bad = tmp_path / "bad.toml"
    bad.write_text(TINY.replace("radius = 3.0", "radius = 3.0\nwobble = 1"))
    with pytest.raises(InputError, match="unknown keys.*wobble"):
        make_scene(str(bad), tmp_path / "bad")
    bad.write_text(TINY.replace("size = [1.0, 1.0, 1.0]", "size = [1.0, 1.0, 1.0]\ncentre = [0, 0, 0]"))
    with pytest.raises(InputError, match="box: unknown keys.*centre"):
        make_scene(str(bad), tmp_path / "bad")
    (tmp_path / "user" / "images").mkdir(parents=True)
    with pytest.raises(InputError, match="no scene.json"):
        make_scene("object_orbit_small", tmp_path / "user")
    # any user file, not only an images/ folder: a scene's own names (calib.txt, gt/) were replaced or deleted
    user = tmp_path / "stereo_user"
    (user / "gt").mkdir(parents=True)
    (user / "gt" / "notes.txt").write_text("mine")
    (user / "calib.txt").write_text("mine")
    with pytest.raises(InputError, match="no scene.json"):
        make_scene("stereo_pair_small", user)
    assert (user / "gt" / "notes.txt").read_text() == (user / "calib.txt").read_text() == "mine"


TINY_TILT = """
kind = "sem_tilt"
[camera]
orthographic = true
width = 32
height = 32
pixel_size = 1.0
[trajectory]
type = "tilt"
angles_deg = [-5.0, 5.0]
distance = 50.0
[[objects]]
type = "quad"
origin = [-10.0, -10.0, 0.0]
u = [20.0, 0.0, 0.0]
v = [0.0, 20.0, 0.0]
texture = "noise"
"""


@pytest.mark.parametrize("base, old, new, expected", [
    # a TypeError ("PerspectiveCamera.__init__() missing 4 required positional arguments") and a folder
    # holding scene.json
    (TINY, "[camera]\nmodel = \"SIMPLE_RADIAL\"\nwidth = 96\nheight = 72\nparams = [80.0, 48.0, 36.0, 0.01]\n", "",
     "no [camera] table; a perspective scene needs one with model, width, height and params (or focal)"),
    (TINY, "width = 96\n", "", "[camera] lacks width"),
    (TINY, "radius = 3.0\n", "", "[trajectory] (orbit) lacks radius"),
    (TINY, "size = [1.0, 1.0, 1.0]\n", "", "[[objects]] #1 box lacks size"),
    (TINY_TILT, "pixel_size = 1.0\n", "", "[camera] lacks pixel_size"),
    (TINY, "width = 96\n", "width = 96\nzoom = [2.0, 1.0]\n",
     "[camera] zoom = [2.0, 1.0]: must be [low, high] with 0 < low <= high"),
    (TINY, "width = 96\n", "width = 96\nsize_step = [8]\n",
     "[camera] size_step = [8]: must be [width, height] steps of 0 or more pixels"),
    # a 0-image scene, exit 0
    (TINY, "count = 3", "count = 0", "[trajectory] count = 0: a scene needs a whole number of views, 2 or more"),
    (TINY, "count = 3", "count = 1", "[trajectory] count = 1: a scene needs a whole number of views, 2 or more"),
    (TINY_TILT, "[-5.0, 5.0]", "[5.0]", "[trajectory] angles_deg = [5.0]: a tilt series needs 2 tilts or more"),
    (TINY_TILT, "[-5.0, 5.0]", "[5.0, 5.01]",
     "[trajectory] angles_deg: 5 and 5.01 deg both make tilt_+5.0.png; tilts must differ by 0.1 deg or more"),
])
def test_scene_entries_lacking_keys_or_views_are_one_line(tmp_path, capsys, base, old, new, expected):
    """Refused in one line naming the file, the table and the key, before a folder is made or a view rendered."""
    from mvrecon.cli import main

    assert old in base
    toml = tmp_path / "entry.toml"
    toml.write_text(base.replace(old, new))
    assert main(["scene", "make", str(toml), "-o", str(tmp_path / "out" / "scene")]) == 2
    assert capsys.readouterr().err.splitlines() == [f"mvrecon: error: {toml}: {expected}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["entry.toml"]


def test_visitor_photos_give_every_view_its_own_camera(tmp_path):
    """`zoom` and `size_step` give each view its own size and focal (photos from many cameras), and the
    ground truth a camera per image that projects its points where the image shows them."""
    from mvrecon.scenes.build import view_cameras

    entry = load_entry("visitor_photos_small")[0]
    cams = view_cameras(entry, 14)
    assert [(c.width, c.height) for c in cams] == [(560 + 8 * k, 420 + 6 * k) for k in range(14)]
    focals = np.array([c.params[0] for c in cams])
    assert np.all((focals >= 0.5 * 480) & (focals <= 2.0 * 480)) and focals.max() / focals.min() > 2.5
    assert all(c.params[1:3] == (c.width / 2, c.height / 2) and c.params[3] == -0.02 for c in cams)
    orbit = load_entry("object_orbit_small")[0]
    assert view_cameras(orbit, 3) == [build_camera(orbit)] * 3
    small = shrunk_entry("visitor_photos_small", tmp_path,
                         {"count = 14": "count = 3", "supersample = 2": "supersample = 1", "size = 2048": "size = 256"})
    scene = make_scene(small, tmp_path / "scene")
    model = load_reconstruction(scene / "gt" / "sparse")
    assert len(model.cameras) == 3 and json.loads((scene / "scene.json").read_text())["camera_per_image"]
    for image in model.images.values():
        camera = model.cameras[image.camera_id]
        size = Image.open(scene / "images" / image.name).size
        assert (camera.width, camera.height) == size
        assert np.allclose(camera.params, cams[int(image.name[:4])].params)


def test_a_failed_make_leaves_no_folder_it_made(tmp_path):
    """An error found while building (an unknown photo) removes the new folder; an existing one stays."""
    toml = tmp_path / "tiny.toml"
    toml.write_text(TINY.replace('{ photo = "coffee", size = 128 }', '{ photo = "nosuch" }'))
    with pytest.raises(InputError, match="unknown photo 'nosuch'"):
        make_scene(str(toml), tmp_path / "new")
    assert not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()
    with pytest.raises(InputError, match="unknown photo 'nosuch'"):
        make_scene(str(toml), tmp_path / "mine")
    assert (tmp_path / "mine").is_dir()


def test_scene_command_lists_and_reports_errors(capsys, tmp_path):
    from mvrecon.cli import main

    assert main(["scene", "list"]) == 0
    assert "object_orbit_small" in capsys.readouterr().out
    assert main(["scene", "make", "no_such_scene", "-o", str(tmp_path / "x")]) == 2
    assert "no such scene" in capsys.readouterr().err


@pytest.mark.parametrize("unbuffered", ["", "1"])
def test_output_piped_to_a_reader_that_stops_early_ends_quietly(unbuffered):
    """`mvrecon scene list | head -1` ends as Unix tools do when the reader has gone, buffered or not: no
    BrokenPipeError traceback, nothing on stderr, exit code 141 (128 + SIGPIPE). The reader here is gone before the
    listing is written."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"} | {"PYTHONUNBUFFERED": unbuffered}
    proc = subprocess.Popen([sys.executable, "-m", "mvrecon.cli", "scene", "list"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    proc.stdout.close()
    assert proc.wait(timeout=60) == 141 and proc.stderr.read() == b""


def test_meshes_load_from_ply_files(tmp_path):
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).translate([-0.5, -0.5, -0.5])
    o3d.io.write_triangle_mesh(str(tmp_path / "cube.ply"), box)
    toml = tmp_path / "cube.toml"
    toml.write_text(
        TINY.replace('type = "orbit"', 'type = "orbit"\ntarget = [0.0, 0.0, 0.0]')
        .replace("height = 1.5", "height = 0.0")
        .replace(
            'type = "box"\ncenter = [0.0, 0.0, 0.0]\nsize = [1.0, 1.0, 1.0]',
            'type = "mesh"\npath = "cube.ply"',
        )
    )
    out = make_scene(str(toml), tmp_path / "cube")
    depth = np.load(out / "gt" / "depth" / "0000.npy")
    # the first orbit camera stands at (3, 0, 0) looking at the cube's centre: the face x = 0.5 is 2.5 away
    assert depth[36, 48] == pytest.approx(2.5, abs=1e-5)
    assert np.isinf(depth[0, 0])


def test_exposure_and_vignetting_scale_the_image():
    mesh = meshes.quad([-5.0, -5.0, 0.0], [10.0, 0, 0], [0, 10.0, 0], TextureSpec())
    flat = [np.full((8, 8, 3), 0.8, np.float32)]
    cam = cameras.PerspectiveCamera("PINHOLE", 64, 48, (60.0, 60.0, 32.0, 24.0))
    pose = cameras.look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    plain = Renderer(mesh, RenderSettings(ambient=1.0, noise_sigma=0.0), flat).render(cam, pose)[0]
    assert np.all(plain == round(0.8 * 255))
    dim = Renderer(mesh, RenderSettings(ambient=1.0, noise_sigma=0.0, vignetting=0.3), flat)
    image = dim.render(cam, pose, exposure=1.2)[0].astype(float)
    r2 = ((0.5 - 32) ** 2 + (0.5 - 24) ** 2) / (32**2 + 24**2)
    assert image[24, 32, 0] == pytest.approx(0.8 * 255 * 1.2, abs=1.0)
    assert image[0, 0, 0] == pytest.approx(0.8 * 255 * 1.2 * (1 - 0.3 * r2), abs=1.0)


def test_alpha_images_are_transparent_where_no_surface_and_read_alike(tmp_path):
    """`render.alpha`: RGBA PNGs as a transparent-film render writes them (NeRF synthetic): alpha is the share
    of a pixel's rays that hit, colour 0 where none does; mvrecon and COLMAP both drop alpha, so both see the
    object on black, pixel for pixel."""
    import pycolmap
    from PIL import Image

    from mvrecon.io.images import read_image

    toml = tmp_path / "alpha.toml"
    toml.write_text(TINY.replace("[trajectory]", "[render]\nalpha = true\n[trajectory]"))
    out = make_scene(str(toml), tmp_path / "alpha")
    rgba = np.asarray(Image.open(out / "images" / "0000.png"))
    depth = np.load(out / "gt" / "depth" / "0000.npy")
    assert rgba.shape == (72, 96, 4)
    alpha = rgba[..., 3]
    # depth is cast through pixel centres, alpha counts 2x2 rays around them
    assert np.all(alpha[np.isinf(depth)] < 255) and np.all(alpha[np.isfinite(depth)] > 0)
    assert (alpha == 0).mean() > 0.3 and (alpha == 255).mean() > 0.1 and ((alpha > 0) & (alpha < 255)).any()
    assert np.all(rgba[alpha == 0, :3] == 0) and rgba[alpha == 255, :3].mean() > 20
    ours = read_image(out / "images" / "0000.png")
    theirs = pycolmap.Bitmap.read(str(out / "images" / "0000.png"), True).to_array()
    assert np.array_equal(ours, rgba[..., :3]) and np.array_equal(theirs, rgba[..., :3])
    with pytest.raises(InputError, match="alpha"):  # JPEG has no alpha channel
        toml.write_text(TINY.replace("[trajectory]", "[render]\nalpha = true\n[trajectory]")
                        .replace('seed = 5', 'seed = 5\nimage_format = "jpg"'))
        make_scene(str(toml), tmp_path / "jpg")


def test_repeated_objects_are_exact_copies_and_cylinders_stand_on_their_base():
    """`repeat`/`step` copies an object along each step vector, sharing its textures (exact repetition, as
    moulded studs or a facade's windows); a cylinder's top cap is at base + height, its side at the radius."""
    from mvrecon.scenes.build import build_object

    spec = {"type": "cylinder", "base": [0.0, 0.0, 0.0], "radius": 0.1, "height": 0.3,
            "texture": {"photo": "noise", "size": 32}}
    one = build_object(spec, 0, None)
    grid = build_object({**spec, "repeat": [3, 2], "step": [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]}, 0, None)
    assert len(grid.textures) == len(one.textures) == 1 and grid.num_triangles == 6 * one.num_triangles
    nv = len(one.vertices)
    offsets = {tuple(np.round(grid.vertices[k * nv] - one.vertices[0], 9)) for k in range(6)}
    assert offsets == {(x, y, 0.0) for x in (0.0, 1.0, 2.0) for y in (0.0, 2.0)}
    renderer = Renderer(grid, RenderSettings(), [np.full((4, 4, 3), 0.5, np.float32)])
    down = renderer.cast(np.array([[2.0, 2.0, 1.0], [1.05, 0.0, 1.0]]), np.array([[0.0, 0.0, -1.0]] * 2))
    assert down.t[0] == pytest.approx(0.7, abs=1e-6) and down.t[1] == pytest.approx(0.7, abs=1e-6)
    side = renderer.cast(np.array([[-1.0, 0.0, 0.15]]), np.array([[1.0, 0.0, 0.0]]))
    assert side.t[0] == pytest.approx(0.9, abs=0.002)  # a 32-sided polygon: within 0.1 * (1 - cos(pi / 32))


def test_handheld_frames_follow_the_arc_with_a_hands_sway():
    """Without sway the frames lie on the arc and look at the target; `jitter` moves the centres off it by
    about its size, `shake_deg` turns each frame on its own, `pace` spaces the frames unevenly."""
    target = np.array([0.0, 0.0, 0.1])

    def centres_and_axes(**kw):
        poses = cameras.handheld(40, 0.5, 0.3, target, -90.0, 120.0, seed=3, **kw)
        return np.array([-R.T @ t for R, t in poses]), np.array([R[2] for R, _ in poses])

    c, z = centres_and_axes()
    np.testing.assert_allclose(np.linalg.norm(c[:, :2] - target[:2], axis=1), 0.5)
    np.testing.assert_allclose(c[:, 2], 0.4)
    to_target = (target - c) / np.linalg.norm(target - c, axis=1, keepdims=True)
    np.testing.assert_allclose(np.sum(z * to_target, axis=1), 1.0)
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert steps.max() / steps.min() < 1.0001  # evenly spaced
    cj, _ = centres_and_axes(jitter=0.02)
    off = np.linalg.norm(cj - c, axis=1)
    assert 0.01 < np.median(off) < 0.06
    _, zs = centres_and_axes(shake_deg=3.0)
    turn = np.degrees(np.arccos(np.clip(np.sum(zs * to_target, axis=1), -1, 1)))
    assert 2.0 < np.median(turn) < 8.0
    cp, _ = centres_and_axes(pace=0.8)
    steps = np.linalg.norm(np.diff(cp, axis=0), axis=1)
    assert steps.max() / steps.min() > 3.0
    assert np.allclose(cp[[0, -1]], c[[0, -1]])  # the same arc, both ends included
    again = cameras.handheld(40, 0.5, 0.3, target, -90.0, 120.0, jitter=0.02, shake_deg=3.0, pace=0.8, seed=3)
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(again, cameras.handheld(
        40, 0.5, 0.3, target, -90.0, 120.0, jitter=0.02, shake_deg=3.0, pace=0.8, seed=3)))


def test_a_texel_coordinate_a_hair_below_the_edge_wraps_round():
    """np.mod of a float32 a hair below zero returns the period itself: a lookup there read past the atlas
    (planar with its seed 202 more crashed its render with an IndexError). It wraps to the first texel, as the
    texture repeats."""
    tex = np.arange(16 * 8 * 3, dtype=np.float32).reshape(16, 8, 3)
    atlas = TextureAtlas([tex])
    hair = np.float32(0.5) - np.float32(3e-8)
    assert np.mod(hair - np.float32(0.5), np.float32(16)) == 16  # the float32 rounding this guards against
    x = np.array([hair, 0.5, hair], np.float32)
    y = np.array([hair, hair, 0.5], np.float32)
    w, h = np.full(3, 8, np.float32), np.full(3, 16, np.float32)
    colours = atlas.lookup(x, y, w, h, np.zeros(3, np.int32))
    assert np.allclose(colours, tex[0, 0], atol=1e-3)
