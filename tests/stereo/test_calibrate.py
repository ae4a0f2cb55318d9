"""Chessboard calibration: a board rendered through known intrinsics and distortion must be recovered (focal
lengths within 0.5 %, the principal point within 0.4 px, each distortion coefficient within a stated bound); the
stereo rig of the ximea set is compared with its author's OpenCV result and rectifies a pair it did not see;
camera.toml round-trips."""

import functools
from pathlib import Path

import numpy as np
import pytest

from mvrecon.cli import main
from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.stereo.calibrate import (
    CalibrationConfig,
    calibrate_mono,
    calibrate_stereo,
    read_camera_toml,
    stereo_pairs,
    write_camera_toml,
)
from tests.helpers import DATA

XIMEA = DATA / "calib_stereo_chessboard_ximea"

K_TRUE = np.array([[620.0, 0, 318.0], [0, 615.0, 244.0], [0, 0, 1]])
DIST_TRUE = np.array([-0.18, 0.06, 0.0008, -0.0005])
BOARD = (9, 6)  # inner corners
SQUARE = 30.0  # mm


@functools.cache
def board_texture(px_per_mm: float = 4.0) -> tuple[np.ndarray, float]:
    """White-margined (BOARD + 1) squares chessboard image and its pixels per mm."""
    cols, rows = BOARD[0] + 1, BOARD[1] + 1
    margin = SQUARE
    w, h = int((cols * SQUARE + 2 * margin) * px_per_mm), int((rows * SQUARE + 2 * margin) * px_per_mm)
    y, x = np.mgrid[0:h, 0:w] / px_per_mm - margin
    inside = (x >= 0) & (x < cols * SQUARE) & (y >= 0) & (y < rows * SQUARE)
    black = ((np.floor(x / SQUARE) + np.floor(y / SQUARE)) % 2 == 0) & inside
    import cv2

    texture = np.where(black, 20, 235).astype(np.float32)
    return cv2.GaussianBlur(texture, (0, 0), px_per_mm * 0.6), px_per_mm  # ~1 image pixel of optical blur


@functools.cache
def undistorted_rays(size=(640, 480)) -> np.ndarray:
    """Normalised undistorted coordinates of every pixel centre of the distorted image."""
    import cv2

    w, h = size
    px = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1).reshape(-1, 1, 2)
    return cv2.undistortPoints(px, K_TRUE, DIST_TRUE).reshape(-1, 2)


def render_view(rvec, tvec, size=(640, 480), seed=0) -> np.ndarray:
    """Image of the board (its first inner corner at the board origin) through K_TRUE and DIST_TRUE: every output
    pixel is undistorted, its ray intersected with the board plane (a homography), and the texture sampled."""
    import cv2

    texture, ppm = board_texture()
    w, h = size
    norm = undistorted_rays(size)
    R = angle_axis_to_rotmat(rvec)
    H = np.column_stack([R[:, 0], R[:, 1], tvec])  # board (X, Y, 1) -> normalised camera ray
    board = np.column_stack([norm, np.ones(len(norm))]) @ np.linalg.inv(H).T
    bx, by = board[:, 0] / board[:, 2], board[:, 1] / board[:, 2]
    # texture pixel of board point (X, Y): (X + SQUARE + SQUARE) * ppm (margin, plus the first square)
    mapx = ((bx + 2 * SQUARE) * ppm).reshape(h, w).astype(np.float32)
    mapy = ((by + 2 * SQUARE) * ppm).reshape(h, w).astype(np.float32)
    img = cv2.remap(texture, mapx, mapy, cv2.INTER_LINEAR, borderValue=235)
    img += np.random.default_rng(seed).normal(0, 2.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


@functools.cache
def synthetic_views(n=12):
    rng = np.random.default_rng(7)
    views = {}
    centre = np.array([(BOARD[0] - 1) * SQUARE / 2, (BOARD[1] - 1) * SQUARE / 2, 0])
    for i in range(n):
        rvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        R = angle_axis_to_rotmat(rvec)
        target = np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(420, 560)])
        tvec = target - R @ centre
        views[f"view{i:02d}.png"] = render_view(rvec, tvec, seed=i)
    return views


