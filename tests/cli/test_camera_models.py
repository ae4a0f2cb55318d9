"""Camera models across the commands: COLMAP's fisheye rule said up front (compare, study) and in the reasons
(COLMAP's runs, `map -w` of a COLMAP database), study's --camera-params, trusted params whose lens folds inside the
image refused, the export's cropped view, demo's hint, one model against --gt, and the cameras in report.json.

pycolmap 4.2 marks every pair of a fisheye camera without a focal-length prior DEGENERATE: the tests that depend on
it run pycolmap on a few views of the catalog scene fisheye_orbit_small, so a pycolmap that stops doing so shows."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from mvrecon.cameras import CameraConfig, group_cameras
from mvrecon.cli import main
from mvrecon.commands.demo import scene_model_hint
from mvrecon.errors import InputError
from mvrecon.eval.runners import run_meta
from mvrecon.io.images import image_metadata

SCENE = "fisheye_orbit_small"
TRUTH = (285.0, 285.0, 320.0, 240.0, 0.05, -0.01, 0.002, -0.0005)  # the scene's lens
VIEWS = ["0000.png", "0001.png", "0002.png", "0003.png"]
COLMAP_FISHEYE_NOTE = "COLMAP verifies no pair of a fisheye camera without a known focal length"


@pytest.fixture(scope="module")
def fisheye(fisheye_orbit_small, tmp_path_factory):
    """The fisheye scene (copied where `demo -o ROOT/demo` finds it) and pycolmap's database of four of its views,
    extracted as OPENCV_FISHEYE without a focal prior and matched exhaustively."""
    root = tmp_path_factory.mktemp("fisheye")
    scene = Path(shutil.copytree(fisheye_orbit_small, root / "demo" / "scene"))
    db = root / "colmap.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV_FISHEYE"
    extraction, matching = pycolmap.FeatureExtractionOptions(), pycolmap.FeatureMatchingOptions()
    extraction.use_gpu = matching.use_gpu = False
    pycolmap.extract_features(db, scene / "images", image_names=VIEWS, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    return root, scene, db


def two_images(folder: Path, size=(160, 120)) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(folder / name), rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8))
    return folder


# --- compare and study say COLMAP's fisheye rule before running ---------------------------------------------

def test_compare_warns_before_running_colmap_on_a_fisheye_without_params(tmp_path, monkeypatch, caplog):
    import mvrecon.commands.compare as compare

    def stop(*args, **kwargs):
        raise InputError("stopped before running")

    monkeypatch.setattr(compare, "compare_images", stop)
    images = two_images(tmp_path / "imgs")
    base = ["compare", str(images), "-o", str(tmp_path / "r"), "--camera-model", "OPENCV_FISHEYE"]
    with caplog.at_level("WARNING"):
        assert main(base) == 2
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == [f"--camera-model OPENCV_FISHEYE without --camera-params: {COLMAP_FISHEYE_NOTE}, so "
                      "COLMAP's runs will register no image; give --camera-params to compare with it"]
    caplog.clear()
    with caplog.at_level("WARNING"):  # a known focal length, or a model COLMAP verifies: nothing to say
        assert main(base + ["--camera-params", "80,80,80,60,0,0,0,0"]) == 2
        assert main(["compare", str(images), "-o", str(tmp_path / "r"), "--camera-model", "OPENCV"]) == 2
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_colmaps_empty_result_on_a_fisheye_without_a_prior_gives_the_reason(fisheye, tmp_path):
    from mvrecon.eval.resumable import StageProgress
    from mvrecon.eval.runners import _write_outputs

    _, _, db = fisheye
    con = __import__("sqlite3").connect(db)
    assert con.execute("SELECT DISTINCT config FROM two_view_geometries").fetchall() == [
        (int(pycolmap.TwoViewGeometryConfiguration.DEGENERATE),)]  # pycolmap's rule, checked on its own output
    con.close()
    _write_outputs(tmp_path, "colmap", {"seed": 0}, [], db, StageProgress(tmp_path))
    reasons = {v["reason"] for v in json.loads((tmp_path / "report.json").read_text())["images"].values()}
    assert reasons == {f"{COLMAP_FISHEYE_NOTE} (camera 1 is OPENCV_FISHEYE without one); give --camera-params to "
                       "compare with it"}  # was "no verified pairs"


def test_study_passes_camera_params_to_both_engines(tmp_path, caplog, capsys):
    images = two_images(tmp_path / "imgs")
    args = ["-q", "study", str(images), "-o", str(tmp_path / "s"), "--noise", "0,5", "--camera-model",
            "OPENCV_FISHEYE", "--timeout", "0.01"]
    with caplog.at_level("WARNING"):
        assert main(args + ["--camera-params", "80,80,80,60,0.01,0,0,0"]) == 0  # the runs time out: failed cells
    for engine in ("mvrecon", "colmap"):
        meta = run_meta(tmp_path / "s" / "runs" / engine / "clean")
        assert meta["options"]["camera_params"] == [80, 80, 80, 60, 0.01, 0, 0, 0], engine
    command = run_meta(tmp_path / "s" / "runs" / "mvrecon" / "clean")["command"]
    assert command[command.index("--camera-params") + 1] == "80,80,80,60,0.01,0,0,0" and "--fix-intrinsics" in command
    assert not [r for r in caplog.records if COLMAP_FISHEYE_NOTE in r.getMessage()]
    # without them COLMAP cannot take part, which is said before anything runs
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert main(args[:4] + [str(tmp_path / "s2")] + args[5:]) == 0
    assert [r.getMessage() for r in caplog.records if COLMAP_FISHEYE_NOTE in r.getMessage()] == [
        f"--camera-model OPENCV_FISHEYE without --camera-params: {COLMAP_FISHEYE_NOTE}, so COLMAP's runs will "
        "register no image; give --camera-params to compare with it"]
    capsys.readouterr()
    # params for the clean images' size do not hold for downscaled copies; bad params are one line
    for extra, message in ((["--camera-params", "80,80,80,60,0,0,0,0", "--downscale", "1,2"],
                            "--camera-params with --downscale 1,2: the params hold for the clean images' size"),
                           (["--camera-params", "80,80,80"], "OPENCV_FISHEYE takes 8 parameters")):
        assert main(args[:4] + [str(tmp_path / "s3")] + args[5:] + extra) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "s3").exists()


# --- map -w says what the database says ---------------------------------------------------------------------

def test_map_of_a_colmap_fisheye_database_without_a_prior_names_the_degenerate_pairs(fisheye, tmp_path, capsys):
    _, _, db = fisheye
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copyfile(db, ws / "database.db")
    assert main(["map", "-w", str(ws)]) == 2
    err = capsys.readouterr().err
    assert err == (f"mvrecon: error: {ws / 'database.db'}: no verified image pairs among 4 images; all 6 matched "
                   f"pairs are DEGENERATE in the database; likely cause: {COLMAP_FISHEYE_NOTE} and marks its pairs "
                   "DEGENERATE (camera 1 is OPENCV_FISHEYE without one): give it a focal prior when extracting "
                   "(COLMAP's camera_params) and match again, or run `mvrecon reconstruct IMAGES -o OUT "
                   "--camera-model OPENCV_FISHEYE`, whose verifier needs none\n")


# --- trusted params whose lens folds inside the image -------------------------------------------------------

@pytest.mark.parametrize("model, params, fold_px", [
    ("OPENCV_FISHEYE", (285, 285, 320, 240, -2, 0, 0, 0), 78),  # theta_d peaks at theta = 23.6 deg
    ("OPENCV_FISHEYE", (285, 285, 320, 240, -0.3, 0, 0, 0), 200),
    ("OPENCV", (500, 500, 320, 240, -0.5, 0, 0, 0), 272),
    ("SIMPLE_RADIAL", (500, 320, 240, -0.3), 351),  # r (1 + k r^2) peaks at r^2 = -1 / 3k
    ("RADIAL", (500, 320, 240, -0.4, 0.02), 311)])
def test_params_whose_lens_folds_inside_the_image_are_refused(model, params, fold_px):
    with pytest.raises(InputError) as refused:
        CameraConfig(model=model, params=params).validate()
    shown = ",".join(f"{v:g}" for v in params)
    assert str(refused.value) == (
        f"--camera-params {shown}: the {model} lens model folds over {fold_px} px "
        "from the principal point, inside the image (its farthest corner is 400 px out), so the image past that "
        "radius has no ray; check the distortion coefficients")


def test_the_fold_is_checked_against_the_farthest_corner_of_the_images(tmp_path, capsys):
    # lenses that hold to the corner are taken, a wide fisheye's with no fold before 90 deg too
    for model, params in (("OPENCV_FISHEYE", TRUTH), ("OPENCV_FISHEYE", (200, 200, 320, 240, 0, 0, 0, 0)),
                          ("OPENCV", (500, 500, 320, 240, -0.2, 0.05, 0.01, 0.01)),
                          ("SIMPLE_RADIAL", (560, 320, 240, -0.03)), ("RADIAL", (500, 320, 240, -0.3, 0.1)),
                          ("SIMPLE_RADIAL", (500, 320, 240, 0.3)), ("PINHOLE", (500, 500, 320, 240))):
        assert CameraConfig(model=model, params=params).validate(size=(640, 480)).params == params
    # principal point near the top-left corner: the fold at 311 px is past that corner (141 px), not past the far one
    config = CameraConfig(model="RADIAL", params=(500, 100, 100, -0.4, 0.02))
    assert config.validate() is config
    images = two_images(tmp_path / "imgs", size=(640, 480))
    metas = {n: image_metadata(images / n) for n in ("a.png", "b.png")}
    with pytest.raises(InputError, match="folds over 311 px .* farthest corner is 660 px out"):
        group_cameras(["a.png", "b.png"], metas, config)
    # and the command refuses it in one line before any work
    assert main(["reconstruct", str(images), "-o", str(tmp_path / "out"), "--camera-model", "OPENCV_FISHEYE",
                 "--camera-params", "285,285,320,240,-2,0,0,0"]) == 2
    err = capsys.readouterr().err
    assert "--camera-params 285,285,320,240,-2,0,0,0: the OPENCV_FISHEYE lens model folds over 78 px" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "out").exists()


# --- export of a lens wider than a PINHOLE image holds ------------------------------------------------------

def fisheye_model(folder: Path, images: Path, max_angle_deg: float) -> tuple[Path, pycolmap.Camera]:
    """Two views of a 640x480 fisheye with f = 200 px (about 230 deg across the diagonal, the audit's lens) and
    points seen by both at up to `max_angle_deg` off the first view's axis."""
    cam = pycolmap.Camera(model="OPENCV_FISHEYE", width=640, height=480, params=[200, 200, 320, 240, 0, 0, 0, 0],
                          camera_id=1)
    u, v = np.meshgrid(np.arange(4, 640, 12.0), np.arange(4, 480, 12.0))
    rays = cam.cam_from_img(np.c_[u.ravel(), v.ravel()])
    rays = np.c_[rays, np.ones(len(rays))]
    rays = rays[np.degrees(np.arccos(1 / np.linalg.norm(rays, axis=1))) <= max_angle_deg]
    xyz = 5.0 * rays / np.linalg.norm(rays, axis=1)[:, None]
    poses = [pycolmap.Rigid3d(pycolmap.Rotation3d(), [0.0, 0, 0]),
             pycolmap.Rigid3d(pycolmap.Rotation3d(), [-0.2, 0, 0])]
    xy = [cam.img_from_cam(xyz + pose.translation) for pose in poses]
    keep = np.all([np.isfinite(p).all(1) & (p >= 0).all(1) & (p[:, 0] < 640) & (p[:, 1] < 480) for p in xy], axis=0)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    images.mkdir(parents=True)
    rng = np.random.default_rng(1)
    for k, pose in enumerate(poses, start=1):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{k}.png", keypoints=xy[k - 1][keep], camera_id=1,
                                                        image_id=k), pose)
        cv2.imwrite(str(images / f"{k}.png"), rng.integers(0, 256, (480, 640, 3), dtype=np.uint8))
    for i in range(int(keep.sum())):
        track = pycolmap.Track()
        track.add_element(1, i)
        track.add_element(2, i)
        rec.add_point3D(xyz[keep][i], track)
    folder.mkdir(parents=True)
    rec.write(str(folder))
    return folder, cam


