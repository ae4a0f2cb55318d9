"""The camera model chosen from the data (sfm/lens.py): a wide lens left at the default becomes OPENCV, a lens
the default describes keeps it, and a model the user named is never changed."""

import json
import shutil

import numpy as np
import pytest

from mvrecon.cameras import GIVEN_KEY, CameraConfig, recorded_model_left_open
from mvrecon.cli import build_parser, main
from mvrecon.commands._options import frontend_config_from_args
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models
from mvrecon.geometry import camera as cammodel
from mvrecon.sfm.lens import converted_params
from tests.helpers import edited_scene


def test_converted_parameters_project_as_the_simple_radial_lens():
    """OPENCV takes SIMPLE_RADIAL's k as its k1 (the same projection); the fisheye fit, a start its BA
    refines, is within 0.5 px over the image for a mild lens and the 149 deg lens's SIMPLE_RADIAL fit (f 263,
    k -0.092)."""
    rays = np.c_[np.random.default_rng(0).uniform(-1.0, 1.0, (400, 2)), np.ones(400)]
    for params in (np.array([500.0, 320.0, 240.0, 0.02]), np.array([263.0, 320.0, 240.0, -0.092])):
        sr = cammodel.project("SIMPLE_RADIAL", params, rays)
        inside = (np.abs(sr[:, 0] - 320) < 320) & (np.abs(sr[:, 1] - 240) < 240)
        opencv = cammodel.project("OPENCV", converted_params("OPENCV", params, 640, 480), rays)
        assert np.abs(opencv - sr).max() < 1e-9
        fisheye_params = converted_params("OPENCV_FISHEYE", params, 640, 480)
        fisheye = cammodel.project("OPENCV_FISHEYE", fisheye_params, rays)
        central = inside & (np.linalg.norm(sr - [320, 240], axis=1) < 200)  # short of where the lens flattens
        assert np.abs(fisheye - sr)[central].max() < 0.5


def test_a_named_default_model_is_recorded_and_never_left_open(tmp_path):
    """`--camera-model SIMPLE_RADIAL` names the default: the features stage records that, so `map -w` keeps
    the model as `reconstruct` does; without the flag the model is left open."""
    parser = build_parser("reconstruct")
    for flags, left_open in (([], True), (["--camera-model", "SIMPLE_RADIAL"], False),
                             (["--camera-model", "OPENCV"], False)):
        args = parser.parse_args(["reconstruct", str(tmp_path), "-o", str(tmp_path / "out"), *flags])
        camera = frontend_config_from_args(args).camera
        assert camera.model_left_open is left_open
        record = {"camera": {"model": camera.model, "params": list(camera.params)}}
        if camera.model_given and camera.model == CameraConfig.model:
            record[GIVEN_KEY] = True
        assert recorded_model_left_open(record) is left_open
    assert not recorded_model_left_open(None)  # another tool's database: its cameras are its choice
    assert not recorded_model_left_open({"camera": {"model": "SIMPLE_RADIAL", "params": [300, 320, 240, 0]}})


@pytest.fixture(scope="module")
def wide_half(tmp_path_factory):
    """wide_orbit_small (an OPENCV lens, k1 -0.22, about 100 deg across) at half its size: 12 views,
    320x240."""
    return edited_scene("wide_orbit_small", tmp_path_factory.mktemp("wide_half"), {
        "width = 640": "width = 320", "height = 480": "height = 240", "supersample = 2": "supersample = 1",
        "[269.0, 269.0, 320.0, 240.0,": "[134.5, 134.5, 160.0, 120.0,", "size = 2048": "size = 1024"})


def _run(scene, out, *flags):
    """`reconstruct` with the mapper allowed to choose the lens (MapperConfig.choose_camera_model)."""
    config = out.parent / f"{out.name}.toml"
    config.write_text("[mapper]\nchoose_camera_model = true\n")
    assert main(["reconstruct", str(scene / "images"), "-o", str(out), "-q", "--config", str(config),
                 *flags]) == 0
    report = json.loads((out / "report.json").read_text())
    gt = load_ground_truth(scene / "gt" / "sparse")
    auc = accuracy_summary([poses(m) for m in sparse_models(out / "sparse")], gt)
    return report["models"][0]["cameras"][0], auc