def test_recovers_rendered_intrinsics_within_half_percent(tmp_path):
    views = synthetic_views()
    result = calibrate_mono(views, CalibrationConfig(square=SQUARE))  # board size found automatically
    assert result.board == BOARD
    K, dist = result.camera.opencv()
    assert abs(K[0, 0] - 620.0) / 620.0 < 0.005 and abs(K[1, 1] - 615.0) / 615.0 < 0.005
    assert abs(K[0, 2] - 318.0) < 0.4 and abs(K[1, 2] - 244.0) < 0.4  # measured 0.17 and 0.23 px
    # k2 is the least determined by a board filling part of the view (measured errors: k1 0.0012, k2 0.007,
    # p1 7e-5, p2 5e-5)
    np.testing.assert_array_less(np.abs(dist[:4] - DIST_TRUE), [0.005, 0.015, 3e-4, 3e-4])
    assert result.rms_px < 0.3
    assert len(result.per_view_rms_px) + len(result.dropped) == len(views)
    write_camera_toml(tmp_path / "camera.toml", result, CalibrationConfig(square=SQUARE))
    cam = read_camera_toml(tmp_path / "camera.toml")
    # the file holds the camera in COLMAP's pixel convention (OpenCV's principal point + 0.5), not OpenCV's K
    np.testing.assert_allclose(cam["left"].params[2:4], [K[0, 2] + 0.5, K[1, 2] + 0.5])
    np.testing.assert_allclose(cam["left"].params, result.camera.params)
    assert cam["stereo"] is None


def test_outlier_view_is_dropped():
    import cv2

    views = dict(list(synthetic_views().items())[:8])
    name = "view03.png"
    views[name] = cv2.GaussianBlur(views[name], (0, 0), 2.5)  # a badly blurred view
    warp = views[name].astype(np.float32)
    h, w = warp.shape
    mapx, mapy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    mapx += (3 * np.sin(mapy / 15)).astype(np.float32)  # wavy lens distortion no model explains
    views[name] = cv2.remap(warp, mapx, mapy, cv2.INTER_LINEAR).astype(np.uint8)
    result = calibrate_mono(views, CalibrationConfig(board=BOARD, square=SQUARE))
    assert result.dropped == [name]  # that view only, and the others still give the true camera
    K, _ = result.camera.opencv()
    assert abs(K[0, 0] - 620.0) / 620.0 < 0.01 and abs(K[1, 1] - 615.0) / 615.0 < 0.01
    assert result.rms_px < 0.3


def test_stereo_pairs_by_name():
    lefts, rights, pairs = stereo_pairs(["left01.jpg", "right01.jpg", "left02.jpg", "right03.jpg", "x.png",
                                         "L/left/a.png", "L/right/a.png"])
    assert sorted(pairs) == [("L/left/a.png", "L/right/a.png"), ("left01.jpg", "right01.jpg")]
    assert sorted(lefts) == ["L/left/a.png", "left01.jpg"]


def test_ximea_stereo_against_authors_result(tmp_path):
    import cv2

    if not XIMEA.is_dir():
        pytest.skip(f"ximea chessboard set not found at {XIMEA}")
    names = sorted(p.name for p in (XIMEA / "images").glob("*.jpg"))
    lefts, rights, pairs = stereo_pairs(names)
    pairs = pairs[::2]  # 13 of the 25 pairs keep the test fast
    read = {n: cv2.imread(str(XIMEA / "images" / n), cv2.IMREAD_GRAYSCALE) for p in pairs for n in p}
    result = calibrate_stereo({a: read[a] for a, _ in pairs}, {b: read[b] for _, b in pairs}, pairs,
                              CalibrationConfig(square=1.0))
    fs = cv2.FileStorage(str(XIMEA / "intrinsics.yml"), cv2.FILE_STORAGE_READ)
    M1, M2 = fs.getNode("M1").mat(), fs.getNode("M2").mat()
    fe = cv2.FileStorage(str(XIMEA / "extrinsics.yml"), cv2.FILE_STORAGE_READ)
    R_ref, T_ref = fe.getNode("R").mat(), fe.getNode("T").mat().ravel()
    K1, _ = result.left.camera.opencv()
    K2, _ = result.right.camera.opencv()
    assert result.left.board == (9, 6)
    assert abs(K1[0, 0] - M1[0, 0]) / M1[0, 0] < 0.03
    assert abs(K2[0, 0] - M2[0, 0]) / M2[0, 0] < 0.03
    from mvrecon.geometry.rotation import rotation_error_deg, vector_angle_deg

    assert rotation_error_deg(result.R, R_ref) < 1.0
    assert vector_angle_deg(result.t, T_ref) < 3.0
    assert result.rms_px < 1.0