def export(model, images, out):
    argv = ["-q", "export", str(model), "--model", str(model), "--image-dir", str(images), "--undistort", "-o",
            str(out)]
    return subprocess.run([sys.executable, "-m", "mvrecon.cli", *argv], capture_output=True, text=True, timeout=120)


def test_export_of_a_lens_wider_than_a_pinhole_image_says_what_it_crops(tmp_path):
    model, cam = fisheye_model(tmp_path / "wide", tmp_path / "imgs", 89.0)
    done = export(model, tmp_path / "imgs", tmp_path / "out")
    assert done.returncode == 0, done.stderr
    # the share of observations outside, counted apart: each keypoint's ray through the exported PINHOLE camera
    pinhole = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0")).cameras[1]
    original = pycolmap.Reconstruction(str(model))
    outside = total = 0
    for im in original.images.values():
        rays = cam.cam_from_img(np.array([p.xy for p in im.points2D]))
        uv = pinhole.img_from_cam(np.c_[rays, np.ones(len(rays))])
        outside += int((~((uv >= 0).all(1) & (uv[:, 0] <= pinhole.width) & (uv[:, 1] <= pinhole.height))).sum())
        total += len(rays)
    assert outside > 0.3 * total  # most of the wide view is cropped
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"{tmp_path / 'out'}: {100 * outside / total:.0f}% of the model's observations ({outside} of {total}) fall "
        "outside the undistorted images: COLMAP's undistorter keeps of the OPENCV_FISHEYE view only"), lines
    # a view the PINHOLE image holds whole is exported without a word
    narrow, _ = fisheye_model(tmp_path / "narrow", tmp_path / "imgs2", 40.0)
    done = export(narrow, tmp_path / "imgs2", tmp_path / "out2")
    assert (done.returncode, done.stderr) == (0, "")
    # and its PINHOLE camera is one: COLMAP took the fisheye without distortion terms for undistorted and copied
    # its images, which were exported as PINHOLE with the fisheye's focal (errors of tens of px)
    exported = pycolmap.Reconstruction(str(tmp_path / "out2" / "sparse" / "0"))
    assert exported.cameras[1].model.name == "PINHOLE" and exported.compute_mean_reprojection_error() < 0.05


