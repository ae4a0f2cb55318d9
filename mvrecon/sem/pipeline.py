"""The `mvrecon sem` run: SIFT for every image pair, affine verification, joint tilt solution, per-pair heights
from parallax merged by ICP, a height map on the reference grid, and the outputs (PLY, TIFF, PNG, report.json).

The seed paper (section 3) picks the image pairs with the most matches, computes each pair's 3D points by
parallel-projection photogrammetry from the tilt angles and the scale, and integrates the pairs' point sets with
ICP. Unknown tilts (common on real microscopes) come from the joint solution of all images (`factorization.py`),
which also supplies the frame the pair sets are merged into.
"""

import json
import logging
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import tifffile
from scipy.spatial import cKDTree

from ..errors import InputError
from ..features.sift import SiftConfig, extract_sift
from ..io.files import made_folder
from ..io.images import image_metadata, list_images, read_image, to_gray
from ..io.ply import write_ply
from ..io.record import digest
from ..matching.matcher import MatcherConfig, match_descriptors, prepare_descriptors
from ..progress import progress
from ..stereo.sgbm import SGBMConfig
from .affine import (
    AffineRansacConfig,
    affine_epipolar_error,
    ransac_affine_fundamental,
    tilt_axis_from_affine_fundamental,
)
from .dense import DenseMatchConfig, fill_nearest, refine_heights
from .factorization import build_tracks, solve_tilt_series
from .heightmap import grid_heights, height_accuracy, height_outliers, profile
from .icp import IcpConfig, icp
from .parallax import axis_vectors, heights_from_parallax
from .rectified import StereoConfig, pair_heights, stereo_heights

log = logging.getLogger("mvrecon.sem")
HEIGHT_SOURCES = ("dense", "stereo", "joint", "merged")
# A pair whose matches move beyond a common shift by less than this many times their matching noise shows no
# parallax: measured 0x to 2.8x for an image and its shifted, JPEG or noisy copy, 14.7x to 58.7x for the pairs of
# sem_tilt_small and of the Karido DSA and quartz series (docs/sem.md, "Checks on the input").
MIN_PARALLAX_RATIO = 6.0
# A pair below that ratio inside a series with parallax is one view twice (a copy under another name, re-encoded
# or noisy) unless its matches move with their neighbours: tilting moves nearby points alike (their heights are
# alike), two exposures of one view move each point by its own matching noise. Correlation of a match's motion
# across the axis with its 4 nearest neighbours' mean, measured: -0.06 to 0.06 for noisy, JPEG and shifted copies
# of sem_tilt_small and Karido images, 0.27 to 0.61 for rendered pairs 1 deg apart (ratio 2.5 to 4.9), 0.92 or more
# for the pairs of sem_tilt_small and of the Karido series (docs/sem.md, "Checks on the input").
MIN_MOTION_COHERENCE = 0.15
MIN_COHERENCE_MATCHES = 50  # fewer matches: the correlation's own noise (1 / sqrt(matches)) is too large to judge
# A given --axis farther than this from the matches' own estimate is warned about: that estimate (median over
# the pairs of the affine-F axis) is within 0.2 deg of the true or jointly estimated axis on the good series
# (single pairs within 1.8 deg); an axis 5 deg off raises sem_tilt_small's height error from 0.61 to 1.00 %.
AXIS_TOLERANCE_DEG = 5.0


@dataclass(frozen=True)
class SemConfig:
    """tilts_deg: one known tilt per image, or None to estimate them (>= 3 images). axis_deg: in-plane tilt axis
    (deg from image +x towards +y; 90 = vertical), None to estimate. pixel_size_um: size of an input pixel; None
    reports heights in input pixels. max_size: shrink images so the long side is at most this (None: full size).
    reference: image whose grid the height map uses (None: the tilt closest to 0, or the middle image when tilts
    are estimated). pairs: how many best-matched pairs give per-pair point sets (the paper uses 2).
    icp_method: kdtree | brute | open3d-point | open3d-plane. height_source: "dense" (default) refines the
    gridded joint points at every pixel by least-squares matching of all images (`dense.py`; the sparse points
    alone are too few and too noisy for 1% accuracy), "stereo" refines the same way a start made by semi-global
    matching of the rectified pairs (reference, other view) where the pairs agree (`rectified.py`), "joint"
    grids the points of the joint adjustment (every observation of a track), "merged" grids the ICP-merged union
    of the joint points and the pair point sets (the paper's integration). densify: SGBM on the rectified pair
    of the reference and the image tilted farthest from it, replacing the map where it matched. profile:
    (x0, y0, x1, y1) in input pixels, None = the line across the tilt axis through the image centre."""

    tilts_deg: tuple | None = None
    axis_deg: float | None = None
    pixel_size_um: float | None = None
    max_size: int | None = None
    reference: int | None = None
    pairs: int = 2
    icp_method: str = "kdtree"
    height_source: str = "dense"
    densify: bool = False
    profile: tuple | None = None
    sift: SiftConfig = field(default_factory=lambda: SiftConfig(max_num_features=8192))
    matcher: MatcherConfig = field(default_factory=MatcherConfig)
    ransac: AffineRansacConfig = field(default_factory=AffineRansacConfig)
    icp: IcpConfig = field(default_factory=IcpConfig)
    densify_matcher: SGBMConfig = field(default_factory=lambda: SGBMConfig(block_size=5))
    dense_match: DenseMatchConfig = field(default_factory=DenseMatchConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)

    def validate(self) -> None:
        """An InputError for a `max_size` too small to find features in (below 16 pixels)."""
        if self.max_size is not None and self.max_size < 16:
            raise InputError(f"--max-size {self.max_size}: must be at least 16 pixels")


