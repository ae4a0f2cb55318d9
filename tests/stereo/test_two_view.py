"""Two-view stereo: metrics, the paper's GEE method, SGBM and `best` against Middlebury ground truth (and its
left-edge band), the CLI run end to end (depth against ground-truth depth), a rerun reusing finished stages,
uncalibrated rectification, and bad input."""

import json
from pathlib import Path

import numpy as np
import pytest

from mvrecon.cli import main
from mvrecon.stereo.best import BestConfig, best_disparity
from mvrecon.stereo.calib import StereoCalib, read_calib, write_calib
from mvrecon.stereo.evaluate import disparity_metrics, evaluate
from mvrecon.stereo.gee import GEEConfig, gee_disparity
from mvrecon.stereo.sgbm import SGBMConfig, sgbm_disparity
from tests.helpers import DATA

MOTO = DATA / "stereo_middlebury2014_motorcycle_quarter"
CONES = DATA / "stereo_middlebury2003_cones_gray"


@pytest.fixture(scope="module")
def motorcycle():
    import skimage.data

    return skimage.data.stereo_motorcycle()


@pytest.fixture(scope="module")
def motorcycle_best(motorcycle):
    left, right, _ = motorcycle
    return best_disparity(left, right, BestConfig(num_disparities=64))


def moto_calib(path) -> Path:
    """calib.txt for the quarter-size Motorcycle, from the numbers in its SOURCE.txt / skimage's docstring."""
    K0 = np.array([[994.978, 0, 311.193], [0, 994.978, 254.877], [0, 0, 1]])
    K1 = K0.copy()
    K1[0, 2] += 31.086
    write_calib(path, StereoCalib(K0, K1, 31.086, 193.001, 741, 500, 64))
    return Path(path)


def test_metrics_count_holes_as_bad():
    gt = np.full((10, 10), 10.0)
    gt[0, :] = np.nan  # unknown ground truth: ignored
    pred = gt.copy()
    pred[1, :5] += 3.0  # 5 errors of 3 px
    pred[2, :2] = np.nan  # 2 holes
    pred[3, 0] += 0.75  # one error between 0.5 and 1
    m = disparity_metrics(pred, gt)
    assert m["pixels"] == 90
    assert m["invalid"] == pytest.approx(200 / 90)
    assert m["bad-2"] == pytest.approx(700 / 90)
    assert m["bad-0.5"] == pytest.approx(800 / 90)
    assert m["bad-2-sparse"] == pytest.approx(500 / 88)
    assert m["avgerr"] == pytest.approx((15 + 0.75) / 88)
    nonocc = np.ones_like(gt, bool)
    nonocc[1] = False
    assert evaluate(pred, gt, nonocc)["nonocc"]["bad-2"] == pytest.approx(200 / 80)
    # nothing predicted: every pixel bad, and the figures over predicted pixels null (strict JSON has no NaN)
    holes = disparity_metrics(np.full_like(gt, np.nan), gt)
    assert holes["invalid"] == 100.0 and holes["bad-0.5"] == 100.0
    assert holes["avgerr"] is None and holes["rms"] is None and holes["bad-2-sparse"] is None
    json.dumps(holes, allow_nan=False)


def test_gee_recovers_a_known_shift():
    rng = np.random.default_rng(0)
    right = (rng.random((60, 120)) * 255).astype(np.uint8)
    left = np.roll(right, 6, axis=1)  # x_left = x_right + 6
    result = gee_disparity(left, right, GEEConfig(num_disparities=16, window=5, smoothing_iterations=2))
    inner = result.disparity[:, 20:]
    assert np.nanmedian(inner) == 6
    assert np.mean(inner == 6) > 0.95
    assert result.reliability > 0


def test_best_is_repeatable(motorcycle):
    """The weighted median of `best`, guided by a colour image, gave other values on each call (OpenCV 5.0)."""
    from mvrecon.stereo.best import weighted_median

    left = motorcycle[0]
    d = (np.random.default_rng(0).random(left.shape[:2]) * 60).astype(np.float32)
    first = weighted_median(d, left, 7, 25.5)
    assert np.array_equal(first, weighted_median(d, left, 7, 25.5)) and not np.array_equal(first, d)


