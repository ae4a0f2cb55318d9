"""Chessboard camera calibration with OpenCV (Zhang's method), mono and stereo: the seed's "calibration toolkit".

Corners: OpenCV's classic detector refined by `cornerSubPix`, falling back to the sector-based detector; the board
size (inner corners) is found from the images when not given. Every view's RMS reprojection error is reported and
views far above the median are dropped before the final solve, because one blurred or mis-ordered view biases all
intrinsics. Results go to a small TOML file (`camera.toml`) in COLMAP's OPENCV model and pixel convention (top-left
pixel centre at (0.5, 0.5)); `mvrecon stereo --camera` reads it, and its `colmap_params` string is what
`--camera-model OPENCV --camera-params` takes.
"""

import logging
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.files import replace_whole
from ..progress import progress

log = logging.getLogger("mvrecon.calibrate")


@dataclass(frozen=True)
class CalibrationConfig:
    """board: inner corners (cols, rows) or None to detect; square: square size (the unit of the stereo baseline);
    outlier_factor/outlier_floor_px: a view is dropped when its RMS error exceeds factor * median and floor;
    min_views: fewer usable views is an error."""

    board: tuple[int, int] | None = None
    square: float = 1.0
    outlier_factor: float = 3.0
    outlier_floor_px: float = 0.5
    min_views: int = 4


@dataclass(frozen=True)
class CameraParams:
    """One calibrated camera in COLMAP's OPENCV model: params = fx, fy, cx, cy, k1, k2, p1, p2 (COLMAP pixels)."""

    width: int
    height: int
    params: tuple[float, ...]
    model: str = "OPENCV"

    def opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """(K, dist) in OpenCV's pixel convention (top-left pixel centre at (0, 0))."""
        fx, fy, cx, cy, *dist = self.params
        K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
        return K, np.array(dist, dtype=float)

    @staticmethod
    def from_opencv(K, dist, width: int, height: int) -> "CameraParams":
        d = np.zeros(4)
        d[:min(4, len(np.ravel(dist)))] = np.ravel(dist)[:4]
        return CameraParams(width, height, (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + 0.5,
                                            float(K[1, 2]) + 0.5, *map(float, d)))


@dataclass
class MonoResult:
    camera: CameraParams
    rms_px: float
    per_view_rms_px: dict[str, float]
    dropped: list[str]
    board: tuple[int, int]
    views: dict = field(default_factory=dict)  # name -> (rvec, tvec, corners) of the kept views


@dataclass
class StereoResult:
    left: MonoResult
    right: MonoResult
    R: np.ndarray
    t: np.ndarray
    rms_px: float
    per_pair_rms_px: dict[str, float]
    dropped_pairs: list[str]


def _gray(image) -> np.ndarray:
    from ..stereo.pipeline import to_gray

    return to_gray(image)


def detect_board_size(gray) -> tuple[int, int] | None:
    """Inner-corner count (cols, rows) of the largest chessboard OpenCV's sector detector finds, or None."""
    import cv2

    ok, corners, meta = cv2.findChessboardCornersSBWithMeta(gray, (3, 3), cv2.CALIB_CB_LARGER)
    if not ok or meta is None:
        return None
    rows, cols = meta.shape[:2]
    return (max(rows, cols), min(rows, cols))  # landscape order; the detectors accept either orientation


def find_corners(gray, board: tuple[int, int]) -> np.ndarray | None:
    """(N,2) sub-pixel inner corners in OpenCV pixels, row by row, or None when the board is not found."""
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    for size in (board, board[::-1]):
        ok, corners = cv2.findChessboardCorners(gray, size, flags=flags)
        if ok:
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
            corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
            return _row_major(corners.reshape(-1, 2), size, board)
        ok, corners = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_ACCURACY)
        if ok:
            return _row_major(corners.reshape(-1, 2), size, board)
    return None


def _row_major(corners, found_size, board) -> np.ndarray:
    """Corners of a board found as `found_size` reordered to `board` = (cols, rows) row-major order."""
    if tuple(found_size) == tuple(board):
        return corners
    cols, rows = found_size
    return corners.reshape(rows, cols, 2).transpose(1, 0, 2).reshape(-1, 2)


def board_points(board: tuple[int, int], square: float) -> np.ndarray:
    cols, rows = board
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
    return np.column_stack([grid, np.zeros(len(grid))]).astype(np.float32)


def _view_errors(obj, corners, K, dist, rvecs, tvecs) -> np.ndarray:
    import cv2

    errs = []
    for o, c, r, t in zip(obj, corners, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        errs.append(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - c) ** 2, axis=1))))
    return np.array(errs)


def _outliers(errors, config: CalibrationConfig) -> np.ndarray:
    limit = max(config.outlier_factor * float(np.median(errors)), config.outlier_floor_px)
    return errors > limit