def parse_length_um(text: str) -> float:
    """'0.05um', '50nm', '0.05 µm', '1e-3mm' or a bare number (micrometres) -> micrometres."""
    m = re.fullmatch(r"\s*([0-9.eE+-]+)\s*(nm|um|µm|mm)?\s*", str(text))
    try:
        value = float(m.group(1)) if m else float("nan")
    except ValueError:
        value = float("nan")
    if not m or not np.isfinite(value) or value <= 0:
        raise ValueError(f"pixel size must be a positive length like 0.05um or 50nm, got {text!r}")
    return value * {"nm": 1e-3, "mm": 1e3}.get(m.group(2) or "um", 1.0)


def _natural_key(name: str):
    """Names compared with their signed numbers as numbers: tilt_-10.0 < tilt_-5.0 < tilt_+0.0 < tilt_+10.0."""
    parts = re.split(r"([+-]?\d+(?:\.\d+)?)", name)
    return [(0, float(t), "") if i % 2 else (1, 0.0, t.lower()) for i, t in enumerate(parts)]


def resolve_images(inputs: list[Path | str]) -> list[Path]:
    """Image files from a list of files and/or folders (a folder gives its images in natural name order, signed
    numbers compared as numbers)."""
    paths = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            names, _ = list_images(p)
            paths += [p / n for n in sorted(names, key=_natural_key)]
        elif p.is_file():
            paths.append(p)
        else:
            raise InputError(f"{p}: no such file or folder")
    return paths


def _check_distinct_files(paths) -> None:
    """Refuse one file given twice (also through a link): two copies of one view have no parallax, and the run
    would turn matching noise into a height map."""
    seen = {}
    for p in paths:
        st = p.stat()
        key = (st.st_dev, st.st_ino)
        if key in seen:
            raise InputError(f"{p}: the same file as {seen[key]} (given twice); a tilt series needs one image per "
                             "tilt, and one view twice has no parallax")
        seen[key] = p


def _load(paths, max_size):
    """Grey images at working size and the downscale factor; two files with identical pixels are refused."""
    images, seen = [], {}
    for p in paths:
        image = read_image(p)
        key = digest(image)
        if key in seen:
            raise InputError(f"{p}: identical pixels to {seen[key]}; a tilt series needs one image per tilt, and "
                             "one view twice has no parallax")
        seen[key] = p
        images.append(to_gray(image))
    odd = next((k for k, im in enumerate(images) if im.shape != images[0].shape), None)
    if odd is not None:
        (h0, w0), (h1, w1) = images[0].shape, images[odd].shape
        raise InputError(f"{paths[odd]}: is {w1}x{h1} but {paths[0]} is {w0}x{h0}; the images of a tilt series "
                         "must share one size")
    h, w = images[0].shape
    factor = min(1.0, max_size / max(h, w)) if max_size else 1.0
    if factor < 1.0:
        size = (max(1, round(w * factor)), max(1, round(h * factor)))
        images = [cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in images]
        factor = images[0].shape[1] / w
    return images, factor


def _match_all(images, config: SemConfig):
    """Keypoints (OpenCV pixel convention) per image and the affine-verified matches of every pair, each verified
    pair with its affine-F axis and parallax measure (`_parallax`)."""
    keypoints, descriptors = [], []
    for im in progress(images, desc="SIFT", unit="image"):
        kp, desc = extract_sift(im, config.sift)
        keypoints.append(kp[:, :2].astype(float) - 0.5)  # COLMAP pixel centres -> OpenCV
        descriptors.append(prepare_descriptors(desc))
    pairs = {}
    pair_list = [(i, j) for i in range(len(images)) for j in range(i + 1, len(images))]
    for i, j in progress(pair_list, desc="match + affine F", unit="pair"):
        m = match_descriptors(descriptors[i], descriptors[j], config.matcher)
        F, inliers = ransac_affine_fundamental(keypoints[i][m[:, 0]], keypoints[j][m[:, 1]], config.ransac)
        pairs[(i, j)] = {"matches": int(len(m)), "verified": int(inliers.sum()), "F": F, "index": m[inliers]}
        if F is not None:
            idx = m[inliers]
            spread, noise = _parallax(keypoints[i][idx[:, 0]], keypoints[j][idx[:, 1]], F)
            pairs[(i, j)].update(axis_deg=tilt_axis_from_affine_fundamental(F), parallax_px=spread, noise_px=noise,
                                 parallax_ratio=spread / noise if noise > 0 else (np.inf if spread > 0 else 0.0))
    return keypoints, pairs