def test_three_methods_on_motorcycle(motorcycle, motorcycle_best):
    """Acceptance: bad-2.0 on all valid pixels, holes counted as bad (measured: gee 25.3, sgbm 18.4, best 5.4)."""
    left, right, gt = motorcycle
    gee = evaluate(gee_disparity(left, right, GEEConfig(num_disparities=64)).disparity, gt)["all"]
    sgbm = evaluate(sgbm_disparity(left, right, SGBMConfig(num_disparities=64)), gt)["all"]
    best = evaluate(motorcycle_best, gt)["all"]
    assert best["bad-2"] <= 12.0
    assert best["invalid"] == 0.0
    assert sgbm["bad-2"] < 21.0
    assert gee["bad-2"] < 30.0
    assert best["bad-2"] < sgbm["bad-2"] < gee["bad-2"]


def test_best_left_edge_band_is_filled_not_zero(motorcycle, motorcycle_best):
    """In columns 0-63 the search range 0..64 reaches outside the right image. Matches against its border columns
    can pass the left-right check there and spread as disparity 0 where the ground truth is 7 px or more; the band
    is cleared and filled from its right (0 pixels at 0, band bad-2 2.7 %)."""
    gt = motorcycle[2]
    band, gt_band = motorcycle_best[:, :64], gt[:, :64]
    known = np.isfinite(gt_band)
    assert np.isfinite(band).all() and band.min() >= 1.0
    assert np.mean(np.abs(band[known] - gt_band[known]) > 2) < 0.05


def test_a_wrong_match_at_the_left_edge_does_not_stop_the_band():
    """A pixel's own disparity (0 at column 0) must not decide that it is visible: the surface on its right does."""
    from mvrecon.stereo.best import clear_left_border, fill_holes_background, remove_speckles

    row = np.full((1, 20), 9.0, np.float32)
    row[0, 1:9] = np.nan
    row[0, 0] = 0.0  # passed the left-right check, but the surface to its right (d = 9) cannot be seen from x < 9
    assert np.isnan(clear_left_border(row)[0, 0])
    np.testing.assert_array_equal(fill_holes_background(clear_left_border(row)), np.full((1, 20), 9.0))
    chain = np.repeat(row, 3, axis=0)
    chain[0, :3] = [0.0, 0.0, 0.5]  # a chain of such matches (the first stops the band at the second): a speckle
    kept = remove_speckles(chain, 20, 1.0)
    assert np.isnan(kept[0, :3]).all() and np.isfinite(kept[:, 9:]).all()