def _calibrate_views(names, corners, size, config: CalibrationConfig, board) -> MonoResult:
    """calibrateCamera (k1, k2, p1, p2), drop outlier views once, solve again."""
    import cv2

    obj = [board_points(board, config.square)] * len(names)
    flags = cv2.CALIB_FIX_K3
    names, corners = list(names), [c.astype(np.float32) for c in corners]
    dropped = []
    for attempt in range(3):
        if len(names) < config.min_views:
            raise InputError(f"only {len(names)} views with a detected {board[0]}x{board[1]} board; "
                             f"{config.min_views} needed")
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj[:len(names)], corners, size, None, None, flags=flags)
        errors = _view_errors(obj, corners, K, dist, rvecs, tvecs)
        bad = _outliers(errors, config)
        if attempt == 2 or not bad.any() or len(names) - bad.sum() < config.min_views:
            break
        dropped += [n for n, b in zip(names, bad) if b]
        names = [n for n, b in zip(names, bad) if not b]
        corners = [c for c, b in zip(corners, bad) if not b]
    return MonoResult(CameraParams.from_opencv(K, dist, *size), float(rms),
                      {n: float(e) for n, e in zip(names, errors)}, dropped, board,
                      {n: (r, t, c) for n, r, t, c in zip(names, rvecs, tvecs, corners)})


def _detect_all(images: dict, board) -> tuple[tuple[int, int], dict]:
    """Board size (given or the most common detected one) and {name: corners} for the views where it is found."""
    grays = {n: _gray(img) for n, img in images.items()}
    if board is None:
        sizes = {}
        first = list(grays.items())[:8]
        for name, g in progress(first, desc="board size", unit="img"):
            s = detect_board_size(g)
            if s:
                sizes[s] = sizes.get(s, 0) + 1
        if not sizes:
            raise InputError(f"no chessboard found in the first {len(first)} images; give --size CxR (inner corners)")
        board = max(sizes, key=sizes.get)
        log.info("board size detected: %dx%d inner corners", *board)
    found = {}
    for name, g in progress(grays.items(), total=len(grays), desc="corners", unit="img"):
        c = find_corners(g, board)
        if c is None:
            log.info("%s: no %dx%d board found, skipped", name, *board)
        else:
            found[name] = c
    return board, found


def calibrate_mono(images: dict, config: CalibrationConfig = CalibrationConfig()) -> MonoResult:
    """images: {name: array}. All images must share one size."""
    sizes = {}  # (h, w) -> the first image of that size, an example to find
    for name, img in images.items():
        sizes.setdefault(img.shape[:2], name)
    if len(sizes) != 1:
        raise InputError("calibration images differ in size: " + ", ".join(
            f"{w}x{h} (e.g. {name})" for (h, w), name in sorted(sizes.items())))
    h, w = next(iter(sizes))
    board, found = _detect_all(images, config.board)
    return _calibrate_views(list(found), list(found.values()), (w, h), config, board)


def _consistent_order(c_left, c_right) -> np.ndarray:
    """Reverse the right view's corners when its detector started from the opposite board corner."""
    dl, dr = c_left[-1] - c_left[0], c_right[-1] - c_right[0]
    return c_right[::-1].copy() if dl @ dr < 0 else c_right


def calibrate_stereo(left: dict, right: dict, pairs: list[tuple[str, str]],
                     config: CalibrationConfig = CalibrationConfig()) -> StereoResult:
    """Mono calibration of each camera, then stereoCalibrate (intrinsics fixed) on pairs seen by both, with
    outlier pairs dropped; R, t map left-camera coordinates to the right camera (x_r = R x_l + t)."""
    import cv2

    mono_l = calibrate_mono(left, config)
    mono_r = calibrate_mono(right, CalibrationConfig(mono_l.board, config.square, config.outlier_factor,
                                                     config.outlier_floor_px, config.min_views))
    Kl, Dl = mono_l.camera.opencv()
    Kr, Dr = mono_r.camera.opencv()
    h, w = next(iter(left.values())).shape[:2]
    usable = [(a, b) for a, b in pairs if a in mono_l.views and b in mono_r.views]
    dropped = [f"{a}|{b}" for a, b in pairs if (a, b) not in usable]
    obj = board_points(mono_l.board, config.square)
    for attempt in range(3):
        if len(usable) < 3:
            raise InputError(f"only {len(usable)} stereo pairs with the board found in both views; 3 needed")
        cl = [mono_l.views[a][2] for a, _ in usable]
        cr = [_consistent_order(mono_l.views[a][2], mono_r.views[b][2]) for a, b in usable]
        out = cv2.stereoCalibrateExtended([obj] * len(usable), cl, cr, Kl, Dl, Kr, Dr, (w, h), None, None,
                                          flags=cv2.CALIB_FIX_INTRINSIC)
        rms, R, T, per_view = out[0], out[5], out[6], out[-1]
        errors = np.asarray(per_view).reshape(len(usable), 2).max(axis=1)
        bad = _outliers(errors, config)
        if attempt == 2 or not bad.any() or len(usable) - bad.sum() < 3:
            break
        dropped += [f"{a}|{b}" for (a, b), x in zip(usable, bad) if x]
        usable = [p for p, x in zip(usable, bad) if not x]
    return StereoResult(mono_l, mono_r, np.asarray(R), np.asarray(T).ravel(), float(rms),
                        {f"{a}|{b}": float(e) for (a, b), e in zip(usable, errors)}, dropped)


