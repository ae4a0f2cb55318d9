"""The OPENCV_FISHEYE camera model (COLMAP's equidistant lens): projection against COLMAP and GTSAM, bundle
adjustment of its k1..k4, the rendered fisheye_orbit_small scene reconstructed end to end and exported
undistorted, the same scene through a 184 deg lens (whose views match the repeated ground of views across the
orbit), the fx / fy plausibility test, and the one-line refusal of a database whose camera model the mapper
does not model."""

import shutil

import numpy as np
import pycolmap
import pytest

from mvrecon.cli import main
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import model_stats, poses, sparse_models
from mvrecon.geometry import camera
from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.sfm.filtering import degenerate_cameras, non_square_cameras, plausible_bundle
from mvrecon.sfm.model import Camera, Reconstruction
from mvrecon.workspace import Workspace

FISHEYE = "OPENCV_FISHEYE"
TRUTH = [285.0, 285.0, 320.0, 240.0, 0.05, -0.01, 0.002, -0.0005]  # fisheye_orbit_small's lens
LENS = [250.0, 252.0, 320.5, 240.2, 0.05, -0.01, 0.002, -0.0005]  # wider (171 deg diagonal), fx != fy
WIDE = [200.0, 200.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0]  # 184 deg across the width (the corners pass 90 deg)


def _rays(rng, n, max_angle_deg):
    """Camera-frame points up to `max_angle_deg` off the axis, at depths 0.5-5, plus the axis itself and a
    point 1e-9 off it (where r = 0 must not divide by zero)."""
    angle = np.radians(rng.uniform(0, max_angle_deg, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.sin(angle) * np.cos(phi), np.sin(angle) * np.sin(phi), np.cos(angle)], axis=1)
    return np.vstack([d * rng.uniform(0.5, 5, (n, 1)), [[0, 0, 2.0], [1e-9, 0, 1.0]]])