def test_best_on_cones_non_occluded(tmp_path):
    """Cones 2003 through the CLI: already rectified, float TIFF ground truth (0 = unknown), occlusion mask."""
    if not CONES.is_dir():
        pytest.skip(f"Cones pair not found at {CONES}")
    out = tmp_path / "cones"
    assert main(["stereo", str(CONES / "left.png"), str(CONES / "right.png"), "-o", str(out), "--rectified",
                 "--gt", str(CONES / "disp_left.tif"), "--mask", str(CONES / "occlusion.png"),
                 "--min-disparity", "0", "--num-disparities", "64", "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["metrics"]["nonocc"]["pixels"] == pytest.approx(0.85 * 450 * 375, rel=0.02)
    assert report["metrics"]["nonocc"]["bad-2"] < 5.0  # measured 2.6
    assert report["metrics"]["all"]["bad-2"] < 12.0  # measured 7.0
    assert not (out / "cloud.ply").exists()  # no calibration, no metric depth


def test_cli_on_middlebury_motorcycle(tmp_path):
    from mvrecon.io.pfm import read_pfm
    from mvrecon.io.ply import read_ply_points

    if not MOTO.is_dir():
        pytest.skip(f"Middlebury Motorcycle not found at {MOTO}")
    calib = moto_calib(tmp_path / "calib.txt")
    out = tmp_path / "out"
    code = main(["stereo", str(MOTO / "motorcycle_left.png"), str(MOTO / "motorcycle_right.png"), "-o", str(out),
                 "--calib", str(calib), "--method", "sgbm", "--gt", str(MOTO / "motorcycle_disp.npz"), "-q"])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert report["inliers"] > 500 and report["sampson_median_px"] < 1.0
    assert report["opencv"]["sampson_median_px_of_our_inliers"] < 1.0
    assert report["vertical_disparity_px"]["median"] < 0.5  # the pair is rectified
    assert report["disparity_range"] == [0, 64]
    # SGBM's figures (measured 18.35, 13.5 % holes), not `best`'s (5.39, no holes): the --method given is used
    assert 14.0 < report["metrics"]["all"]["bad-2"] < 21.0 and report["metrics"]["all"]["invalid"] > 5.0
    gt = np.load(MOTO / "motorcycle_disp.npz")["arr_0"]
    c = read_calib(calib)
    depth = read_pfm(out / "depth.pfm")
    gt_depth = c.focal * c.baseline / (gt + c.doffs)
    both = np.isfinite(depth) & np.isfinite(gt)
    rel = np.abs(depth[both] - gt_depth[both]) / gt_depth[both]
    assert np.median(rel) < 0.01  # depth Z = f B / (d + doffs) matches the ground truth's depth
    points, colors = read_ply_points(out / "cloud.ply")
    assert len(points) == report["points"] > 0.7 * gt.size and colors is not None
    for name in ("matches_epipolar.png", "rectified_pair.png", "disparity_view.png", "depth_view.png",
                 "error_map.png"):
        assert (out / name).stat().st_size > 10_000
    # the 16-bit PNG (KITTI: 256 d, 0 = hole) holds the PFM's disparities, pixel for pixel
    import cv2

    png = cv2.imread(str(out / "disparity.png"), cv2.IMREAD_UNCHANGED)
    pfm = read_pfm(out / "disparity.pfm")
    assert report["disparity_png"] and png.dtype == np.uint16 and png.shape == pfm.shape == gt.shape
    assert np.array_equal(png == 0, ~np.isfinite(pfm) | (pfm < 1 / 512))
    np.testing.assert_allclose(png[png > 0] / 256, pfm[png > 0], atol=1 / 512 + 1e-6)


def test_a_rerun_reuses_the_stages_done(tmp_path, capsys, monkeypatch, motorcycle):
    """Ctrl-C during the last figure, then the same command: the SIFT matches, the disparity and the figures done
    are reused and the outputs are those of an uninterrupted run; another setting, method or input is recomputed."""
    import cv2

    import mvrecon.stereo.figures as figures
    import mvrecon.stereo.pipeline as pipeline
    from mvrecon.io.pfm import read_pfm

    left, right, gt = (cv2.resize(a, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA) for a in motorcycle)
    cv2.imwrite(str(tmp_path / "l.png"), left[..., ::-1])
    cv2.imwrite(str(tmp_path / "r.png"), right[..., ::-1])
    np.savez(tmp_path / "gt.npz", np.where(np.isfinite(gt), gt / 4, np.inf))
    calls = []

    def counted(name):
        function = getattr(pipeline, name)
        monkeypatch.setattr(pipeline, name, lambda *a, **k: calls.append(name) or function(*a, **k))

    for name in ("sift_matches", "best_disparity", "gee_disparity"):
        counted(name)

    def stereo(out, *extra):
        calls.clear()
        code = main(["stereo", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "-o", str(tmp_path / out),
                     "--rectified", "--gt", str(tmp_path / "gt.npz"), "-q", *extra])
        return code, json.loads((tmp_path / out / "report.json").read_text()) if code == 0 else None

    code, reference = stereo("reference")
    assert code == 0 and calls == ["sift_matches", "best_disparity"] and reference["reused"] == []
    draw = figures.error_map_figure

    def interrupt(*args):
        raise KeyboardInterrupt
    monkeypatch.setattr(figures, "error_map_figure", interrupt)
    capsys.readouterr()
    assert stereo("out")[0] == 130
    assert capsys.readouterr().err == ("mvrecon: interrupted; the matches, disparities and figures done are kept in "
                                       "the output folder; rerun the same command to continue\n")
    assert not (tmp_path / "out" / "error_map.png").exists() and not list((tmp_path / "out").glob(".*partial*"))
    monkeypatch.setattr(figures, "error_map_figure", draw)
    code, report = stereo("out")
    assert code == 0 and calls == []  # neither SIFT nor the disparity again
    assert "disparity_best" in report["reused"] and "error_map.png" not in report["reused"]
    assert report["metrics"] == reference["metrics"] and report["matches"] == reference["matches"]
    assert (tmp_path / "out" / "disparity.pfm").read_bytes() == (tmp_path / "reference" / "disparity.pfm").read_bytes()
    assert (tmp_path / "out" / "error_map.png").is_file()
    # another method: computed, and each method keeps its own disparity; another search range: computed
    assert stereo("out", "--method", "gee")[0] == 0 and calls == ["gee_disparity"]
    code, report = stereo("out")
    assert code == 0 and calls == [] and report["metrics"] == reference["metrics"]
    assert stereo("out", "--num-disparities", "40")[0] == 0 and calls == ["best_disparity"]
    # another right image (one pixel changed): everything from the matches on is computed again
    right[0, 0] = 255 - right[0, 0]
    cv2.imwrite(str(tmp_path / "r.png"), right[..., ::-1])
    assert stereo("out")[0] == 0 and calls == ["sift_matches", "best_disparity"]
    assert np.isfinite(read_pfm(tmp_path / "out" / "disparity.pfm")).all()


def test_uncalibrated_rectification_of_a_rotated_pair(tmp_path, motorcycle):
    """Turn and shift the right view: Hartley rectification must bring matches back onto common rows."""
    import cv2

    from mvrecon.stereo.pipeline import StereoConfig, run_stereo

    left, right = (cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) for img in motorcycle[:2])
    h, w = right.shape[:2]
    M = cv2.getRotationMatrix2D((w / 2, h / 2), 3.0, 1.0)
    M[1, 2] += 6
    warped = cv2.warpAffine(right, M, (w, h))
    cv2.imwrite(str(tmp_path / "l.png"), left[..., ::-1])
    cv2.imwrite(str(tmp_path / "r.png"), warped[..., ::-1])
    report = run_stereo(StereoConfig(method="sgbm"), tmp_path / "l.png", tmp_path / "r.png", tmp_path / "out")
    assert report["rectification"].startswith("uncalibrated")
    assert report["vertical_disparity_px"]["median"] < 0.5
    assert report["vertical_disparity_px"]["p95"] < 1.5
    assert report["invalid_percent"] < 40
    assert not (tmp_path / "out" / "cloud.ply").exists()  # no metric depth without calibration


def test_bad_input_gives_one_line_errors(tmp_path, capsys, motorcycle):
    import cv2

    left, right, _ = motorcycle
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    cv2.imwrite(str(tmp_path / "small.png"), right[:400, :600])
    cv2.imwrite(str(tmp_path / "blank.png"), np.full_like(left, 128))
    cv2.imwrite(str(tmp_path / "blank2.png"), np.full_like(left, 129))
    np.savez(tmp_path / "gt.npz", np.zeros(left.shape[:2], np.float32))
    out = str(tmp_path / "out")

    def error(args):
        capsys.readouterr()
        assert main(["stereo", *args, "-o", out, "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("mvrecon: error:") and "\n" not in err
        return err

    assert "differs from the left image" in error([str(tmp_path / "l.png"), str(tmp_path / "small.png")])
    assert "calib.txt: calibration file not found" in error(
        [str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--calib", str(tmp_path / "calib.txt")])
    assert "SIFT matches" in error([str(tmp_path / "blank.png"), str(tmp_path / "blank2.png")])
    (tmp_path / "bad.txt").write_text("hello=1\n")
    assert "not a Middlebury calib.txt" in error(
        [str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--calib", str(tmp_path / "bad.txt")])
    pair = [str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--rectified", "--method", "sgbm",
            "--gt", str(tmp_path / "gt.npz")]
    assert "bad.txt: cannot read the mask image" in error(pair + ["--mask", str(tmp_path / "bad.txt")])
    assert "small.png: mask is 600x400, images are" in error(pair + ["--mask", str(tmp_path / "small.png")])


def small_pair(folder, shift: int = 6) -> tuple[Path, Path]:
    """A 240x160 textured pair, already rectified, every pixel at disparity `shift` (x_left = x_right + shift)."""
    import cv2

    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur((rng.random((160, 260)) * 255).astype(np.float32), (0, 0), 2)
    base = cv2.normalize(base, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    left, right = Path(folder) / "l.png", Path(folder) / "r.png"
    cv2.imwrite(str(left), base[:, 10 - shift:250 - shift])
    cv2.imwrite(str(right), base[:, 10:250])
    return left, right


def small_calib(path, width: int = 240, height: int = 160, ndisp: int = 16) -> Path:
    K = np.array([[200.0, 0, 119.5], [0, 200, 79.5], [0, 0, 1]])
    write_calib(path, StereoCalib(K, K, 0.0, 10.0, width, height, ndisp))
    return Path(path)


CAMERA_TOML = """[camera]
model = "OPENCV"
width = 640
height = 512
params = [512.0, 512.0, 320.0, 256.0, 0, 0, 0, 0]

[camera_right]
model = "OPENCV"
width = 640
height = 512
params = [512.0, 512.0, 320.0, 256.0, 0, 0, 0, 0]

[stereo]
R = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
t = [-1, 0, 0]
"""


def test_a_calibration_for_another_image_size_is_refused(tmp_path, capsys):
    """calib.txt and camera.toml hold f, cx, cy (and ndisp) in the pixels of the images they were made for: another
    size gave wrong depth and search range with exit 0 (the rendered scene's 640x480 calib.txt on Motorcycle's
    741x500: 30 % holes; a 640x512 rig file: rows 27 px apart). Refused before any work, OUT not made."""
    left, right = small_pair(tmp_path)
    out = tmp_path / "out"

    def error(*extra):
        capsys.readouterr()
        assert main(["stereo", str(left), str(right), "-o", str(out), "-q", *extra]) == 2
        return capsys.readouterr().err

    calib = small_calib(tmp_path / "calib.txt", 640, 480)
    assert error("--calib", str(calib)) == (f"mvrecon: error: {calib}: made for 640x480 images, these are 240x160 "
                                            f"({left})\n")
    # no width/height in the file: a principal point outside the image tells another size
    (tmp_path / "nosize.txt").write_text("cam0=[500 0 319.5; 0 500 239.5; 0 0 1]\n"
                                         "cam1=[500 0 319.5; 0 500 239.5; 0 0 1]\nbaseline=10\n")
    assert error("--calib", str(tmp_path / "nosize.txt")) == (
        f"mvrecon: error: {tmp_path / 'nosize.txt'}: no width/height given and its principal point (319.5, 239.5) "
        f"lies outside these 240x160 images ({left}): made for other images?\n")
    camera = tmp_path / "camera.toml"
    camera.write_text(CAMERA_TOML)
    assert error("--camera", str(camera)) == (f"mvrecon: error: {camera}: [camera] made for 640x512 images, these "
                                              f"are 240x160 ({left})\n")
    assert not out.exists()


def test_a_calibration_file_that_cannot_be_parsed_is_one_line(tmp_path, capsys):
    """A binary file given as --calib raised UnicodeDecodeError with a traceback (exit 1)."""
    left, right = small_pair(tmp_path)

    def error(*extra):
        capsys.readouterr()
        assert main(["stereo", str(left), str(right), "-o", str(tmp_path / "out"), "-q", *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("mvrecon: error: ") and err.count("\n") == 1
        return err

    assert f"{left}: not a Middlebury calib.txt (not text)" in error("--calib", str(left))
    assert f"{left}: not a camera file from `mvrecon calibrate` (not text)" in error("--camera", str(left))
    bad = tmp_path / "bad.toml"
    for text, reason in (("[camera\nwidth = 3\n", "not TOML: "), ("[other]\nx = 1\n", "no [camera] table"),
                         (CAMERA_TOML.replace("width = 640\n", "", 1), "[camera] has no width"),
                         (CAMERA_TOML.replace("t = [-1, 0, 0]", "t = [-1, 0]"), "[stereo] needs R as 3x3")):
        bad.write_text(text)
        assert f"{bad}: not a camera file from `mvrecon calibrate` ({reason}" in error("--camera", str(bad))
    (tmp_path / "calib.txt").write_text("cam0=[0 0 1; 0 0 1; 0 0 1]\ncam1=[0 0 1; 0 0 1; 0 0 1]\nbaseline=1\n")
    assert "calib.txt: focal length 0 and baseline 1 must be positive" in error("--calib", str(tmp_path / "calib.txt"))


def test_the_same_image_twice_is_refused(tmp_path, capsys):
    """The same image as left and right ran F estimation and rectification on zero parallax, exit 0. Refused: the
    same file, a copy (identical pixels), and a copy moved by 0.3 px (the matches show no parallax)."""
    import shutil

    import cv2

    left, right = small_pair(tmp_path)
    shutil.copy(left, tmp_path / "copy.png")
    moved = cv2.warpAffine(cv2.imread(str(left)), np.float32([[1, 0, 0.3], [0, 1, 0]]), (240, 160),
                           borderMode=cv2.BORDER_REFLECT)
    cv2.imwrite(str(tmp_path / "moved.png"), moved)
    out = tmp_path / "out"

    def error(other):
        capsys.readouterr()
        assert main(["stereo", str(left), str(other), "-o", str(out), "-q"]) == 2
        return capsys.readouterr().err

    assert error(left) == (f"mvrecon: error: {left}: given as both left and right image; stereo needs two views from "
                           "different positions (no parallax, no depth)\n")
    assert error(tmp_path / "copy.png") == (f"mvrecon: error: {left}, {tmp_path / 'copy.png'}: identical pixels; "
                                            "stereo needs two views from different positions (no parallax, no depth)\n")
    assert not out.exists()
    err = error(tmp_path / "moved.png")
    assert err.startswith(f"mvrecon: error: {left}, {tmp_path / 'moved.png'}: no parallax: the ") and err.endswith(
        " px between the images (0.5 px at least); stereo needs two views from different positions\n")
    assert main(["stereo", str(left), str(right), "-o", str(out), "-q", "--method", "sgbm"]) == 0  # 6 px: fine


def test_a_swapped_or_misaligned_pair_is_flagged(tmp_path, caplog):
    """Left and right exchanged: every match disparity is negative, calib.txt's range 0..ndisp misses them all (the
    rendered pair: 58.6 % holes), so a warning goes to the log and report.json. With --rectified the range clipped
    at 0 keeps 16 disparities, so SGBM runs. Rows that do not line up are flagged too;
    the pair in the right order gets no warning."""
    import logging

    import cv2

    left, right = small_pair(tmp_path)
    calib = small_calib(tmp_path / "calib.txt")
    cv2.imwrite(str(tmp_path / "low.png"), np.roll(cv2.imread(str(right)), -5, axis=0))  # rows 5 px apart

    def warnings(name, *args):
        caplog.clear()
        caplog.set_level(logging.WARNING, logger="mvrecon")
        assert main(["stereo", *map(str, args), "-o", str(tmp_path / name), "-q", "--method", "sgbm"]) == 0
        report = json.loads((tmp_path / name / "report.json").read_text())
        assert [f"warning: {w}" for w in report["warnings"]] == [r.getMessage() for r in caplog.records]
        return report

    assert warnings("ok", left, right, "--calib", calib)["warnings"] == []
    swapped = ("100 % of the inlier matches have a negative disparity (x_left - x_right, median -6.0 px): the left and "
               "right images are probably swapped; give them the other way round")
    report = warnings("swap", right, left, "--calib", calib)
    assert report["warnings"] == [swapped] and report["match_disparities_px"]["negative_percent"] == 100
    assert warnings("swap_rect", right, left, "--rectified")["warnings"] == [swapped]
    # the rendered pair swapped (disparities -36..-16) left a range of -16 disparities after the clip at 0
    from mvrecon.stereo.pipeline import StereoConfig, search_range

    assert search_range(StereoConfig(), None, np.full(50, -25.0), nonnegative=True) == (0, 16)
    assert warnings("ok_rect", left, right, "--rectified")["warnings"] == []
    (vertical,) = warnings("low", left, tmp_path / "low.png", "--rectified")["warnings"]
    assert vertical.startswith("rows do not line up after rectification (the inlier matches lie a median 5.0 px "
                               "apart vertically")


def small_camera(path, t=(-1, 0, 0), right_cx: float = 120.0) -> Path:
    """A rig file for `small_pair`'s 240x160 images: two equal pinhole cameras side by side (R = I, t along x), so
    the calibrated rectification keeps the images as they are; `right_cx` moves the right principal point."""
    text = CAMERA_TOML.replace("width = 640", "width = 240").replace("height = 512", "height = 160")
    text = text.replace("320.0, 256.0", "120.0, 80.0", 1).replace("320.0, 256.0", f"{right_cx}, 80.0", 1)
    Path(path).write_text(text.replace("t = [-1, 0, 0]", f"t = {list(t)}"))
    return Path(path)


def test_camera_file_warnings(tmp_path, caplog):
    """--camera: the warnings of `judge_matches` for a rig file, in the log and in report.json. The pair in the rig's
    order gets none; swapped, its sign is judged on d + doffs; a file of a rig with a vertical baseline, or rows 5 px
    apart, give rows that do not line up (with the camera file's hint); a search range beside the matches is named."""
    import logging

    import cv2

    left, right = small_pair(tmp_path)
    rig = small_camera(tmp_path / "rig.toml")
    cv2.imwrite(str(tmp_path / "low.png"), np.roll(cv2.imread(str(right)), -5, axis=0))  # rows 5 px apart

    def warnings(name, first, second, camera, *extra):
        caplog.clear()
        caplog.set_level(logging.WARNING, logger="mvrecon")
        assert main(["stereo", str(first), str(second), "-o", str(tmp_path / name), "-q", "--method", "sgbm",
                     "--camera", str(camera), *extra]) == 0
        report = json.loads((tmp_path / name / "report.json").read_text())
        assert report["rectification"] == "calibrated (camera file)"
        assert [f"warning: {w}" for w in report["warnings"]] == [r.getMessage() for r in caplog.records]
        return report

    report = warnings("ok", left, right, rig)
    assert report["warnings"] == [] and report["geometry"]["doffs"] == 0.0
    assert report["match_disparities_px"]["median"] == pytest.approx(6.0, abs=0.1)
    assert warnings("swap", right, left, rig)["warnings"] == [
        "100 % of the inlier matches have a negative disparity (x_left - x_right + doffs, median -6.0 px): the left "
        "and right images are probably swapped; give them the other way round"]
    # principal points 10 px apart: d = -6 px is d + doffs = 4 px, a point in front of the rig (Z = f B / 4)
    converging = warnings("doffs", right, left, small_camera(tmp_path / "doffs.toml", right_cx=130.0))
    assert converging["warnings"] == [] and converging["geometry"]["doffs"] == 10.0
    rows = ("rows do not line up after rectification (the inlier matches lie a median {} px apart vertically, under "
            "2 px expected): the camera file may be another rig's, or LEFT and RIGHT swapped; the disparity map is "
            "likely wrong")
    assert warnings("low", left, tmp_path / "low.png", rig)["warnings"] == [rows.format("5.0")]
    vertical = small_camera(tmp_path / "vertical.toml", t=(0, -1, 0))  # a rig with one camera above the other
    assert warnings("vertical", left, right, vertical)["warnings"] == [rows.format("6.0")]
    assert warnings("range", left, right, rig, "--min-disparity", "20", "--num-disparities", "16")["warnings"] == [
        "100 % of the inlier matches' disparities (1-99 %: 6.0 to 6.0 px) lie outside the search range [20, 36]: "
        "those surfaces come out as holes or wrong; give --min-disparity and --num-disparities"]


def test_a_run_refused_after_the_matches_leaves_no_folder_it_made(tmp_path, capsys):
    """The parallax check needs the matches, so it runs after OUT (and OUT/.stages) have been made: a refused run
    removes them when it made them; a folder the user made, or an earlier run's, stays."""
    import cv2

    left, right = small_pair(tmp_path)
    moved = tmp_path / "moved.png"  # the left image moved by 0.3 px: no parallax
    cv2.imwrite(str(moved), cv2.warpAffine(cv2.imread(str(left)), np.float32([[1, 0, 0.3], [0, 1, 0]]), (240, 160),
                                           borderMode=cv2.BORDER_REFLECT))

    def refused(out):
        capsys.readouterr()
        assert main(["stereo", str(left), str(moved), "-o", str(out), "-q", "--method", "sgbm"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(f"mvrecon: error: {left}, {moved}: no parallax: "), err

    refused(tmp_path / "new" / "out")
    assert not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()
    refused(tmp_path / "mine")
    assert list((tmp_path / "mine").iterdir()) == []
    assert main(["stereo", str(left), str(right), "-o", str(tmp_path / "done"), "-q", "--method", "sgbm"]) == 0
    before = sorted(p.relative_to(tmp_path / "done") for p in (tmp_path / "done").rglob("*"))
    refused(tmp_path / "done")
    assert sorted(p.relative_to(tmp_path / "done") for p in (tmp_path / "done").rglob("*")) == before


def test_mask_without_gt_is_refused(tmp_path, capsys):
    left, right = small_pair(tmp_path)
    assert main(["stereo", str(left), str(right), "-o", str(tmp_path / "out"), "--mask", str(left), "-q"]) == 2
    assert capsys.readouterr().err == ("mvrecon: error: --mask goes with --gt: it selects the non-occluded pixels "
                                       "scored against the ground truth\n")


def test_output_folder_and_search_range_are_checked_first(tmp_path, capsys, motorcycle):
    import cv2

    left, right, _ = motorcycle
    data = tmp_path / "data"
    data.mkdir()
    cv2.imwrite(str(data / "l.png"), left)
    cv2.imwrite(str(data / "r.png"), right)
    pair = [str(data / "l.png"), str(data / "r.png"), "--rectified", "--method", "sgbm", "-q"]
    for extra, message in ((["-o", str(data)], f"{data}: the output folder must differ from the folder of "
                                                f"{data / 'l.png'}"),
                           (["-o", str(tmp_path / "out"), "--num-disparities", "100000"],
                            f"--num-disparities 100000: beyond the image width (741 px, {data / 'l.png'})"),
                           (["-o", str(tmp_path / "out"), "--min-disparity", "-741"],
                            f"--min-disparity -741: beyond the image width (741 px, {data / 'l.png'})")):
        capsys.readouterr()
        assert main(["stereo", *pair, *extra]) == 2
        assert capsys.readouterr().err == f"mvrecon: error: {message}\n"
    assert sorted(p.name for p in data.iterdir()) == ["l.png", "r.png"] and not (tmp_path / "out").exists()


def test_a_search_range_too_large_for_memory_is_one_line(tmp_path, capsys, monkeypatch, motorcycle):
    import cv2

    import mvrecon.stereo.pipeline as pipeline

    def out_of_memory(*args, **kwargs):
        raise MemoryError  # numpy's ArrayMemoryError for a cost volume that does not fit
    monkeypatch.setattr(pipeline, "compute_disparity", out_of_memory)
    left, right, _ = motorcycle
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    assert main(["stereo", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "-o", str(tmp_path / "out"),
                 "--rectified", "--num-disparities", "700", "-q"]) == 2
    assert capsys.readouterr().err == (f"mvrecon: error: {tmp_path / 'l.png'}: not enough memory for 700 disparities "
                                       "of a 741x500 image; give a smaller --num-disparities or smaller images\n")


def test_long_disparity_loops_show_their_progress(capsys, caplog, monkeypatch):
    import logging

    from mvrecon import progress

    monkeypatch.setattr(progress, "_enabled", True)
    caplog.set_level(logging.INFO, logger="mvrecon")
    rng = np.random.default_rng(0)
    right = (rng.random((40, 90)) * 255).astype(np.uint8)
    left = np.roll(right, 5, axis=1)
    best = best_disparity(left, right, BestConfig(num_disparities=16, median_radius=0))
    assert np.median(best[:, 20:]) == pytest.approx(5, abs=0.5)
    err = capsys.readouterr().err
    # every scanline step of the 8 SGM paths (2 W + 6 H), and every disparity of the two loops over them
    for text in ("SGM paths: 100% |####################| 420/420", "census cost: 100% |####################| 16/16",
                 "right disparities: 100% |####################| 16/16"):
        assert text in err, err
    gee_disparity(left, right, GEEConfig(num_disparities=12, window=5, smoothing_iterations=2))
    assert "GEE energies: 100% |####################| 12/12" in capsys.readouterr().err