def _parallax(x1, x2, F) -> tuple[float, float]:
    """(median motion beyond the pair's common shift, median distance to the affine F), px. Tilting moves points
    by their height and position across the axis; two exposures of one view move all points alike and leave
    only the matching noise that the second figure measures."""
    d = x2 - x1
    spread = float(np.median(np.linalg.norm(d - np.median(d, axis=0), axis=1)))
    return spread, float(np.median(affine_epipolar_error(F, x1, x2)))


def _motion_coherence(x1, x2, axis_deg: float, neighbours: int = 4, min_distance: float = 2.0) -> float:
    """Correlation of each match's motion across the tilt axis (beyond the common shift) with the mean motion of
    its `neighbours` nearest matches at least `min_distance` px away in the first image: nearer ones are the same
    keypoint at another orientation, with the same localisation error. Motions beyond 4 sigma (wrong matches) are
    clipped; a pair that moves all alike (a shifted copy) gives 0."""
    _, nvec = axis_vectors(axis_deg)
    r = (x2 - x1) @ nvec
    r = r - np.median(r)
    sigma = 1.4826 * np.median(np.abs(r))
    r = np.clip(r, -4 * sigma, 4 * sigma)
    dist, index = cKDTree(x1).query(x1, k=min(len(x1), neighbours + 8))
    use = (dist >= min_distance) & (np.cumsum(dist >= min_distance, axis=1) <= neighbours)
    full = use.sum(axis=1) == neighbours
    around = np.where(use, r[index], 0.0).sum(axis=1)[full] / neighbours
    norm = np.sqrt(np.sum(r[full] ** 2) * np.sum(around ** 2))
    return float(np.sum(r[full] * around) / norm) if norm > 0 else 0.0


def _check_pairs_have_parallax(paths, keypoints, pairs, tilts_deg) -> None:
    """Refuse a pair without parallax inside a series whose other pairs have it: one view saved twice (under two
    names, re-encoded or noisy). Given tilts then put one view at two tilts and bend the joint adjustment (RMS
    0.135 -> 0.247 px on sem_tilt_small); estimated ones rest on one view fewer than the user thinks (two, in a
    series of three: the tilt step and the height scale cannot be told apart). A pair given equal tilts is a
    repeated exposure the user declared, and passes (the pair step skips it)."""
    tilted = [p for p, v in pairs.items() if v.get("parallax_ratio", 0.0) >= MIN_PARALLAX_RATIO]
    axis = _median_axis([pairs[p]["axis_deg"] for p in tilted], pairs[tilted[0]]["axis_deg"])
    for (i, j), v in pairs.items():
        if v.get("parallax_ratio", np.inf) >= MIN_PARALLAX_RATIO or len(v["index"]) < MIN_COHERENCE_MATCHES:
            continue
        if tilts_deg is not None and abs(np.sin(np.radians(tilts_deg[j] - tilts_deg[i]))) < 1e-9:
            continue
        idx = v["index"]
        v["coherence"] = _motion_coherence(keypoints[i][idx[:, 0]], keypoints[j][idx[:, 1]], axis)
        if v["coherence"] >= MIN_MOTION_COHERENCE:
            continue  # a small tilt step: little parallax, but it follows the relief
        if tilts_deg is None:
            given, remedy = ", although the series' other pairs show it", "remove one"
        else:
            given = f" although --tilts puts them {abs(tilts_deg[j] - tilts_deg[i]):g} deg apart"
            remedy = "remove one, or give a repeated exposure the same tilt twice"
        coherence = round(v["coherence"], 2) + 0.0  # no "-0.00"
        raise InputError(f"{paths[j]}: no parallax against {paths[i]}{given}: their matches move "
                         f"{v['parallax_px']:.3f} px beyond a common shift ({v['parallax_ratio']:.1f}x the matching "
                         f"noise), each on its own (coherence {coherence:.2f} with its neighbours; tilted views give "
                         f"{MIN_MOTION_COHERENCE:g} or more); the same view twice? {remedy}")


def _axis_difference(a: float, b: float) -> float:
    """Angle between two axis directions in degrees (0..90): axes are lines, 179 and 1 deg are 2 deg apart."""
    return float(abs((a - b + 90.0) % 180.0 - 90.0))


def _median_axis(axes, around: float) -> float:
    """Median of axis angles (deg, modulo 180), each taken within 90 deg of `around`."""
    return float((around + np.median([(a - around + 90.0) % 180.0 - 90.0 for a in axes])) % 180.0)