def stereo_pairs(names: list[str]) -> tuple[list[str], list[str], list[tuple[str, str]]]:
    """Pair names that differ only by 'left' <-> 'right' (case-insensitive; file or folder names), e.g.
    left01.jpg / right01.jpg or left/001.png / right/001.png. Returns (lefts, rights, pairs)."""
    def key(name, side):
        low = name.lower()
        i = low.find(side)
        return None if i < 0 else low[:i] + "#" + low[i + len(side):]

    lefts = {key(n, "left"): n for n in names if key(n, "left")}
    rights = {key(n, "right"): n for n in names if key(n, "right")}
    common = sorted(set(lefts) & set(rights))
    return [lefts[k] for k in common], [rights[k] for k in common], [(lefts[k], rights[k]) for k in common]


def _camera_toml(section: str, result: MonoResult) -> str:
    cam = result.camera
    per_view = ", ".join(f'"{n}" = {e:.4f}' for n, e in result.per_view_rms_px.items())
    dropped = ", ".join(f'"{n}"' for n in result.dropped)
    return (f"[{section}]\nmodel = \"{cam.model}\"\nwidth = {cam.width}\nheight = {cam.height}\n"
            f"# fx, fy, cx, cy, k1, k2, p1, p2 in COLMAP pixels (top-left pixel centre at 0.5, 0.5)\n"
            f"params = [{', '.join(f'{p:.10g}' for p in cam.params)}]\n"
            f"colmap_params = \"{','.join(f'{p:.10g}' for p in cam.params)}\"\n"
            f"rms_px = {result.rms_px:.6f}\nviews_used = {len(result.per_view_rms_px)}\n"
            f"views_dropped = [{dropped}]\nper_view_rms_px = {{ {per_view} }}\n")


def write_camera_toml(path, result: "MonoResult | StereoResult", config: CalibrationConfig) -> None:
    left = result.left if isinstance(result, StereoResult) else result
    text = (f"# written by `mvrecon calibrate`: chessboard {left.board[0]}x{left.board[1]} inner corners, "
            f"square {config.square:g}\n" + _camera_toml("camera", left))
    if isinstance(result, StereoResult):
        R = "[" + ", ".join("[" + ", ".join(f"{v:.12g}" for v in row) + "]" for row in result.R) + "]"
        per_pair = ", ".join(f'"{n}" = {e:.4f}' for n, e in result.per_pair_rms_px.items())
        dropped = ", ".join(f'"{n}"' for n in result.dropped_pairs)
        text += "\n" + _camera_toml("camera_right", result.right) + (
            f"\n[stereo]\n# x_right = R x_left + t (OpenCV stereoCalibrate); t in square units\n"
            f"R = {R}\nt = [{', '.join(f'{v:.12g}' for v in result.t)}]\n"
            f"baseline = {float(np.linalg.norm(result.t)):.10g}\nrms_px = {result.rms_px:.6f}\n"
            f"pairs_used = {len(result.per_pair_rms_px)}\npairs_dropped = [{dropped}]\n"
            f"per_pair_rms_px = {{ {per_pair} }}\n")
    replace_whole(path, lambda tmp: tmp.write_text(text))


def read_camera_toml(path) -> dict:
    """{"path", "left": CameraParams, "right": CameraParams | None, "stereo": {"R", "t"} | None}."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera file not found")
    try:
        data = tomllib.loads(path.read_text())
        def cam(section):
            s = data[section]
            return CameraParams(int(s["width"]), int(s["height"]), tuple(float(v) for v in s["params"]),
                                s.get("model", "OPENCV"))
        left = cam("camera")
        right = cam("camera_right") if "camera_right" in data else None
        stereo = None
        if "stereo" in data:
            stereo = {"R": np.array(data["stereo"]["R"], dtype=float), "t": np.array(data["stereo"]["t"], float)}
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: not a camera file from `mvrecon calibrate` ({exc})") from None
    for c in (left, right):
        if c is not None and (c.model != "OPENCV" or len(c.params) != 8):
            raise InputError(f"{path}: expected OPENCV cameras with 8 parameters")
    return {"path": str(path), "left": left, "right": right, "stereo": stereo}