@pytest.mark.slow
def test_a_wide_lens_left_at_the_default_becomes_opencv(wide_half, tmp_path):
    """Default camera settings, choose_camera_model on: the camera ends OPENCV, report.json gives the errors
    that chose it, and the poses are far better than SIMPLE_RADIAL's; `--camera-model SIMPLE_RADIAL` named
    keeps SIMPLE_RADIAL on the same images (AUC@1 0.71 against 0.09 with SIMPLE_RADIAL kept)."""
    camera, auc = _run(wide_half, tmp_path / "open")
    assert camera["model"] == "OPENCV", camera
    errors = camera["model_choice"]["mean_error_px"]
    assert errors["OPENCV"] < 0.8 * errors["SIMPLE_RADIAL"]
    assert auc["auc@1"] > 0.6, auc
    named, named_auc = _run(wide_half, tmp_path / "named", "--camera-model", "SIMPLE_RADIAL")
    assert named["model"] == "SIMPLE_RADIAL" and "model_choice" not in named, named
    assert named_auc["auc@1"] < auc["auc@1"] - 0.3, (named_auc, auc)


@pytest.mark.slow
def test_a_simple_radial_lens_keeps_its_model(object_orbit_small, tmp_path):
    """object_orbit_small's lens is SIMPLE_RADIAL: tried at 8 images, the richer models do not fit it clearly
    better, and the camera stays SIMPLE_RADIAL."""
    out = tmp_path / "out"
    shutil.rmtree(out, ignore_errors=True)
    camera, auc = _run(object_orbit_small, out)
    assert camera["model"] == "SIMPLE_RADIAL", camera
    errors = camera["model_choice"]["mean_error_px"]
    assert min(errors["OPENCV"], errors["OPENCV_FISHEYE"]) > 0.8 * errors["SIMPLE_RADIAL"], errors
    assert auc["auc@5"] > 0.98, auc


@pytest.fixture(scope="module")
def wide_480(tmp_path_factory):
    """wide_orbit_small at 480x360 (12 views): at 320x240 the global mapper's view graph has too few matches
    to place the cameras with any lens model."""
    return edited_scene("wide_orbit_small", tmp_path_factory.mktemp("wide_480"), {
        "width = 640": "width = 480", "height = 480": "height = 360", "supersample = 2": "supersample = 1",
        "[269.0, 269.0, 320.0, 240.0,": "[201.75, 201.75, 240.0, 180.0,"})


@pytest.mark.slow
def test_the_global_mapper_chooses_the_wide_lens_too(wide_480, tmp_path):
    """`--mapper global`, default camera settings: the guessed focal (2.9x the lens's) is calibrated from a
    wide start, the camera ends OPENCV with the errors that chose it in report.json, every image registered at
    AUC@5 0.95 measured, where the same mapper with SIMPLE_RADIAL named reaches 0.10 on these images."""
    camera, auc = _run(wide_480, tmp_path / "open", "--mapper", "global")
    assert camera["model"] == "OPENCV", camera
    errors = camera["model_choice"]["mean_error_px"]
    assert errors["OPENCV"] < 0.8 * errors["SIMPLE_RADIAL"], errors
    assert abs(camera["params"][4] + 0.22) < 0.02, camera  # the lens's k1
    assert auc["registered"] == 12 and auc["auc@5"] > 0.7, auc


@pytest.mark.slow
def test_the_global_mapper_takes_a_fisheye_fit_that_folds_only_beyond_its_observations(fisheye_orbit_small, tmp_path):
    """fisheye_orbit_small, `--mapper global`, default camera settings: the SIMPLE_RADIAL start holds
    observations out to about 300 px only, and the OPENCV_FISHEYE fit to them folds beyond that but inside the
    400 px corners. Judged out to the observations, the fit is taken and its adjustment ends at the lens's own
    parameters, every image registered at AUC@5 0.99 measured; judged out to the corners, it was refused and
    the camera went OPENCV with fx / fy 296 / 338 at AUC@5 0.16."""
    camera, auc = _run(fisheye_orbit_small, tmp_path / "out", "--mapper", "global")
    assert camera["model"] == "OPENCV_FISHEYE", camera
    fx, fy = camera["params"][:2]
    assert abs(fx - 285.0) < 3.0 and abs(fy - 285.0) < 3.0, camera  # the lens's focal, square pixels
    assert auc["registered"] == 12 and auc["auc@5"] > 0.95, auc
