"""Chessboard camera calibration with OpenCV (Zhang's method), mono and stereo: the seed's "calibration toolkit".

Corners: OpenCV's classic detector refined by `cornerSubPix`, falling back to the sector-based detector; the board
size (inner corners) is found from the images when not given. Every view's RMS reprojection error is reported and
views far above the median are dropped before the final solve, because one blurred or mis-ordered view biases all
intrinsics. Results go to a small TOML file (`camera.toml`) in COLMAP's OPENCV model and pixel convention (top-left
pixel centre at (0.5, 0.5)); `mvrecon stereo --camera` reads it, and its `colmap_params` string is what
`--camera-model OPENCV --camera-params` takes. The board search is most of the time (85 % on the ximea set): given
an `io.record.Record`, each image's corners are kept as they are found, and a rerun finds only the missing ones.
"""

import base64
import logging
import tomllib
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..io.files import replace_whole
from ..io.images import as_uint8, to_gray
from ..io.record import Record, code_digest, digest
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
    def from_opencv(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> "CameraParams":
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


def detect_board_size(gray: np.ndarray) -> tuple[int, int] | None:
    """Inner-corner count (cols, rows) of the largest chessboard OpenCV's sector detector finds, or None."""
    ok, corners, meta = cv2.findChessboardCornersSBWithMeta(gray, (3, 3), cv2.CALIB_CB_LARGER)
    if not ok or meta is None:
        return None
    rows, cols = meta.shape[:2]
    return (max(rows, cols), min(rows, cols))  # landscape order; the detectors accept either orientation


def find_corners(gray: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """(N,2) sub-pixel inner corners in OpenCV pixels, row by row, or None when the board is not found."""
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
    errs = []
    for o, c, r, t in zip(obj, corners, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        errs.append(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - c) ** 2, axis=1))))
    return np.array(errs)


def _outliers(errors, config: CalibrationConfig) -> np.ndarray:
    limit = max(config.outlier_factor * float(np.median(errors)), config.outlier_floor_px)
    return errors > limit


@contextmanager
def _one_thread():
    """OpenCV's calibration solvers sum their normal equations over threads in whatever order the threads finish:
    with 2 threads, three runs on the same corners gave three camera files differing in the 9th-10th digit. On one
    thread (the solves take under 0.1 s of the 2.7 s of the ximea set) the same corners give the same bytes, so that
    a resumed run writes what an uninterrupted one writes."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(threads)


def _calibrate_views(names, corners, size, config: CalibrationConfig, board) -> MonoResult:
    """calibrateCamera (k1, k2, p1, p2), drop outlier views once, solve again."""
    obj = [board_points(board, config.square)] * len(names)
    flags = cv2.CALIB_FIX_K3
    names, corners = list(names), [c.astype(np.float32) for c in corners]
    dropped = []
    for attempt in range(3):
        if len(names) < config.min_views:
            raise InputError(f"only {len(names)} views with a detected {board[0]}x{board[1]} board; "
                             f"{config.min_views} needed")
        with _one_thread():
            rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj[:len(names)], corners, size, None, None,
                                                             flags=flags)
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


def _pack(corners) -> dict | None:
    """Corners as JSON: the float32 bytes in base64 (exact, and a tenth of their decimal text)."""
    if corners is None:
        return None
    c = np.ascontiguousarray(corners, dtype=np.float32)
    return {"shape": list(c.shape), "float32": base64.b64encode(c.tobytes()).decode()}


def _unpack(packed) -> np.ndarray | None:
    if packed is None:
        return None
    return np.frombuffer(base64.b64decode(packed["float32"]), np.float32).reshape(packed["shape"]).copy()


def _once(stages, name: str, key_parts, make) -> dict:
    """make() (a JSON-able dict), or what an earlier run recorded for the same inputs in `stages` (a Record)."""
    if stages is None:
        return make()
    return stages.run(name, digest(*key_parts), (), make)


def _detect_all(images: dict, board, stages=None) -> tuple[tuple[int, int], dict]:
    """Board size (given or the most common detected one) and {name: corners} for the views where it is found.
    With `stages` (an io.record.Record), each image's board search and corners are recorded as they are found
    and taken from the record when an earlier run found them in the same pixels with the same code."""
    grays = {n: to_gray(as_uint8(img)) for n, img in images.items()}
    code = (code_digest(__name__), cv2.__version__) if stages is not None else None
    if board is None:
        sizes = {}
        first = list(grays.items())[:8]
        for name, g in progress(first, desc="board size", unit="img"):
            s = _once(stages, f"board size {name}", (g, code),
                      lambda: {"size": detect_board_size(g)})["size"]
            if s:
                s = tuple(s)
                sizes[s] = sizes.get(s, 0) + 1
        if not sizes:
            raise InputError(f"no chessboard found in the first {len(first)} images; give --size CxR (inner corners)")
        board = max(sizes, key=sizes.get)
        log.info("board size detected: %dx%d inner corners", *board)
    found = {}
    for name, g in progress(grays.items(), total=len(grays), desc="corners", unit="img"):
        c = _unpack(_once(stages, f"corners {name}", (g, list(board), code),
                          lambda: {"corners": _pack(find_corners(g, board))})["corners"])
        if c is None:
            log.info("%s: no %dx%d board found, skipped", name, *board)
        else:
            found[name] = c
    return board, found


def calibrate_mono(images: dict, config: CalibrationConfig = CalibrationConfig(),
                   stages: Record | None = None) -> MonoResult:
    """images: {name: array}. All images must share one size. stages: an `io.record.Record` that keeps each
    image's corners for a rerun (None: nothing kept)."""
    sizes = {}  # (h, w) -> the first image of that size, an example to find
    for name, img in images.items():
        sizes.setdefault(img.shape[:2], name)
    if len(sizes) != 1:
        raise InputError("calibration images differ in size: " + ", ".join(
            f"{w}x{h} (e.g. {name})" for (h, w), name in sorted(sizes.items())))
    h, w = next(iter(sizes))
    board, found = _detect_all(images, config.board, stages)
    return _calibrate_views(list(found), list(found.values()), (w, h), config, board)