def test_projection_and_unprojection_match_colmap_and_gtsam():
    import gtsam

    rng = np.random.default_rng(0)
    X = _rays(rng, 2000, 89.0)
    ours = camera.project(FISHEYE, LENS, X)
    colmap = pycolmap.Camera(model=FISHEYE, width=640, height=480, params=LENS)
    np.testing.assert_allclose(ours, colmap.img_from_cam(X), rtol=0, atol=1e-9)
    cal = gtsam.Cal3Fisheye(LENS[0], LENS[1], 0.0, LENS[2], LENS[3], *LENS[4:])  # what bundle.py optimises
    np.testing.assert_allclose(ours, [cal.uncalibrate(p) for p in X[:, :2] / X[:, 2:]], rtol=0, atol=1e-9)
    # pixels -> rays: every pixel of the image (the corners are 85 deg off the axis), the principal point and
    # a pixel 1e-12 from it; the ray projects back onto its pixel
    grid = np.stack(np.meshgrid(np.linspace(0, 640, 41), np.linspace(0, 480, 31)), -1).reshape(-1, 2)
    px = np.vstack([grid, LENS[2:4], [LENS[2] + 1e-12, LENS[3]]])
    xy = camera.pixels_to_normalized(FISHEYE, LENS, px)
    np.testing.assert_allclose(xy, colmap.cam_from_img(px), rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(xy[-2], [0, 0])
    np.testing.assert_allclose(camera.project(FISHEYE, LENS, np.c_[xy, np.ones(len(xy))]), px, rtol=0, atol=1e-9)
    # the equidistant lens is no pinhole even with k = 0, and a pixel past 90 deg (f = 150: 150 px from the
    # centre is 57 deg, 300 px is 115 deg) has no ray in front of the camera: NaN. COLMAP returns a point there
    # (the distorted one, for k = 0), which projects elsewhere
    plain = [150.0, 150.0, 320.0, 240.0, 0, 0, 0, 0]
    np.testing.assert_allclose(camera.pixels_to_normalized(FISHEYE, plain, [[470.0, 240.0]]), [[np.tan(1.0), 0]])
    far = np.array([[20.0, 240.0]])
    assert np.isnan(camera.pixels_to_normalized(FISHEYE, plain, far)).all()
    colmap = pycolmap.Camera(model=FISHEYE, width=640, height=480, params=plain)
    assert np.abs(colmap.img_from_cam(np.c_[colmap.cam_from_img(far), [1.0]]) - far).max() > 100


def _synthetic_model(params):
    """Five views of 400 points spread over the fisheye's field of view (up to ~70 deg off the axes), with
    exact keypoints of the lens TRUTH, and a camera starting at `params`."""
    from mvrecon.sfm.model import Camera, Reconstruction

    rng = np.random.default_rng(1)
    X = rng.uniform([-4, -3, 0.5], [4, 3, 3.0], size=(400, 3))
    Rs = [angle_axis_to_rotmat(rng.normal(scale=0.08, size=3)) for _ in range(5)]
    centers = [np.array([x, 0.1 * x, -1.5]) for x in (-0.6, -0.3, 0.0, 0.3, 0.6)]
    ts = [-R @ c for R, c in zip(Rs, centers)]
    keypoints = [camera.project(FISHEYE, TRUTH, X @ R.T + t) for R, t in zip(Rs, ts)]
    assert all(np.isfinite(k).all() for k in keypoints)
    cam = Camera(FISHEYE, 640, 480, np.array(params, float), prior_focal=float(params[0]))
    m = Reconstruction(np.arange(1, 6), [f"{k}.png" for k in range(5)], np.ones(5), {1: cam}, keypoints, len(X))
    for i, (R, t) in enumerate(zip(Rs, ts)):
        m.register(i, R, t)
    n = len(X)
    m.add_points(X + rng.normal(scale=0.01, size=X.shape), np.arange(n), np.tile(np.arange(n), 5),
                 np.repeat(np.arange(5), n), np.tile(np.arange(n), 5))
    return m


def test_bundle_adjustment_refines_the_fisheye_lens_and_keeps_k_fixed_when_told():
    """bundle.py maps OPENCV_FISHEYE to GTSAM's Cal3Fisheye: from a focal 4% off and no distortion the BA finds
    the lens the keypoints were made with; refining the focal only (the mapper's stage below
    distortion_min_images) moves fx and fy and leaves k1..k4 as they were."""
    from mvrecon.sfm.bundle import bundle_adjust
    from mvrecon.sfm.config import MapperConfig

    config = MapperConfig(global_ba_iterations=100, ba_relative_tolerance=1e-10)
    start = [297.0, 297.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0]
    m = _synthetic_model(start)
    bundle_adjust(m, m.registered_images(), config, refine_intrinsics=True, refine_distortion=True)
    np.testing.assert_allclose(m.cameras[1].params, TRUTH, rtol=0, atol=1e-6)  # 2e-11 measured
    errors, _ = m.reprojection_errors(m.alive_observations())
    assert errors.max() < 1e-4
    m = _synthetic_model(start)
    bundle_adjust(m, m.registered_images(), config, refine_intrinsics=True, refine_distortion=False)
    params = m.cameras[1].params
    # principal point and k1..k4 held by the BA's tight prior (sigma 1e-6): 1e-7 measured, where free k1 is 0.05
    np.testing.assert_allclose(params[2:], start[2:], rtol=0, atol=1e-6)
    assert abs(params[0] - 297.0) > 1.0 and abs(params[1] - 297.0) > 1.0


def test_a_guessed_focal_moves_fx_and_fy_together():
    """The mapper replaces a guessed focal (initial pair, third view, absolute pose) with Camera.set_focal;
    for the fisheye it set fx alone (768 -> 285 gave fx 285, fy 768 and a focal of 526.5)."""
    from mvrecon.sfm.model import Camera

    cam = Camera(FISHEYE, 640, 480, camera.default_params(FISHEYE, 768.0, 640, 480), prior_focal=768.0)
    cam.set_focal(285.0)
    np.testing.assert_allclose(cam.params, [285.0, 285.0, 320.0, 240.0, 0, 0, 0, 0])
    assert cam.focal() == pytest.approx(285.0)


@pytest.fixture(scope="module")
def fisheye_run(fisheye_orbit_small, tmp_path_factory):
    """fisheye_orbit_small reconstructed by `mvrecon demo --camera-model OPENCV_FISHEYE` (which runs
    `reconstruct` on its images; no EXIF: the focal starts at the 768 px guess for 285)."""
    import json

    root = tmp_path_factory.mktemp("fisheye")
    shutil.copytree(fisheye_orbit_small, root / "scene")  # rendered once: demo finds it up to date
    assert main(["-q", "demo", "-o", str(root), "--scene", "fisheye_orbit_small", "--camera-model", FISHEYE]) == 0
    scene, run = root / "scene", root / "run"
    assert Workspace(run).stage_config("features")["camera"]["model"] == FISHEYE
    assert json.loads((root / "accuracy.json").read_text())["registered"] == 12
    return scene, run


@pytest.mark.slow
def test_fisheye_scene_is_reconstructed_with_its_lens(fisheye_run):
    """The catalog's fisheye scene with OPENCV_FISHEYE registers in one model with its lens recovered (seeds 0-3:
    AUC@1 0.941-0.962, median rotation error 0.025-0.039 deg, focal 285.1-285.9). The final refinement runs LM to
    1e-5 for this four-term lens (MapperConfig.four_term_final_tolerance): at 1e-3 it stops wherever the seed's
    and the machine's path left focal and k1..k4 (up to 0.125 deg). The default SIMPLE_RADIAL on the same
    images: AUC@1 0.50; OPENCV: AUC@5 0.12."""
    scene, run = fisheye_run
    models = sparse_models(run / "sparse")
    summary = accuracy_summary([poses(m) for m in models], load_ground_truth(scene / "gt" / "sparse"))
    assert summary["registered"] == 12 and summary["components"] == 1
    assert summary["median_rotation_error_deg"] < 0.1
    assert summary["auc@1"] >= 0.85 and summary["auc@5"] >= 0.95
    assert model_stats(models[0])["mean_reprojection_error_px"] < 1.0
    rec = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    (cam,) = rec.cameras.values()
    assert cam.model.name == FISHEYE
    assert abs(cam.focal_length_x - 285.0) < 0.01 * 285 and abs(cam.focal_length_y - 285.0) < 0.01 * 285
    assert abs(cam.params[4] - TRUTH[4]) < 0.015  # k1: 0.0446 measured (k2..k4 trade off against each other)
    # the lens as a whole: the recovered camera puts each true ray within 2 px of its pixel over the whole
    # image (at the corners 0.43-1.14 px over seeds 0-3, median 0.09-0.39 px; up to 2.44 px at a final
    # tolerance of 1e-3)
    grid = np.stack(np.meshgrid(np.linspace(0.5, 639.5, 33), np.linspace(0.5, 479.5, 25)), -1).reshape(-1, 2)
    rays = camera.pixels_to_normalized(FISHEYE, TRUTH, grid)
    moved = np.linalg.norm(cam.img_from_cam(np.c_[rays, np.ones(len(rays))]) - grid, axis=1)
    assert moved.max() < 2.0 and np.median(moved) < 1.0


@pytest.mark.slow
def test_fisheye_export_is_undistorted_to_pinhole(fisheye_run, tmp_path):
    from scipy.ndimage import map_coordinates

    from mvrecon.io.images import read_image

    scene, run = fisheye_run
    out = tmp_path / "splat"
    assert main(["-q", "export", str(run), "--undistort", "-o", str(out)]) == 0
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    original = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    (cam,), (src,) = rec.cameras.values(), original.cameras.values()
    assert cam.model.name == "PINHOLE" and rec.num_reg_images() == 12
    np.testing.assert_allclose(cam.params[:2], src.params[:2])
    assert rec.compute_mean_reprojection_error() < 1.0
    # the images were resampled to that camera: a model point shows the same grey level at its PINHOLE
    # projection in the exported image as at its fisheye projection in the rendered one
    xyz = np.array([p.xyz for p in original.points3D.values()])[::5]
    diffs = []
    for image_id, im in rec.images.items():
        exported = read_image(out / "images" / im.name).astype(float).mean(axis=2)
        rendered = read_image(scene / "images" / im.name).astype(float).mean(axis=2)
        assert exported.shape == (cam.height, cam.width)
        Xc = xyz @ im.cam_from_world().rotation.matrix().T + im.cam_from_world().translation
        new, old = cam.img_from_cam(Xc), src.img_from_cam(Xc)
        inside = np.isfinite(new).all(axis=1) & np.isfinite(old).all(axis=1)
        for px, shape in ((new, exported.shape), (old, rendered.shape)):
            inside &= (px[:, 0] > 2) & (px[:, 1] > 2) & (px[:, 0] < shape[1] - 2) & (px[:, 1] < shape[0] - 2)
        sample = [map_coordinates(g, (p[inside, 1] - 0.5, p[inside, 0] - 0.5), order=1)
                  for g, p in ((exported, new), (rendered, old))]
        diffs.append(np.abs(sample[0] - sample[1]))
    diffs = np.concatenate(diffs)
    assert len(diffs) > 1000 and np.median(diffs) < 3.0


@pytest.fixture(scope="module")
def wide_scene(tmp_path_factory):
    """fisheye_orbit_small's catalog entry with the WIDE lens, rendered (the renderer stops at 90 deg, so the
    corners are background). Its ground repeats a gravel texture every 6 m, about the orbit's diameter, so
    views across the orbit see the same ground and their verified pairs hold only false matches."""
    from mvrecon.scenes import make_scene
    from mvrecon.scenes.catalog import load_entry

    root = tmp_path_factory.mktemp("fisheye_wide")
    text = load_entry("fisheye_orbit_small")[2].read_text()
    assert f"params = {TRUTH}" in text
    (root / "wide.toml").write_text(text.replace(f"params = {TRUTH}", f"params = {WIDE}"))
    return make_scene(str(root / "wide.toml"), root / "scene")


@pytest.mark.slow
@pytest.mark.parametrize("params", [[], ["--camera-params", ",".join(f"{v:g}" for v in WIDE)]],
                         ids=["guessed", "known"])
def test_wide_fisheye_registers_every_view_in_its_place(wide_scene, tmp_path, params):
    """From the fourth image on, each view's 2D-3D matches fit a second pose one ground tile away (at several
    steps with more inliers than the true pose); taking the pose with the most inliers puts a block of 4-5 views
    there (AUC@5 0.37-0.51). The pose the image's best-connected views support wins, and an image whose
    best-connected views are not registered yet waits: AUC@5 0.989 and 0.988, median rotation error 0.04 deg
    (COLMAP's mapper on the same database with the known lens: 0.990)."""
    run = tmp_path / "run"
    assert main(["-q", "reconstruct", str(wide_scene / "images"), "-o", str(run), "--camera-model", FISHEYE,
                 *params]) == 0
    models = sparse_models(run / "sparse")
    summary = accuracy_summary([poses(m) for m in models], load_ground_truth(wide_scene / "gt" / "sparse"))
    assert summary["registered"] == 12 and summary["components"] == 1
    assert summary["auc@5"] >= 0.95 and summary["median_rotation_error_deg"] < 0.2


def test_non_square_cameras_are_implausible():
    """fx / fy beyond 1.5 is no lens (pixels are square): the three-image model fisheye_orbit_small made per
    image had fx / fy 1597 / 461, 603 / 1137 and 499 / 857 (29 deg rotation error). A trusted calibration is
    left alone (it may be anamorphic), and so is a camera no registered image uses."""
    fits = {1: [1597.0, 461.0], 2: [603.0, 1137.0], 3: [499.0, 857.0], 4: [286.0, 287.0], 5: [400.0, 590.0],
            6: [200.0, 400.0], 7: [900.0, 300.0]}
    cams = {c: Camera(FISHEYE, 640, 480, np.array([*f, 320.0, 240.0, 0, 0, 0, 0]), prior_trusted=c == 6,
                      prior_focal=768.0) for c, f in fits.items()}
    m = Reconstruction(np.arange(1, 8), [f"{c}.png" for c in fits], np.array(list(fits)), cams,
                       [np.zeros((0, 2))] * 7, 0)
    for i in range(6):  # camera 7's image is not registered
        m.register(i, np.eye(3), np.zeros(3))
    assert non_square_cameras(m) == [1, 2, 3]
    assert non_square_cameras(m, max_aspect_ratio=1.4) == [1, 2, 3, 5]
    assert degenerate_cameras(m) == []  # the focal and distortion bounds pass them all


@pytest.mark.slow
@pytest.mark.parametrize("model", ["FULL_OPENCV", "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE",
                                   "THIN_PRISM_FISHEYE"])
def test_map_refuses_a_camera_model_it_does_not_model(fisheye_run, tmp_path, capsys, model):
    """A COLMAP database whose camera is of a model mvrecon's mapper lacks: one line and exit 2, before any
    work (a Python traceback from geometry/camera.py before)."""
    _, run = fisheye_run
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copy(run / "database.db", ws / "database.db")
    with pycolmap.Database.open(str(ws / "database.db")) as db:
        db.update_camera(pycolmap.Camera.create_from_model_name(1, model, 300.0, 640, 480))
    capsys.readouterr()
    assert main(["-q", "map", "-w", str(ws)]) == 2
    assert capsys.readouterr().err == (
        f"mvrecon: error: {ws / 'database.db'}: camera 1 is {model}, which mvrecon's mapper does not model; "
        "supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE\n")
    assert sorted(p.name for p in ws.iterdir()) == ["database.db"]


def test_fisheye_camera_params_flag(tmp_path, capsys):
    """--camera-params takes the fisheye's eight numbers; fewer is one line naming both flags."""
    from mvrecon.cameras import CameraConfig

    assert CameraConfig(model=FISHEYE, params=tuple(TRUTH)).validate().params == tuple(TRUTH)
    images = tmp_path / "images"
    images.mkdir()
    assert main(["-q", "features", str(images), "-w", str(tmp_path / "ws"), "--camera-model", FISHEYE,
                 "--camera-params", "285,285,320,240,0.05"]) == 2
    assert capsys.readouterr().err == (
        "mvrecon: error: --camera-params 285,285,320,240,0.05 with --camera-model OPENCV_FISHEYE: OPENCV_FISHEYE "
        "takes 8 parameters (fx, fy, cx, cy, k1, k2, k3, k4), got 5\n")


@pytest.mark.parametrize("square", [False, True])
def test_a_global_bundle_adjustment_that_leaves_a_camera_non_square_is_undone(square):
    """The global mapper's adjustments (`square`) are undone when they leave fx / fy apart, and retried with the
    distortion fixed: on wide_orbit_small an OPENCV fit ran to fx / fy 328 / 6903, and the view graph made again
    at it (global positioning on 500 tracks an image) put every rotation 43 deg off. A growing model's (the
    incremental mapper's) are not."""
    cam = Camera("OPENCV", 640, 480, np.array([768.0, 768.0, 320.0, 240.0, 0, 0, 0, 0]), prior_focal=768.0)
    m = Reconstruction(np.arange(1, 4), ["a.png", "b.png", "c.png"], np.ones(3, int), {1: cam},
                       [np.zeros((0, 2))] * 3, 0)
    for i in range(3):
        m.register(i, np.eye(3), np.zeros(3))
    calls = []

    def adjust(focal, distortion):
        calls.append((focal, distortion))
        fy = 6903.0 if distortion else 270.0
        m.cameras[1].params = np.array([328.0, fy, 320.0, 240.0, -0.19, 0.08, 0.0, 0.0])

    plausible_bundle(m, True, True, adjust, square=square)
    assert calls == ([(True, True), (True, False)] if square else [(True, True)])
    assert m.cameras[1].params[1] == (270.0 if square else 6903.0)