# --- demo's hint, the cameras in report.json, one model against the ground truth ----------------------------

def test_demo_names_the_scenes_camera_model_and_reports_the_cameras(fisheye, caplog):
    root, scene, _ = fisheye
    with caplog.at_level("INFO"):
        assert main(["demo", "-o", str(root / "demo"), "--scene", SCENE]) == 0
    # the model left open, the mapper chooses the scene's lens itself (sfm/lens.py): no hint to name it
    assert [r.getMessage() for r in caplog.records if "--camera-model" in r.getMessage()] == []
    # report.json holds each model's cameras with their final parameters, as sparse/0 has them
    run = root / "demo" / "run"
    report = json.loads((run / "report.json").read_text())
    written = pycolmap.Reconstruction(str(run / "sparse" / "0")).cameras
    cameras = report["models"][0]["cameras"]
    assert [c.pop("model_choice")["chosen"] for c in cameras] == ["OPENCV_FISHEYE"]  # with each model's error
    assert cameras == [
        {"camera_id": cid, "model": "OPENCV_FISHEYE", "width": 640, "height": 480, "params": list(cam.params)}
        for cid, cam in sorted(written.items())]
    # a model named keeps the hint
    assert scene_model_hint(SCENE, scene, "SIMPLE_RADIAL") == (
        f"scene {SCENE} is rendered with OPENCV_FISHEYE cameras and this demo reconstructs with SIMPLE_RADIAL; "
        "--camera-model OPENCV_FISHEYE fits the scene")
    assert scene_model_hint(SCENE, scene, "OPENCV_FISHEYE") is None  # the scene's own model: nothing to say