def _consistent_order(c_left, c_right) -> np.ndarray:
    """Reverse the right view's corners when its detector started from the opposite board corner."""
    dl, dr = c_left[-1] - c_left[0], c_right[-1] - c_right[0]
    return c_right[::-1].copy() if dl @ dr < 0 else c_right


def calibrate_stereo(left: dict, right: dict, pairs: list[tuple[str, str]],
                     config: CalibrationConfig = CalibrationConfig(),
                     stages: Record | None = None) -> StereoResult:
    """Mono calibration of each camera, then stereoCalibrate (intrinsics fixed) on pairs seen by both, with
    outlier pairs dropped; R, t map left-camera coordinates to the right camera (x_r = R x_l + t). stages: as for
    `calibrate_mono`."""
    mono_l = calibrate_mono(left, config, stages)
    mono_r = calibrate_mono(right, CalibrationConfig(mono_l.board, config.square, config.outlier_factor,
                                                     config.outlier_floor_px, config.min_views), stages)
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
        with _one_thread():
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


def write_camera_toml(path: Path | str, result: "MonoResult | StereoResult",
                      config: CalibrationConfig) -> None:
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


def read_camera_toml(path: Path | str) -> dict:
    """{"path", "left": CameraParams, "right": CameraParams | None, "stereo": {"R", "t"} | None}. Anything else
    (not text, not TOML, a missing table or key, a value of the wrong kind) is one InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera file not found")

    def bad(reason):
        return InputError(f"{path}: not a camera file from `mvrecon calibrate` ({reason})")

    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise bad("not text") from None
    except tomllib.TOMLDecodeError as exc:
        raise bad(f"not TOML: {exc}") from None

    def table(name):
        if not isinstance(data.get(name), dict):
            raise bad(f"no [{name}] table")
        return data[name]

    def cam(section):
        s = table(section)
        missing = [k for k in ("width", "height", "params") if k not in s]
        if missing:
            raise bad(f"[{section}] has no {', '.join(missing)}")
        try:
            width, height = int(s["width"]), int(s["height"])
            params = tuple(float(v) for v in s["params"])
        except (TypeError, ValueError):
            raise bad(f"[{section}] width, height and params must be numbers") from None
        if width <= 0 or height <= 0 or not np.isfinite(params).all():
            raise bad(f"[{section}] needs a positive width and height and finite params")
        return CameraParams(width, height, params, s.get("model", "OPENCV"))

    left = cam("camera")
    right = cam("camera_right") if "camera_right" in data else None
    stereo = None
    if "stereo" in data:
        s = table("stereo")
        try:
            stereo = {"R": np.array(s["R"], dtype=float), "t": np.array(s["t"], dtype=float).ravel()}
        except KeyError as exc:
            raise bad(f"[stereo] has no {exc.args[0]}") from None
        except (TypeError, ValueError):
            raise bad("[stereo] R and t must be numbers") from None
        if stereo["R"].shape != (3, 3) or stereo["t"].shape != (3,) or not (
                np.isfinite(stereo["R"]).all() and np.isfinite(stereo["t"]).all()):
            raise bad("[stereo] needs R as 3x3 and t as 3 finite numbers")
    for c in (left, right):
        if c is not None and (c.model != "OPENCV" or len(c.params) != 8):
            raise InputError(f"{path}: expected OPENCV cameras with 8 parameters")
    return {"path": str(path), "left": left, "right": right, "stereo": stereo}