def test_cli_calibrate_writes_the_camera_file_and_stereo_refuses_one_without_a_rig(tmp_path, capsys, caplog):
    import cv2

    views = dict(list(synthetic_views().items())[:8])
    folder = tmp_path / "boards"
    folder.mkdir()
    for name, img in views.items():
        cv2.imwrite(str(folder / name), img)
    cv2.imwrite(str(tmp_path / "whole.jpg"), views["view00.png"])
    whole = (tmp_path / "whole.jpg").read_bytes()
    (folder / "view99.jpg").write_bytes(whole[: len(whole) // 2])  # cut off: left out with a warning
    with caplog.at_level("WARNING"):
        camera = tmp_path / "new" / "camera.toml"  # its folder is made
        assert main(["calibrate", str(folder), "-o", str(camera), "--square", "30", "-q"]) == 0
    assert "skipping" in caplog.text and "view99.jpg" in caplog.text
    cam = read_camera_toml(camera)
    assert abs(cam["left"].params[0] - 620) / 620 < 0.005
    (folder / "view99.jpg").unlink()
    capsys.readouterr()
    assert main(["calibrate", str(tmp_path / "nothing"), "-o", str(tmp_path / "c.toml")]) == 2
    assert "mvrecon: error:" in capsys.readouterr().err
    assert main(["stereo", str(folder / "view00.png"), str(folder / "view01.png"), "-o", str(tmp_path / "s"),
                 "--camera", str(camera)]) == 2
    assert "no [stereo] section" in capsys.readouterr().err


def test_cli_stereo_calibration_rectifies_a_held_out_pair(tmp_path):
    """`calibrate --stereo` on 8 of the ximea pairs, then `stereo --camera` on a pair it did not see: the board's
    corners, found independently in the two rectified images, must lie on the same rows (26 px apart before)."""
    import json
    import shutil

    import cv2

    if not XIMEA.is_dir():
        pytest.skip(f"ximea chessboard set not found at {XIMEA}")
    boards = tmp_path / "boards"
    boards.mkdir()
    for k in range(1, 16, 2):
        for side in ("left", "right"):
            shutil.copy(XIMEA / "images" / f"{side}{k:02d}.jpg", boards)
    camera = tmp_path / "camera.toml"
    assert main(["calibrate", str(boards), "--stereo", "-o", str(camera), "-q"]) == 0
    assert read_camera_toml(camera)["stereo"] is not None
    out = tmp_path / "s"
    assert main(["stereo", str(XIMEA / "images" / "left06.jpg"), str(XIMEA / "images" / "right06.jpg"), "-o",
                 str(out), "--camera", str(camera), "--method", "sgbm", "-q"]) == 0
    assert json.loads((out / "report.json").read_text())["rectification"] == "calibrated (camera file)"
    rows = []
    for name in ("rectified_left.png", "rectified_right.png"):
        img = cv2.imread(str(out / name), cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(img, (9, 6))
        assert found, name
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
        rows.append(cv2.cornerSubPix(img, corners, (5, 5), (-1, -1), criteria).reshape(-1, 2)[:, 1])
    dy = np.abs(rows[0] - rows[1])
    assert np.median(dy) < 0.3 and dy.max() < 1.0  # measured 0.13 and 0.29 px


def _board_folder(folder, views) -> Path:
    import cv2

    folder.mkdir()
    for name, img in views.items():
        cv2.imwrite(str(folder / name), img)
    return folder


def test_cli_output_file_is_checked_before_the_work(tmp_path, capsys, monkeypatch):
    import mvrecon.commands.calibrate as calibrate

    folder = _board_folder(tmp_path / "boards", dict(list(synthetic_views().items())[:2]))
    original = (folder / "view00.png").read_bytes()

    def no_work(*args, **kwargs):
        raise AssertionError("calibrated before the output was checked")

    monkeypatch.setattr(calibrate, "calibrate_mono", no_work)
    for output, reason in ((folder / "view00.png", "is one of the input images"),
                           (folder / "view01.png" / "c.toml", f"cannot make folder {folder / 'view01.png'}"),
                           (Path("/proc/c.toml"), "cannot write in /proc"), (folder, "is a folder")):
        capsys.readouterr()
        assert main(["calibrate", str(folder), "-o", str(output), "-q"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"mvrecon: error: {output}: {reason}") and err.count("\n") == 1, err
    assert (folder / "view00.png").read_bytes() == original
    assert sorted(p.name for p in folder.iterdir()) == ["view00.png", "view01.png"]


def test_cli_calibration_errors_name_the_folder(tmp_path, capsys):
    import cv2

    views = synthetic_views()
    mixed = _board_folder(tmp_path / "mixed", {"a.png": views["view00.png"], "b.png": views["view01.png"],
                                               "c.png": cv2.resize(views["view02.png"], (320, 240))})
    blank = _board_folder(tmp_path / "blank", {f"{k}.png": np.full((240, 320), 128, np.uint8) for k in range(3)})
    few = _board_folder(tmp_path / "few", dict(list(views.items())[:2]))
    for folder, extra, message in (
            (mixed, [], "calibration images differ in size: 320x240 (e.g. c.png), 640x480 (e.g. a.png)"),
            (blank, [], "no chessboard found in the first 3 images; give --size CxR (inner corners)"),
            (few, ["--size", "9x6"], "only 2 views with a detected 9x6 board; 4 needed")):
        capsys.readouterr()
        assert main(["calibrate", str(folder), "-o", str(tmp_path / "c.toml"), "-q", *extra]) == 2
        assert capsys.readouterr().err == f"mvrecon: error: {folder}: {message}\n"
    assert not (tmp_path / "c.toml").exists()


def test_cli_calibrate_resumes_after_ctrl_c(tmp_path, monkeypatch, capsys, caplog):
    """Ctrl-C while the fifth board's corners are searched, then the same command: the board size and the four
    boards done are not searched again, and the camera file is byte for byte that of an uninterrupted run (the
    solvers run on one thread: on two, each run gave other 9th-10th digits). A board whose pixels changed is
    searched again."""
    import cv2

    import mvrecon.stereo.calibrate as calibrate

    folder = _board_folder(tmp_path / "boards", dict(list(synthetic_views().items())[:8]))
    searched, sized = [], []
    find_corners, detect_board_size = calibrate.find_corners, calibrate.detect_board_size

    def counted(gray, board):
        searched.append(1)
        if len(searched) == stop_at:
            raise KeyboardInterrupt
        return find_corners(gray, board)

    monkeypatch.setattr(calibrate, "find_corners", counted)
    monkeypatch.setattr(calibrate, "detect_board_size", lambda gray: sized.append(1) or detect_board_size(gray))

    def run(name):
        searched.clear()
        sized.clear()
        return main(["calibrate", str(folder), "-o", str(tmp_path / name), "--square", "30"])

    stop_at = None
    assert run("ref.toml") == 0 and len(searched) == 8 and len(sized) == 8
    stop_at = 5
    capsys.readouterr()
    assert run("cut.toml") == 130 and not (tmp_path / "cut.toml").exists()
    interrupted = capsys.readouterr().err.splitlines()[-1]
    stop_at = None
    with caplog.at_level("INFO", logger="mvrecon"):
        assert run("cut.toml") == 0
    assert len(searched) == 4 and len(sized) == 0  # view04 (cut off) to view07
    assert (tmp_path / "cut.toml").read_bytes() == (tmp_path / "ref.toml").read_bytes()
    assert interrupted == ("mvrecon: interrupted; the corners found are kept next to the camera file (in .stages); "
                           "rerun the same command to continue")
    assert "the corners of 4 of the 8 images and the board size search" in caplog.text
    img = cv2.imread(str(folder / "view06.png"), cv2.IMREAD_GRAYSCALE)
    img[0, 0] ^= 1
    cv2.imwrite(str(folder / "view06.png"), img)
    assert run("cut.toml") == 0 and len(searched) == 1 and len(sized) == 1  # view06 is one of the first eight