def test_colmap_run_reports_list_the_cameras_the_same_way():
    from mvrecon.eval.runners import _cameras

    pycolmap.set_random_seed(0)
    rec = pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(
        num_rigs=1, num_frames_per_rig=3, num_points3D=20, camera_width=320, camera_height=240,
        camera_params=[300.0, 160.0, 120.0, 0.01]))
    (cid, cam), = rec.cameras.items()
    assert _cameras(rec) == [{"camera_id": cid, "model": cam.model.name, "width": 320, "height": 240,
                              "params": list(cam.params)}]


def test_compare_scores_one_model_against_the_ground_truth(fisheye, tmp_path, capsys):
    _, scene, _ = fisheye
    gt = scene / "gt" / "sparse"
    assert main(["compare", "-q", "--models", str(gt), "--gt", str(gt), "-o", str(tmp_path / "r")]) == 0
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    (summary,) = [e["summary"] for e in m["engines"].values()]
    assert m["reference"]["name"] == "ground truth" and summary["registered"] == 12 and summary["auc@1"] > 0.999
    capsys.readouterr()
    assert main(["compare", "--models", str(gt), "-o", str(tmp_path / "r2")]) == 2  # nothing to score it against
    assert capsys.readouterr().err == ("mvrecon: error: --models: give at least two models to compare, or one with "
                                       "--gt\n")