def _check_tilts_in_range(tilts_deg) -> None:
    """Refuse a given tilt of 90 deg or more either way: the specimen's surface is then edge-on or faces away from
    the detector, and under parallel projection tilts t and t + 180 deg give one view mirrored, with no parallax
    between them (`--tilts=-5,175,5` ran as three tilts)."""
    for x in tilts_deg:
        if not -90.0 < x < 90.0:
            raise InputError(f"--tilts {','.join(f'{t:g}' for t in tilts_deg)}: {x:g} deg is not between -90 and 90 "
                             "(at 90 the surface is edge-on, beyond it faces away; tilts 180 deg apart give one view "
                             "mirrored, without parallax); give each image's stage tilt")


def _check_tilts_differ(tilts_deg) -> None:
    """Refuse given tilts that are all the same (modulo 180 deg): no image pair would have parallax."""
    t = np.radians(np.asarray(tilts_deg, dtype=float))
    if not (np.abs(np.sin(t[:, None] - t[None, :])) >= 1e-9).any():
        raise InputError(f"--tilts {','.join(f'{x:g}' for x in tilts_deg)}: no two tilts differ, so the image pairs "
                         "have no parallax (equal tilts) to give heights")


def _check_ground_truth_size(gt_height, first) -> None:
    """Ground truth must lie on the input images' grid (it is resampled with them under --max-size)."""
    meta = image_metadata(first)
    if np.shape(gt_height) != (meta.height, meta.width):
        rows, cols = np.shape(gt_height)
        raise InputError(f"--gt: a {cols}x{rows} height map for {meta.width}x{meta.height} images ({first}); "
                         "it must lie on the input images' grid")


def _reference(config: SemConfig, n: int) -> int:
    if config.reference is not None:
        if not 0 <= config.reference < n:
            raise InputError(f"--reference {config.reference}: must be an image index in 0..{n - 1}")
        return config.reference
    if config.tilts_deg is not None:
        return int(np.argmin(np.abs(np.asarray(config.tilts_deg, float))))
    return n // 2


