"""The seed paper's two-view stereo run: matches -> F (our eight-point RANSAC, checked against OpenCV) ->
rectification -> disparity (gee | sgbm | best) -> depth, point cloud, figures, and scores against ground truth.

`run_stereo(config, left_path, right_path, out_dir, ...)` is what `mvrecon stereo` calls; it returns the report
dict it also writes to `out_dir/report.json`. A rerun into the same folder reuses the stages already done
(`io.record`).
"""

import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import tifffile
from PIL import Image

from ..errors import InputError
from ..features.sift import SiftConfig, extract_sift
from ..geometry.fundamental import RansacConfig, ransac_fundamental, sampson_distance
from ..geometry.rectification import apply_homography, calibrated_rectification, fit_to_canvas, hartley_rectification
from ..io.files import made_folder, replace_whole, write_json
from ..io.images import as_uint8, read_image, to_gray, write_image
from ..io.pfm import read_pfm, write_pfm
from ..io.record import Record, code_digest, digest
from ..matching.matcher import MatcherConfig, match_descriptors
from . import figures
from .best import BestConfig, best_disparity
from .calib import StereoCalib, check_image_size, read_calib
from .calibrate import read_camera_toml
from .depth import disparity_to_depth, write_point_cloud
from .evaluate import error_map, evaluate
from .gee import GEEConfig, gee_disparity
from .sgbm import SGBMConfig, sgbm_disparity

log = logging.getLogger("mvrecon.stereo")

METHODS = ("gee", "sgbm", "best")


@dataclass(frozen=True)
class StereoConfig:
    """method: disparity algorithm; min/num_disparities: search range (None: from calib.txt's ndisp or from the
    inlier matches); ransac: F estimation; ratio: Lowe's ratio for SIFT matches; the per-method configs hold the
    method parameters (their search range is overwritten by the one chosen here)."""

    method: str = "best"
    min_disparity: int | None = None
    num_disparities: int | None = None
    ransac: RansacConfig = RansacConfig()
    ratio: float = 0.8
    max_features: int = 8192
    gee: GEEConfig = GEEConfig()
    sgbm: SGBMConfig = SGBMConfig()
    best: BestConfig = BestConfig()


def sift_matches(left: np.ndarray, right: np.ndarray, ratio: float = 0.8,
                 max_features: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Front-end SIFT matches (mutual nearest neighbours passing Lowe's ratio) as (x1, x2) pixel arrays with pixel
    centres at integers, the convention of the image arrays (the front end stores COLMAP's +0.5)."""
    sift = SiftConfig(max_num_features=max_features)
    k1, d1 = extract_sift(left, sift)
    k2, d2 = extract_sift(right, sift)
    if len(k1) < 2 or len(k2) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = np.asarray(match_descriptors(d1, d2, MatcherConfig(max_ratio=ratio)), dtype=int).reshape(-1, 2)
    return (k1[pairs[:, 0], :2].astype(float) - 0.5, k2[pairs[:, 1], :2].astype(float) - 0.5)


def load_ground_truth(path: Path | str, scale: float = 1.0) -> np.ndarray:
    """Disparity ground truth as float32 with NaN where unknown: PFM (inf = unknown), npz (first array, inf =
    unknown), TIFF (0 = unknown) or PNG (0 = unknown; divide by `scale`, e.g. 4 for Middlebury 2003 PNGs)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: ground-truth disparity not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".pfm":
            gt = read_pfm(path)
        elif suffix == ".npz":
            with np.load(path) as data:
                gt = np.asarray(data[data.files[0]], dtype=np.float32)
        elif suffix in (".tif", ".tiff"):
            gt = tifffile.imread(path).astype(np.float32)
            gt[gt == 0] = np.nan
        else:
            gt = np.asarray(Image.open(path), dtype=np.float32)
            gt[gt == 0] = np.nan
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}: cannot read ground truth ({exc})") from None
    if gt.ndim == 3:
        gt = gt[..., 0]
    gt = gt / scale
    gt[~np.isfinite(gt)] = np.nan
    return gt.astype(np.float32)


def load_mask(path: Path | str) -> np.ndarray:
    """Non-occluded mask: the brightest value of the mask image (255 in Middlebury 2014, 1 in the Cones palette)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: non-occlusion mask not found")
    try:
        m = np.asarray(Image.open(path))
    except Exception as exc:  # Pillow raises several types for a file it cannot read
        raise InputError(f"{path}: cannot read the mask image ({type(exc).__name__})") from None
    if m.ndim == 3:
        m = m[..., 0]
    return m == m.max()


def read_pair(left_path: Path | str, right_path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    left, right = read_image(left_path), read_image(right_path)
    if left.shape[:2] != right.shape[:2]:
        raise InputError(f"{right_path}: size {right.shape[1]}x{right.shape[0]} differs from the left image's "
                         f"{left.shape[1]}x{left.shape[0]}; a stereo pair needs equal sizes")
    if left.ndim != right.ndim:
        left, right = to_gray(as_uint8(left)), to_gray(as_uint8(right))
    return as_uint8(left), as_uint8(right)


def _disparity_range(d, margin_fraction: float = 0.25, margin: float = 8.0) -> tuple[int, int]:
    """(min, num) search range around the 1-99 % range of the match disparities, num a multiple of 16."""
    lo, hi = np.percentile(d, [1, 99])
    pad = margin + margin_fraction * (hi - lo)
    dmin = int(np.floor(lo - pad))
    num = int(np.ceil((hi + pad - dmin) / 16.0) * 16)
    return dmin, max(num, 16)


def search_range(config: StereoConfig, calib: StereoCalib | None, match_disparities: np.ndarray,
                 nonnegative: bool) -> tuple[int, int]:
    """(min, num) disparities: the config's when set, else calib.txt's ndisp, else the matches' range with a margin
    (clipped at 0 when disparities cannot be negative: Middlebury geometry, or after `fit_to_canvas`)."""
    if calib is not None and calib.ndisp > 0:
        dmin, num = 0, int(np.ceil(calib.ndisp / 16) * 16)
    else:
        dmin, num = _disparity_range(match_disparities)
        if nonnegative and dmin < 0:  # at least 16: a swapped pair's matches all lie below 0 (judge_matches says so)
            dmin, num = 0, max(16, int(np.ceil((num + dmin) / 16) * 16))
    if config.min_disparity is not None:
        dmin = config.min_disparity
    if config.num_disparities is not None:
        num = config.num_disparities
    return dmin, num


def compute_disparity(left: np.ndarray, right: np.ndarray, config: StereoConfig, min_disparity: int,
                      num_disparities: int) -> tuple[np.ndarray, dict]:
    """(disparity float32 with NaN holes, extra info dict) by the configured method."""
    if config.method == "gee":
        result = gee_disparity(left, right, replace(config.gee, min_disparity=min_disparity,
                                                    num_disparities=num_disparities))
        return result.disparity, {"gee_threshold_Ve": result.threshold, "gee_reliability": result.reliability}
    if config.method == "sgbm":
        return sgbm_disparity(left, right, replace(config.sgbm, min_disparity=min_disparity,
                                                   num_disparities=num_disparities)), {}
    if config.method == "best":
        return best_disparity(left, right, replace(config.best, min_disparity=min_disparity,
                                                   num_disparities=num_disparities)), {}
    raise InputError(f"unknown stereo method {config.method!r}; expected one of {', '.join(METHODS)}")


VERTICAL_LIMIT_PX = 2.0  # median |y_left - y_right| of the inlier matches after rectification: 0.05-0.15 px measured
MIN_PARALLAX_PX = 0.5  # median |x_left - x_right| of the SIFT matches below this: no depth to measure


def judge_matches(p1: np.ndarray, p2: np.ndarray, dmin: int, num: int, kind: str,
                  doffs: float = 0.0) -> tuple[dict, list[str]]:
    """Figures of the inlier matches in the rectified frame, and warnings for a result that is likely wrong
    although every step ran: rows that do not line up (a camera file of another rig, a pair that is not
    rectified), disparities that are mostly negative (left and right swapped: the search range, calib.txt's
    0..ndisp or clipped at 0, then misses every surface), or many outside the search range (those surfaces come out
    as holes or wrong). kind: "calib", "rectified", "camera" or "uncalibrated"; the sign is judged on d + doffs for
    "camera" (Z = f B / (d + doffs) > 0), on d for calib.txt and --rectified (Middlebury: 0 <= d), and not at all
    for "uncalibrated" (`fit_to_canvas` shifts the right image so the disparities are positive either way)."""
    dy = float(np.median(np.abs(p1[:, 1] - p2[:, 1])))
    d = p1[:, 0] - p2[:, 0]
    signed = d + (doffs if kind == "camera" else 0.0)
    outside = (d < dmin - 1) | (d > dmin + num)  # 1 px of slack: sub-pixel matches at the ends of the range
    lo, median, hi = (float(v) for v in np.percentile(d, [1, 50, 99]))
    figures = {"p1": lo, "median": median, "p99": hi, "negative_percent": float(100 * np.mean(signed < 0)),
               "outside_search_range_percent": float(100 * np.mean(outside))}
    warnings = []
    if dy > VERTICAL_LIMIT_PX:
        hint = {"camera": "the camera file may be another rig's, or LEFT and RIGHT swapped",
                "uncalibrated": "the fundamental matrix is probably wrong (too few or wrong matches)"}.get(
            kind, "the pair may not be rectified")
        warnings.append(f"rows do not line up after rectification (the inlier matches lie a median {dy:.1f} px apart "
                        f"vertically, under {VERTICAL_LIMIT_PX:g} px expected): {hint}; the disparity map is likely "
                        "wrong")
    if kind != "uncalibrated" and figures["negative_percent"] > 50:
        what = "x_left - x_right + doffs" if kind == "camera" else "x_left - x_right"
        warnings.append(f"{figures['negative_percent']:.0f} % of the inlier matches have a negative disparity ({what}, "
                        f"median {float(np.median(signed)):.1f} px): the left and right images are probably swapped; "
                        "give them the other way round")
    elif figures["outside_search_range_percent"] > 10:
        warnings.append(f"{figures['outside_search_range_percent']:.0f} % of the inlier matches' disparities "
                        f"(1-99 %: {lo:.1f} to {hi:.1f} px) lie outside the search range [{dmin}, {dmin + num}]: "
                        "those surfaces come out as holes or wrong; give --min-disparity and --num-disparities")
    return figures, warnings


def _check_camera(camera, width: int, height: int, image) -> None:
    """Refuse, before any work, a camera file without a rig or made for another image size: its focal lengths,
    principal points and distortion are in that size's pixels (reconstruct and export refuse such an image too)."""
    if camera.get("stereo") is None or camera.get("right") is None:
        raise InputError(f"{camera['path']}: camera file has no [stereo] section; run `mvrecon calibrate --stereo`")
    for section, cam in (("[camera]", camera["left"]), ("[camera_right]", camera.get("right"))):
        if cam is not None and (cam.width, cam.height) != (width, height):
            raise InputError(f"{camera['path']}: {section} made for {cam.width}x{cam.height} images, these are "
                             f"{width}x{height} ({image})")


def _same_file(a, b) -> bool:
    try:
        return Path(a).samefile(b)
    except OSError:  # a missing file: read_pair names it
        return False


def _rectify_with_camera(left, right, camera, x1, x2):
    """Undistort and rectify with a stereo calibration from `mvrecon calibrate --stereo`."""
    (K1, D1), (K2, D2) = camera["left"].opencv(), camera["right"].opencv()
    rect = calibrated_rectification(K1, K2, camera["stereo"]["R"], camera["stereo"]["t"])
    h, w = left.shape[:2]
    maps = [cv2.initUndistortRectifyMap(K, D, R, Kn, (w, h), cv2.CV_32FC1)
            for K, D, R, Kn in ((K1, D1, rect.R1, rect.K1), (K2, D2, rect.R2, rect.K2))]
    out = [cv2.remap(img, mx, my, cv2.INTER_LINEAR) for img, (mx, my) in zip((left, right), maps)]
    # pixels of the rectified left view that come from inside the left image
    inside = cv2.remap(np.ones((h, w), np.uint8), *maps[0], cv2.INTER_NEAREST, borderValue=0) > 0
    p1 = cv2.undistortPoints(x1.reshape(-1, 1, 2), K1, D1, R=rect.R1, P=rect.K1).reshape(-1, 2)
    p2 = cv2.undistortPoints(x2.reshape(-1, 1, 2), K2, D2, R=rect.R2, P=rect.K2).reshape(-1, 2)
    geometry = {"focal": float(rect.K1[0, 0]), "baseline": rect.baseline, "cx": float(rect.K1[0, 2]),
                "cy": float(rect.K1[1, 2]), "doffs": float(rect.K2[0, 2] - rect.K1[0, 2])}
    return out[0], out[1], p1, p2, geometry, inside


def _save_pfm(path: Path, values) -> None:
    replace_whole(path, lambda tmp: write_pfm(tmp, np.where(np.isfinite(values), values, np.inf)))


def _load_pfm(path: Path) -> np.ndarray:
    values = read_pfm(path)
    values[~np.isfinite(values)] = np.nan
    return values


def run_stereo(config: StereoConfig, left_path: Path | str, right_path: Path | str, out_dir: Path | str,
               calib_path: Path | str | None = None, camera_path: Path | str | None = None,
               gt_path: Path | str | None = None, mask_path: Path | str | None = None, gt_scale: float = 1.0,
               rectified: bool = False) -> dict:
    """The whole two-view run; writes rectified images, disparity/depth PFM and PNG, cloud.ply, figures, report.

    rectified=True takes the pair as already rectified without a calib.txt (disparity only, no metric depth).
    Input that cannot give a right answer (a calibration for another image size, the same image twice) is an
    InputError before any work (the parallax check after the matches: a refused run removes the folder it made); a
    result that is likely wrong (`judge_matches`) is listed in report["warnings"]."""
    if calib_path is not None and camera_path is not None:
        raise InputError("give either --calib or --camera, not both")
    if mask_path is not None and gt_path is None:  # it would be read and never used
        raise InputError("--mask goes with --gt: it selects the non-occluded pixels scored against the ground truth")
    if gt_scale != 1.0 and gt_path is None:
        raise InputError("--gt-scale goes with --gt: it divides the ground-truth disparities")
    if _same_file(left_path, right_path):
        raise InputError(f"{left_path}: given as both left and right image; stereo needs two views from different "
                         "positions (no parallax, no depth)")
    out = Path(out_dir)
    for path in (left_path, right_path):  # eight outputs would land among the dataset's files
        if out.resolve() == Path(path).resolve().parent:
            raise InputError(f"{out_dir}: the output folder must differ from the folder of {path}")
    calib = read_calib(calib_path) if calib_path is not None else None
    camera = None
    if camera_path is not None:
        camera = read_camera_toml(camera_path)
    gt = load_ground_truth(gt_path, gt_scale) if gt_path is not None else None
    mask = load_mask(mask_path) if mask_path is not None else None
    left, right = read_pair(left_path, right_path)
    if np.array_equal(left, right):
        raise InputError(f"{left_path}, {right_path}: identical pixels; stereo needs two views from different "
                         "positions (no parallax, no depth)")
    if calib is not None:
        check_image_size(calib_path, calib, left.shape[1], left.shape[0], left_path)
    if camera is not None:
        _check_camera(camera, left.shape[1], left.shape[0], left_path)
    width = left.shape[1]  # a wider search has no pixel to match, and its cost volume may not fit in memory
    for flag, value in (("--num-disparities", config.num_disparities), ("--min-disparity", config.min_disparity)):
        if value is not None and abs(value) >= width:
            raise InputError(f"{flag} {value}: beyond the image width ({width} px, {left_path})")
    for path, grid, what in ((gt_path, gt, "ground truth"), (mask_path, mask, "mask")):
        if grid is not None and grid.shape != left.shape[:2]:
            raise InputError(f"{path}: {what} is {grid.shape[1]}x{grid.shape[0]}, images are "
                             f"{left.shape[1]}x{left.shape[0]}")
    if config.method not in METHODS:
        raise InputError(f"unknown stereo method {config.method!r}; expected one of {', '.join(METHODS)}")
    # refused after the matches (no parallax, too few): leave no folder of ours behind (OUT when new, else the
    # stage folder when new); an interrupted run keeps its stages
    with made_folder(out, removed_on=InputError, within=out / ".stages"):
        return _run(config, left_path, right_path, out, left, right, calib, camera, gt, mask, rectified)


@dataclass
class _Output:
    """The folder of one run as its steps write it: the stage cache, the report, and the figures."""

    out: Path
    stages: Record
    report: dict
    figures_code: str  # the figures module's source, read once rather than per figure

    def warn(self, text: str) -> None:
        """A result that is likely wrong says so: in the log and in report.json's "warnings"."""
        log.warning("warning: %s", text)
        self.report["warnings"].append(text)

    def figure(self, name: str, key, draw) -> None:
        """Figures take seconds (matplotlib): drawn again only when what they show changed."""
        key = digest(key, self.figures_code)
        self.stages.run(name, key, [name], lambda: replace_whole(self.out / name, draw))


@dataclass
class _Rectified:
    """The pair in the frame the disparity is searched in, with the inlier matches moved there."""

    left: np.ndarray
    right: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    geometry: dict | None  # focal, baseline, cx, cy, doffs when metric depth can be had
    inside: np.ndarray  # pixels of the canvas inside the warped left image


def _run(config: StereoConfig, left_path, right_path, out: Path, left, right, calib, camera, gt, mask,
         rectified: bool) -> dict:
    """run_stereo after its checks, into the existing folder `out` (an interrupted run keeps its stages there)."""
    stages = Record(out)
    stages.path.parent.mkdir(parents=True, exist_ok=True)  # the matches and disparities are kept there too
    report: dict = {"left": str(left_path), "right": str(right_path), "method": config.method, "warnings": []}
    run = _Output(out, stages, report, code_digest(figures.__name__))
    x1, x2, F, inliers = _matches(config, run, left, right, left_path, right_path)
    t0 = time.perf_counter()
    rect = _rectify(left, right, F, x1[inliers], x2[inliers], calib, camera, rectified, report)
    dy = np.abs(rect.p1[:, 1] - rect.p2[:, 1])
    report["vertical_disparity_px"] = {"median": float(np.median(dy)), "p95": float(np.percentile(dy, 95)),
                                       "max": float(dy.max())}
    timings = {"matching_and_F": stages.seconds("matches"), "rectification": time.perf_counter() - t0}
    for name, image in (("rectified_left.png", rect.left), ("rectified_right.png", rect.right)):
        replace_whole(out / name, lambda tmp: write_image(tmp, _bgr(image)))
    run.figure("rectified_pair.png", digest(rect.left, rect.right),
               lambda path: figures.rectified_figure(path, rect.left, rect.right))
    kind = ("calib" if calib is not None else "camera" if camera is not None else
            "rectified" if rectified else "uncalibrated")
    disparity, timings["disparity"] = _disparity(config, run, rect, calib, kind, left_path)
    if rect.geometry is not None:
        _depth_and_cloud(run, disparity, rect)
    else:
        log.info("no calibration given: disparity only (no metric depth without --calib or --camera)")
    if gt is not None:
        _score(config, run, disparity, gt, mask)
    report["timings_s"] = timings
    report["reused"] = stages.reused
    report["config"] = asdict(config)
    write_json(out / "report.json", report, indent=2, allow_nan=False)  # strict JSON: no NaN
    return report


def _matches(config: StereoConfig, run: _Output, left, right, left_path, right_path):
    """SIFT matches and the fundamental matrix (x1, x2, F, inlier mask), found once per pair and code: their
    counts and OpenCV's F for comparison go into the report, the epipolar figure into the folder."""
    def find_matches():
        x1, x2 = sift_matches(left, right, config.ratio, config.max_features)
        if len(x1) < 8:
            raise InputError(f"{left_path}, {right_path}: only {len(x1)} SIFT matches (8 needed for the fundamental "
                             f"matrix); are these two views of the same scene?")
        parallax = float(np.median(np.hypot(*(x1 - x2).T)))
        if parallax < MIN_PARALLAX_PX:
            raise InputError(f"{left_path}, {right_path}: no parallax: the {len(x1)} SIFT matches moved a median "
                             f"{parallax:.2f} px between the images ({MIN_PARALLAX_PX:g} px at least); stereo needs "
                             "two views from different positions")
        try:
            F, inliers = ransac_fundamental(x1, x2, config.ransac)
        except ValueError as exc:
            raise InputError(f"{left_path}, {right_path}: {exc}") from None
        part = {"matches": int(len(x1)), "inliers": int(inliers.sum()), "F": F.tolist(),
                "sampson_median_px": float(np.median(sampson_distance(F, x1[inliers], x2[inliers])))}
        F_cv, mask_cv = cv2.findFundamentalMat(x1, x2, cv2.FM_RANSAC, config.ransac.threshold, 0.999)
        if F_cv is not None and F_cv.shape == (3, 3):
            F_cv = F_cv / np.linalg.norm(F_cv)
            part["opencv"] = {
                "F": F_cv.tolist(), "inliers": int(mask_cv.sum()),
                "sampson_median_px_of_our_inliers": float(np.median(sampson_distance(F_cv, x1[inliers], x2[inliers]))),
                "our_F_sampson_median_px_of_its_inliers": float(np.median(
                    sampson_distance(F, x1[mask_cv.ravel() > 0], x2[mask_cv.ravel() > 0]))),
            }
        replace_whole(run.out / ".stages" / "matches.npz",
                      lambda tmp: np.savez(tmp, x1=x1, x2=x2, F=F, inliers=inliers))
        return part

    matches_key = digest(left, right, config.ratio, config.max_features, asdict(config.ransac),
                         code_digest(__name__, "mvrecon.features.sift", "mvrecon.matching.matcher",
                                     "mvrecon.geometry.fundamental"), cv2.__version__)
    run.report.update(run.stages.run("matches", matches_key, [".stages/matches.npz"], find_matches))
    with np.load(run.out / ".stages" / "matches.npz") as saved:
        x1, x2, F, inliers = saved["x1"], saved["x2"], saved["F"], saved["inliers"]
    run.figure("matches_epipolar.png", matches_key,
               lambda path: figures.matches_epipolar_figure(path, left, right, x1, x2, F, inliers))
    return x1, x2, F, inliers


def _rectify(left, right, F, xi1, xi2, calib, camera, rectified: bool, report: dict) -> _Rectified:
    """The rectified pair: as given (calib.txt, or declared rectified), by the camera file's stereo
    calibration, or by Hartley's homographies from F; how, in report["rectification"]."""
    if calib is not None or (rectified and camera is None):  # Middlebury pairs come rectified
        geometry = None
        if calib is not None:  # calib.txt carries the rectified geometry
            geometry = {"focal": calib.focal, "baseline": calib.baseline, "cx": float(calib.cam0[0, 2]),
                        "cy": float(calib.cam0[1, 2]), "doffs": calib.doffs}
            report["rectification"] = "calibrated (calib.txt: input already rectified)"
        else:
            report["rectification"] = "none (input declared rectified)"
        return _Rectified(left, right, xi1, xi2, geometry, np.ones(left.shape[:2], bool))
    if camera is not None:
        rect_l, rect_r, p1, p2, geometry, inside = _rectify_with_camera(left, right, camera, xi1, xi2)
        report["rectification"] = "calibrated (camera file)"
        return _Rectified(rect_l, rect_r, p1, p2, geometry, inside)
    h, w = left.shape[:2]
    H1, H2 = hartley_rectification(F, xi1, xi2, (w, h))
    frame = fit_to_canvas(H1, H2, (w, h), xi1, xi2)
    size = (frame.width, frame.height)
    rect_l = cv2.warpPerspective(left, frame.H1, size, flags=cv2.INTER_LINEAR)
    rect_r = cv2.warpPerspective(right, frame.H2, size, flags=cv2.INTER_LINEAR)
    inside = cv2.warpPerspective(np.ones((h, w), np.uint8), frame.H1, size, flags=cv2.INTER_NEAREST) > 0
    report["rectification"] = "uncalibrated (Hartley)"
    report["H1"], report["H2"] = frame.H1.tolist(), frame.H2.tolist()
    p1, p2 = apply_homography(frame.H1, xi1), apply_homography(frame.H2, xi2)
    return _Rectified(rect_l, rect_r, p1, p2, None, inside)


def _disparity(config: StereoConfig, run: _Output, rect: _Rectified, calib, kind: str, left_path):
    """The disparity of the rectified left image (NaN outside it and in holes) and the seconds it took:
    searched in the range the matches (or calib.txt, or the config) give, found once per pair, range and code;
    written as PFM, as PNG when it fits, and as a figure."""
    report = run.report
    # disparities are not negative but with a camera file's rectification (never given with a calib.txt)
    dmin, num = search_range(config, calib, rect.p1[:, 0] - rect.p2[:, 0], nonnegative=kind != "camera")
    report["disparity_range"] = [dmin, dmin + num]
    report["match_disparities_px"], warnings = judge_matches(rect.p1, rect.p2, dmin, num, kind,
                                                             rect.geometry["doffs"] if rect.geometry else 0.0)
    for text in warnings:
        run.warn(text)
    cached = run.out / ".stages" / f"disparity_{config.method}.pfm"

    def find_disparity():
        try:
            disparity, extra = compute_disparity(rect.left, rect.right, config, dmin, num)
        except MemoryError:
            h, w = rect.left.shape[:2]
            raise InputError(f"{left_path}: not enough memory for {num} disparities of a {w}x{h} image; give a "
                             "smaller --num-disparities or smaller images") from None
        _save_pfm(cached, disparity)
        return extra

    disparity_key = digest(rect.left, rect.right, config.method, asdict(getattr(config, config.method)), dmin,
                           num, code_digest(f"{__package__}.{config.method}"), cv2.__version__)
    report.update(run.stages.run(cached.stem, disparity_key, [cached.relative_to(run.out)], find_disparity))
    disparity = _load_pfm(cached)
    disparity[~rect.inside] = np.nan  # canvas outside the warped left image has no disparity
    report["invalid_percent"] = float(100 * np.mean(~np.isfinite(disparity)))
    _save_pfm(run.out / "disparity.pfm", disparity)
    report["disparity_png"] = _write_disparity_png(run.out / "disparity.png", disparity)
    run.figure("disparity_view.png", digest(disparity, config.method), lambda path: figures.scalar_map_figure(
        path, disparity, f"disparity ({config.method})", "disparity (px)"))
    return disparity, run.stages.seconds(cached.stem)


def _depth_and_cloud(run: _Output, disparity, rect: _Rectified) -> None:
    """Metric depth (PFM and figure) and the coloured point cloud, from a disparity with known geometry."""
    geometry = rect.geometry
    depth = disparity_to_depth(disparity, geometry["focal"], geometry["baseline"], geometry["doffs"])
    _save_pfm(run.out / "depth.pfm", depth)
    run.figure("depth_view.png", digest(depth), lambda path: figures.scalar_map_figure(
        path, depth, "depth Z = f B / (d + doffs)", "depth (baseline units)", cmap="viridis_r"))
    finite = depth[np.isfinite(depth)]
    max_depth = float(20 * np.median(finite)) if finite.size else None

    def write_cloud(tmp):
        run.report["points"] = write_point_cloud(tmp, depth, rect.left, geometry["focal"], geometry["cx"],
                                                 geometry["cy"], max_depth)
    replace_whole(run.out / "cloud.ply", write_cloud)
    run.report["geometry"] = geometry


def _score(config: StereoConfig, run: _Output, disparity, gt, mask) -> None:
    """Scores against the ground-truth disparity (report["metrics"]) and the error map, when frames agree."""
    if run.report["rectification"].startswith("uncalibrated"):
        run.warn("ground truth is compared in the frame of the uncalibrated rectification; give --calib or "
                 "--rectified for pairs that are already rectified")
    if gt.shape != disparity.shape:
        run.warn(f"rectified frame {disparity.shape} differs from the ground truth {gt.shape}: not evaluated")
        return
    run.report["metrics"] = evaluate(disparity, gt, mask)
    bad2 = run.report["metrics"]["all"]["bad-2"]
    errors = error_map(disparity, gt)
    title = f"{config.method}: bad-2.0 = {bad2:.2f} % (all, holes count as bad)"
    run.figure("error_map.png", digest(errors, title),
               lambda path: figures.error_map_figure(path, errors, title))


def _write_disparity_png(path: Path, disparity) -> bool:
    """KITTI's 16-bit disparity PNG: round(256 d), 0 = hole (so d = 0, a point at infinity, reads as one too).
    Written when every disparity fits (0 <= d < 256); a calibrated rectification can give negative ones, which
    only the PFM holds. Returns whether it was written."""
    finite = np.isfinite(disparity)
    values = disparity[finite]
    if values.size and (values.min() < 0 or values.max() >= 65535 / 256):
        log.info("disparities outside [0, 256): %s not written (disparity.pfm holds them)", path.name)
        path.unlink(missing_ok=True)
        return False
    png = np.zeros(disparity.shape, np.uint16)
    png[finite] = np.round(256 * values).astype(np.uint16)
    replace_whole(path, lambda tmp: write_image(tmp, png))
    return True


def _bgr(image):
    return cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