def _cell_average(points: np.ndarray, shape) -> np.ndarray:
    """One point per grid cell (the mean of those falling in it): near-duplicates from several point sets would
    otherwise make slivers in the triangulation and turn their small disagreements into spikes."""
    h, w = shape
    col = np.clip(np.round(points[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.round(points[:, 1]).astype(int), 0, h - 1)
    cell = row * w + col
    uniq, inv, counts = np.unique(cell, return_inverse=True, return_counts=True)
    out = np.zeros((len(uniq), 3))
    np.add.at(out, inv, points)
    return out / counts[:, None]


def run_sem(image_paths: list[Path], out_dir: Path | str, config: SemConfig = SemConfig(),
            gt_height: np.ndarray | None = None) -> dict:
    """Run the whole SEM pipeline and write the outputs to `out_dir`; returns the report (also report.json).
    gt_height: a ground-truth height map on the reference image's grid at input size, in the output's units
    (um with a pixel size, else input pixels), scored by `heightmap.height_accuracy` into the report's
    "accuracy", with every map made on the way."""
    timings, t0 = {}, time.perf_counter()
    paths = [Path(p) for p in image_paths]
    n = len(paths)
    if n < 2:
        raise InputError(f"{paths[0] if paths else 'IMAGES'}: a tilt series needs at least 2 images, got {n}")
    if config.tilts_deg is not None and len(config.tilts_deg) != n:
        raise InputError(f"--tilts: {len(config.tilts_deg)} angles given for {n} images; give one per image")
    if config.height_source not in HEIGHT_SOURCES:
        raise InputError(f"--height-source {config.height_source}: expected one of {', '.join(HEIGHT_SOURCES)}")
    if config.tilts_deg is None and n < 3:
        raise InputError(f"{paths[0]}: estimating tilts needs at least 3 images (got {n}); give --tilts")
    if config.tilts_deg is not None:
        _check_tilts_in_range(config.tilts_deg)
        _check_tilts_differ(config.tilts_deg)
    _check_distinct_files(paths)
    if gt_height is not None:
        _check_ground_truth_size(gt_height, paths[0])
    ref = _reference(config, n)
    # a failed or interrupted run leaves no folder it made (nothing in it is reused)
    with made_folder(out_dir) as out:
        return _run(paths, out, config, ref, timings, t0, gt_height)


@dataclass
class _Joint:
    """The joint solution of all images (`factorization.solve_tilt_series`) and the checks of its axis."""

    obs: object  # the tracks it adjusted (`factorization.build_tracks`)
    solution: object  # tilts, axis, drifts, points, RMS
    axis_guess: float  # the best-matched pair's affine-F axis: the adjustment's start
    axis_from_pairs: float  # the median affine-F axis of the pairs with parallax
    axis_check: dict | None  # a given --axis against axis_from_pairs (`_check_given_axis`)


@dataclass
class _PointSets:
    """The joint points and their ICP-merged union with the per-pair point sets, height outliers removed."""

    anchor: np.ndarray  # the joint points, centred working pixels
    anchor_outliers: np.ndarray  # per joint point: removed as a height outlier
    merged: np.ndarray
    merged_outliers: np.ndarray
    pair_reports: list  # per pair point set: its images, points, outliers and ICP figures


def _run(paths, out: Path, config: SemConfig, ref: int, timings: dict, t0: float, gt_height) -> dict:
    """run_sem after its argument checks, into the existing folder `out`."""
    report_warnings = []

    def warn(text):
        """A result that is likely wrong says so: in the log and in report.json's "warnings"."""
        log.warning("warning: %s", text)
        report_warnings.append(text)

    images, factor = _load(paths, config.max_size)
    h, w = images[0].shape
    center = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    timings["load_s"] = time.perf_counter() - t0

    t = time.perf_counter()
    keypoints, pairs = _match_all(images, config)
    timings["match_s"] = time.perf_counter() - t
    ranked = _ranked_pairs(paths, keypoints, pairs, config.tilts_deg)

    t = time.perf_counter()
    joint = _solve_joint(paths, keypoints, pairs, ranked, center, ref, config, warn)
    timings["joint_s"] = time.perf_counter() - t

    t = time.perf_counter()
    sets = _merge_point_sets(paths, keypoints, pairs, ranked, joint.solution, center, config)
    timings["pairs_icp_s"] = time.perf_counter() - t

    # height map on the reference grid (working resolution); with ground truth every map on the way is scored
    t = time.perf_counter()
    height, maps, dense_report, stereo_report = _height_maps(
        paths, images, pairs, joint.solution, sets, center, ref, config, gt_height is not None, timings)
    timings["heightmap_s"] = time.perf_counter() - t

    unit = "um" if config.pixel_size_um else "px"
    to_unit = (config.pixel_size_um or 1.0) / factor  # working pixels -> micrometres (or input pixels)
    height_u = height * to_unit
    line = _profile_line(config.profile, factor, joint.solution.axis_deg, center, (h, w))
    _write_outputs(out, images[ref], height_u, sets.merged * to_unit, sets.merged, center, line, unit,
                   to_unit)
    accuracy = None
    if gt_height is not None:
        truth = _to_working_grid(gt_height, (h, w))
        accuracy = {"height_source": config.height_source, "units": unit, **height_accuracy(height_u, truth),
                    "maps": {name: height_accuracy(m * to_unit, truth) for name, m in maps.items()}}
    timings["total_s"] = time.perf_counter() - t0

    report = {
        "images": [str(p) for p in paths],
        "reference": ref,
        "working_size": [w, h],
        "downscale": factor,
        "pixel_size_um": config.pixel_size_um,
        "working_pixel_size": to_unit,
        "units": unit,
        **_tilt_report(config, joint),
        "warnings": report_warnings,
        "keypoints": [int(len(k)) for k in keypoints],
        "pairs": [{"pair": [i, j], "matches": v["matches"], "verified": v["verified"],
                   **{k: v[k] for k in ("axis_deg", "parallax_px", "noise_px", "coherence") if k in v}}
                  for (i, j), v in pairs.items()],
        **_points_report(joint, sets),
        "height_map": _height_map_report(height_u, line, factor),
        "dense": dense_report,
        "stereo": stereo_report,
        "accuracy": accuracy,
        "config": {k: v for k, v in asdict(config).items()
                   if k in ("pairs", "icp_method", "height_source", "densify", "max_size", "reference")},
        "timings": timings,
    }
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return report


def _ranked_pairs(paths, keypoints, pairs, tilts_deg) -> list[tuple[int, int]]:
    """The pairs with verified matches, the most first. A series whose best pair shows no parallax (below
    MIN_PARALLAX_RATIO), or with one view twice (`_check_pairs_have_parallax`), is refused."""
    ranked = sorted((p for p in pairs if pairs[p]["verified"] > 0), key=lambda p: -pairs[p]["verified"])
    if not ranked:
        raise InputError(f"{paths[0].parent}: no image pair has verified matches "
                         "(" + ", ".join(f"{i}-{j}: {v['matches']} raw" for (i, j), v in pairs.items()) + ")")
    log.info("verified matches per pair: %s",
             ", ".join(f"{i}-{j}: {pairs[(i, j)]['verified']}/{pairs[(i, j)]['matches']}" for i, j in pairs))
    most = max(ranked, key=lambda p: pairs[p]["parallax_ratio"])
    if pairs[most]["parallax_ratio"] < MIN_PARALLAX_RATIO:
        (i, j), v = most, pairs[most]
        raise InputError(f"{paths[i]}: the matches show no parallax: the largest, with {paths[j].name}, is "
                         f"{v['parallax_px']:.3f} px beyond a common shift, {v['parallax_ratio']:.1f}x the "
                         f"matching noise ({v['noise_px']:.3f} px; tilted views give "
                         f"{MIN_PARALLAX_RATIO:g}x or more); are these images of one tilt?")
    _check_pairs_have_parallax(paths, keypoints, pairs, tilts_deg)
    return ranked


def _solve_joint(paths, keypoints, pairs, ranked, center, ref: int, config: SemConfig, warn) -> _Joint:
    """The joint solution of all images: tilts (given or estimated), axis, drifts and points from the tracks
    of the verified matches; a given --axis is compared with the pairs' own estimate (`_check_given_axis`)."""
    n = len(paths)
    axis_guess = tilt_axis_from_affine_fundamental(pairs[ranked[0]]["F"])
    obs = build_tracks({p: pairs[p]["index"] for p in ranked}, [k - center for k in keypoints])
    try:
        solution = solve_tilt_series(obs, n, ref, tilts_deg=config.tilts_deg, axis_deg=config.axis_deg,
                                     axis_guess_deg=axis_guess)
    except ValueError as exc:
        raise InputError(f"{paths[0].parent}: {exc}") from None
    log.info("tilts %s deg about the axis at %.2f deg; joint adjustment RMS %.3f px over %d observations",
             ", ".join(f"{x:.3f}" for x in solution.tilts_deg), solution.axis_deg, solution.rms_px,
             solution.observations_used)
    axis_pairs = [p for p in ranked if pairs[p]["parallax_ratio"] >= MIN_PARALLAX_RATIO]
    axis_from_pairs = _median_axis([pairs[p]["axis_deg"] for p in axis_pairs], axis_guess)
    axis_check = None
    if config.axis_deg is not None:
        axis_check = _check_given_axis(config, obs, n, ref, solution, axis_from_pairs, len(axis_pairs), warn)
    return _Joint(obs, solution, axis_guess, axis_from_pairs, axis_check)


def _merge_point_sets(paths, keypoints, pairs, ranked, solution, center, config: SemConfig) -> _PointSets:
    """The paper's step: point sets of the best-matched pairs from their parallax, each merged by ICP into the
    frame of the joint points."""
    tilts, axis = solution.tilts_deg, solution.axis_deg
    anchor = solution.points[np.isfinite(solution.points).all(axis=1)]
    anchor_outliers = height_outliers(anchor)
    anchor = anchor[~anchor_outliers]
    merged, pair_reports = [anchor], []
    # pairs of equal tilts (a repeated exposure in a series) have no parallax to give heights: the next do
    with_parallax = [(i, j) for i, j in ranked if abs(np.sin(np.radians(tilts[j] - tilts[i]))) >= 1e-9]
    for i, j in with_parallax[:max(1, config.pairs)]:
        idx = pairs[(i, j)]["index"]
        cloud = heights_from_parallax(keypoints[i][idx[:, 0]], keypoints[j][idx[:, 1]], tilts[i], tilts[j],
                                      axis, center)
        outliers = height_outliers(cloud)
        cloud = cloud[~outliers]
        init = np.eye(4)
        init[:3, 3] = np.median(anchor, axis=0) - np.median(cloud, axis=0)
        result = icp(cloud, anchor, config.icp_method, config.icp, init)
        merged.append(result.apply(cloud))
        pair_reports.append({"pair": [i, j], "images": [paths[i].name, paths[j].name],
                             "points": int(len(cloud)), "height_outliers": int(outliers.sum()),
                             "icp": _icp_report(result)})
    merged = np.vstack(merged)
    merged_outliers = height_outliers(merged)
    return _PointSets(anchor, anchor_outliers, merged[~merged_outliers], merged_outliers, pair_reports)


def _icp_report(result) -> dict:
    return {"method": result.method, "iterations": result.iterations, "rms_px": result.rms,
            "pairs": result.pairs, "seconds": result.seconds, "translation_px": result.matrix[:3, 3].tolist()}


def _gridded(points: np.ndarray, center, shape) -> np.ndarray:
    """A height map on the working grid from centred points (one per cell, `_cell_average`)."""
    cells = _cell_average(np.column_stack([points[:, :2] + center, points[:, 2]]), shape)
    return grid_heights(cells[:, :2], cells[:, 2], shape)


def _height_maps(paths, images, pairs, solution, sets: _PointSets, center, ref: int, config: SemConfig,
                 scored: bool, timings: dict):
    """(height map of config.height_source on the working grid, every map made on the way by name, dense
    report, stereo report). "dense" and "stereo" refine a start at every pixel; `scored` (ground truth given)
    also grids the sparse source not used, so that both are scored."""
    tilts, axis = solution.tilts_deg, solution.axis_deg
    shape = images[0].shape
    points = {"joint": sets.anchor, "merged": sets.merged}
    sparse = "merged" if config.height_source == "merged" else "joint"
    maps = {sparse: _gridded(points[sparse], center, shape)}
    if not np.isfinite(maps[sparse]).any():
        raise InputError(f"{paths[0].parent}: only {len(points[sparse])} 3D points "
                         "survived the outlier tests; too few for a height map")
    if scored:
        other = "joint" if sparse == "merged" else "merged"
        maps[other] = _gridded(points[other], center, shape)
    height = maps[sparse]
    dense_report = stereo_report = None
    if config.height_source in ("dense", "stereo"):
        start = fill_nearest(height)
        if config.height_source == "stereo":
            t_stereo = time.perf_counter()
            span = (np.percentile(sets.anchor[:, 2], 1), np.percentile(sets.anchor[:, 2], 99))
            matched, stereo_report = stereo_heights(images, tilts, axis, solution.shifts, ref, span,
                                                    config.stereo)
            maps["stereo_matching"] = matched
            start = np.where(np.isfinite(matched), matched, start)
            timings["stereo_s"] = time.perf_counter() - t_stereo
        height = maps[config.height_source] = refine_heights(images, tilts, axis, solution.shifts, ref, start,
                                                             config.dense_match)
    if config.densify:
        height, dense_report = _densify(images, ref, tilts, axis, solution, pairs, height,
                                        config.densify_matcher)
        maps["densify"] = height
    return height, maps, dense_report, stereo_report


def _tilt_report(config: SemConfig, joint: _Joint) -> dict:
    tilts = joint.solution.tilts_deg
    return {
        "tilts_deg": [float(x) for x in tilts],
        "tilts_given": config.tilts_deg is not None,
        "tilt_steps_deg": [float(x) for x in np.diff(tilts)],
        "axis_deg": joint.solution.axis_deg,
        "axis_given": config.axis_deg is not None,
        "axis_from_affine_F_deg": joint.axis_guess,
        "axis_from_pairs_deg": joint.axis_from_pairs,
        "axis_check": joint.axis_check,
    }


def _points_report(joint: _Joint, sets: _PointSets) -> dict:
    solution = joint.solution
    return {
        "joint": {"rms_px": solution.rms_px, "observations": solution.observations_used,
                  "tracks": int(joint.obs.num_points), "points": int(len(sets.anchor)),
                  "drift_px": solution.shifts.tolist()},
        "pair_point_sets": sets.pair_reports,
        "merged_points": int(len(sets.merged)),
        "height_outliers": {"joint": int(sets.anchor_outliers.sum()),
                            "merged": int(sets.merged_outliers.sum())},
    }


def _height_map_report(height_u: np.ndarray, line, factor: float) -> dict:
    finite = np.isfinite(height_u)
    return {"valid_fraction": float(finite.mean()),
            "min": float(np.nanmin(height_u)) if finite.any() else None,
            "max": float(np.nanmax(height_u)) if finite.any() else None,
            "profile_line_px": [float(v / factor) for v in line]}


def _to_working_grid(height, shape) -> np.ndarray:
    """A map of the input grid resampled to the working grid (area average; NaN where any input pixel is NaN)."""
    height = np.asarray(height, np.float32)
    if height.shape == tuple(shape):
        return height
    size = (shape[1], shape[0])
    values = cv2.resize(np.nan_to_num(height, nan=0.0), size, interpolation=cv2.INTER_AREA)
    known = cv2.resize(np.isfinite(height).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return np.where(known > 0.999, values / np.maximum(known, 1e-6), np.nan)


def _check_given_axis(config: SemConfig, obs, n: int, ref: int, solution, axis_from_pairs: float,
                      pairs_used: int, warn) -> dict:
    """Compare a given --axis with the matches' own estimate; beyond AXIS_TOLERANCE_DEG, fit the axis freely too
    and warn with both adjustment RMS figures (an axis 90 deg off: 1.12 px against 0.13 px, heights 26 % off).

    A warning, not a refusal: the estimate assumes a pure eucentric tilt, and a stage that also turns the image
    in its plane bends it, where the user's axis may be the right one."""
    off = _axis_difference(config.axis_deg, axis_from_pairs)
    check = {"given_deg": config.axis_deg, "from_pairs_deg": axis_from_pairs, "pairs_used": pairs_used,
             "difference_deg": off, "tolerance_deg": AXIS_TOLERANCE_DEG, "rms_given_px": solution.rms_px}
    if off <= AXIS_TOLERANCE_DEG:
        return check
    try:
        free = solve_tilt_series(obs, n, ref, tilts_deg=config.tilts_deg, axis_deg=None,
                                 axis_guess_deg=axis_from_pairs)
    except ValueError:
        free = None
    if free is not None:
        check.update(rms_axis_estimated_px=free.rms_px, axis_estimated_deg=free.axis_deg)
    fit = (f"; the joint adjustment's RMS is {solution.rms_px:.3f} px with the given axis and {free.rms_px:.3f} px "
           f"with the axis estimated ({free.axis_deg:.1f} deg)" if free is not None else "")
    warn(f"--axis {config.axis_deg:g} deg contradicts the matches, which put the tilt axis at "
         f"{axis_from_pairs:.1f} deg (median of {pairs_used} image pairs), {off:.1f} deg away (more than "
         f"{AXIS_TOLERANCE_DEG:g}){fit}: the heights are likely wrong; check --axis (y = 90, x = 0) or leave it out "
         "to estimate it")
    return check


def _densify(images, ref, tilts, axis, solution, pairs, sparse_height, matcher: SGBMConfig):
    """SGBM heights of the rectified pair (reference, image tilted farthest from it), holes filled from the map
    made so far."""
    candidates = [j for j in range(len(images)) if j != ref and pairs[tuple(sorted((ref, j)))]["verified"] > 0]
    if not candidates:
        return sparse_height, {"used": False, "reason": "the reference image has no verified pair"}
    other = max(candidates, key=lambda j: abs(tilts[j] - tilts[ref]))
    z = solution.points[np.isfinite(solution.points).all(axis=1), 2]
    dense = pair_heights(images[ref], images[other], tilts[ref], tilts[other], axis, solution.shifts[ref],
                         solution.shifts[other], (np.percentile(z, 1), np.percentile(z, 99)), matcher,
                         margin_px=8.0)
    both = np.isfinite(dense) & np.isfinite(sparse_height)
    diff = float(np.median(np.abs(dense[both] - sparse_height[both]))) if both.any() else float("nan")
    filled = np.where(np.isfinite(dense), dense, sparse_height)
    return filled, {"used": True, "pair": [ref, other], "dense_fraction": float(np.isfinite(dense).mean()),
                    "median_abs_difference_to_sparse_px": diff}


def _profile_line(spec, factor, axis, center, shape):
    """(x0, y0, x1, y1) in working pixels: the given line (input pixels), or across the axis through the centre."""
    if spec is not None:
        return tuple(float(v) * factor for v in spec)
    h, w = shape
    _, nvec = axis_vectors(axis)
    half = 0.45 * min(w / max(abs(nvec[0]), 1e-9), h / max(abs(nvec[1]), 1e-9), np.hypot(w, h))
    x0, y0 = center - half * nvec
    x1, y1 = center + half * nvec
    return (float(x0), float(y0), float(x1), float(y1))


def _write_outputs(out: Path, ref_image, height, merged_u, merged_px, center, line, unit, to_unit):
    import matplotlib  # noqa: PLC0415 - figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 - figures only
    h, w = height.shape
    tifffile.imwrite(out / "height.tif", height.astype(np.float32))
    # coloured PLY of the merged points (y flipped so the cloud is right-handed with heights up)
    col = np.clip(np.round(merged_px[:, 0] + center[0]).astype(int), 0, w - 1)
    row = np.clip(np.round(merged_px[:, 1] + center[1]).astype(int), 0, h - 1)
    grey = ref_image[row, col]
    write_ply(out / "points.ply", np.column_stack([merged_u[:, 0], -merged_u[:, 1], merged_u[:, 2]]),
              colors=np.repeat(grey[:, None], 3, axis=1))
    step = max(1, int(np.ceil(np.sqrt(h * w / 300_000))))
    gy, gx = np.mgrid[0:h:step, 0:w:step]
    hz = height[gy, gx]
    ok = np.isfinite(hz)
    surface = np.column_stack([(gx[ok] - center[0]) * to_unit, -(gy[ok] - center[1]) * to_unit, hz[ok]])
    write_ply(out / "surface.ply", surface, colors=np.repeat(ref_image[gy, gx][ok][:, None], 3, axis=1))

    finite = np.isfinite(height)
    lo, hi = (np.nanpercentile(height, [1, 99]) if finite.any() else (0.0, 1.0))
    fig, ax = plt.subplots(figsize=(7, 7 * h / w + 0.5), dpi=120)
    im = ax.imshow(np.ma.masked_invalid(height), cmap="viridis", vmin=lo, vmax=hi)
    ax.plot([line[0], line[2]], [line[1], line[3]], "r-", lw=1)
    ax.set_title(f"height ({unit}), reference grid; red: profile line")
    fig.colorbar(im, ax=ax, label=f"height ({unit})", shrink=0.8)
    fig.tight_layout()
    fig.savefig(out / "height.png")
    plt.close(fig)

    dist, values = profile(height, line[:2], line[2:])
    fig, ax = plt.subplots(figsize=(8, 3), dpi=120)
    ax.plot(dist * to_unit, values, "k-", lw=1)
    ax.set_xlabel(f"distance along the line ({unit})")
    ax.set_ylabel(f"height ({unit})")
    ax.set_title("height profile")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "profile.png")
    plt.close(fig)
